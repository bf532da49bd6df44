// The set-up view: wires the live WebSocket to the panels. See docs/setup-view.md.

import { getJson } from "./api.js";
import { Cameras, setToolNames } from "./cameras.js";
import { Capture } from "./capture.js";
import { Controls } from "./controls.js";
import { Health, serverFaults } from "./health.js";
import { Live } from "./live.js";
import { Robot } from "./robot.js";
import { Scene3D } from "./scene3d.js";
import { SystemPanel } from "./system.js";

const $ = (id) => document.getElementById(id);

const state = {
  status: null,
  statusCount: 0,
  positions: 0,
  session: null,
  rigKey: null,
  rigNote: "",
};

const fpsSelect = $("preview-fps");
const zoomSelect = $("zoom-px");
const tintBox = $("threshold-view");

const cameras = new Cameras($("cameras"), () => ({ thresholdView: tintBox.checked, fps: Number(fpsSelect.value) }));
const health = new Health();
const robot = new Robot();
const system = new SystemPanel();
const scene = new Scene3D($("scene"), $("scene-info"), $("scene-frame"));
const capture = new Capture($("capture-btn"), $("capture-msg"));
const controls = new Controls((s) => {
  state.session = s;
  robot.setSession(s);
  system.session = s;
  system.buttons();
});

function refreshFaults() {
  if (state.status) health.faults(state.status, cameras.summary());
}

/** Camera poses and the workspace box (`GET /api/scene`), fetched again when the active
 *  parameter set changes. */
async function loadScene(st) {
  const p = st.params || {};
  const key = `${p.loaded}|${p.rig_id}|${p.created_unix_s}|${p.swaps}`;
  if (key === state.rigKey) return;
  state.rigKey = key;
  try {
    scene.setScene(await getJson("/api/scene"));
  } catch (e) {
    state.rigKey = null; // try again with the next status report
    $("scene-info").textContent = `camera poses unavailable: ${e.message}`;
  }
}

function onStatus(msg) {
  const st = msg.status && typeof msg.status === "object" ? msg.status : msg;
  state.status = st;
  state.statusCount += 1;
  cameras.ensure(((st.source || {}).cameras || []).length);
  health.leds(st);
  health.update(st);
  robot.update(st, state.session);
  system.update(st, state.session);
  if (st.tuning && typeof st.tuning === "object") controls.showLive(st.tuning);
  if (st.threshold_suggestion) controls.showStartupSuggestion(st.threshold_suggestion);
  refreshFaults();
  loadScene(st);
  $("foot").textContent =
    `irtrackd ${(st.versions || {}).irtrackd || "?"} · up ${Math.round(st.uptime_s || 0)} s · ` +
    `${state.statusCount} status reports, ${state.positions} positions received`;
}

const live = new Live({
  onStatus,
  onPreview: (head, jpeg) => {
    cameras.preview(head, jpeg);
    refreshFaults();
  },
  onZoom: (head, png) => cameras.zoom(head, png),
  onError: (message) => {
    $("conn").title = `irtrackd: ${message}`;
  },
  onPosition: (rec, tools, loose) => {
    state.positions += 1;
    health.position(rec);
    scene.position(rec);
    if (tools.length) setToolNames(tools.map((t) => t.tool));
    scene.tools(tools);
    if (tools.length || loose.length) scene.loose(loose);
  },
  onState: (s, detail) => {
    const c = $("conn");
    c.dataset.state = s;
    c.textContent = s === "open" ? "live" : s === "connecting" ? "connecting…" : `connection lost (${detail}) — retrying`;
  },
});

fpsSelect.addEventListener("change", () => live.subscribe({ preview_fps: Number(fpsSelect.value) }));
zoomSelect.addEventListener("change", () => live.subscribe({ zoom_px: Number(zoomSelect.value) }));
$("scene-reset").addEventListener("click", () => scene.resetView());
live.subscription.preview_fps = Number(fpsSelect.value);
live.subscription.zoom_px = Number(zoomSelect.value);

// For the browser test and for debugging from the console: what the page shows, as data.
window.__irtrack = {
  ready: false,
  cameras: () => cameras.summary(),
  faults: () => Array.from(document.querySelectorAll("#fault-list li")).map((li) => li.textContent),
  serverFaults: () => (state.status ? serverFaults(state.status) : []),
  statusReports: () => state.statusCount,
  positions: () => state.positions,
  scene: () => ({ webgl: scene.ok, records: scene.records, rigCameras: scene.rig ? scene.rig.cameras.length : 0, workspace: !!scene.workspace, tools: scene.toolSummary(), loose: scene.looseSummary(), labels: scene.labelBoxes() }),
  session: () => state.session,
  tuningMessage: () => $("tuning-msg").textContent,
  captureMessage: () => $("capture-msg").textContent,
  suggestion: () => ($("suggestion").hidden ? null : { text: $("suggestion-head").textContent, threshold_dn: controls.suggestion ? controls.suggestion.threshold_dn : null, why: Array.from(document.querySelectorAll("#suggestion-why li")).map((li) => li.textContent), keeps_only_marker: controls.suggestion ? controls.suggestion.keeps_only_marker : null }),
  suggestNote: () => $("suggest-note").textContent,
  health: () => Array.from(document.querySelectorAll("#camera-health tbody tr")).map((tr) => Array.from(tr.children).map((td) => td.textContent)),
  headers: () => Array.from(document.querySelectorAll(".cam .stats")).map((e) => e.textContent),
  capturesSaved: () => capture.saved,
  system: () => Array.from(document.querySelectorAll("#system dd")).map((dd) => dd.textContent),
  update: () => system.summary(),
  clocks: () => Array.from(document.querySelectorAll("#camera-clocks tbody tr")).map((tr) => ({ cells: Array.from(tr.children).map((td) => td.textContent), title: tr.title, bad: tr.className === "bad" })),
};

live.connect();
controls.start().finally(() => {
  window.__irtrack.ready = true;
});
