// Health panel, mirrored LEDs and the fault banner, all from the status report.

import uPlot from "/web/vendor/uplot/uPlot.esm.js";
import { age, fmt, kv } from "./format.js";

/** A latency in µs: true percentiles (within 1.6 %), so short stages keep a decimal. */
const us = (v) => (typeof v === "number" && v < 100 ? fmt(v, 1) : fmt(v));

const STAGE_WORDS = {
  render: "simulator rendering (ahead of capture)",
  driver: "driver: capture → dequeued",
  detect: "blob detection",
  solve: "undistort + triangulate",
  publish: "gate + publish",
  ours: "ours: dequeued → published",
  process: "whole set incl. viewer copy (vs deadline)",
  end_to_end: "capture → published",
};

/** One line: capture → robot packet split into driver, ours and the link's protocol wait (p50),
 *  or what is missing for it. */
export function latencySplit(lat, link) {
  const p50 = (s) => (s && s.count > 0 ? s.p50_us : null);
  const driver = p50(lat.driver);
  const ours = p50(lat.ours);
  if (driver === null || ours === null) return "capture → robot packet: no processed sets yet.";
  if (!link || !(link.count > 0)) {
    return `capture → published (p50): driver ${us(driver)} µs + ours ${us(ours)} µs; no robot link is sending targets, so there is no protocol wait.`;
  }
  return `capture → robot packet (p50): driver ${us(driver)} µs + ours ${us(ours)} µs + protocol wait ${us(link.wait_p50_us)} µs; the sample's age when it left: ${us(link.p50_us)} µs.`;
}

/** A duration given in µs, in ms words: "0.21 ms". */
const ms = (v, digits) => `${fmt(Math.abs(v) / 1000, digits)} ms`;

/** A camera's clock model (`/status` source.cameras[].clock, docs/timing.md "Camera clocks") in
 *  plain words, e.g. "120.003 fps, 3.1 ms after camera 0, jitter 0.21 ms, drifting +0.4 ms/min".
 *  Returns [text, class]: "bad" after a jump or with drops. */
export function clockWords(index, c) {
  if (!c) return ["—", ""];
  if (c.state === "warming_up") return ["measuring the frame clock…", ""];
  const parts = [];
  if (c.state === "relocking") parts.push("re-locking after a timestamp jump");
  if (typeof c.fps === "number") parts.push(`${fmt(c.fps, 3)} fps`);
  if (index === 0) {
    parts.push("the reference");
  } else if (typeof c.phase_us === "number") {
    parts.push(`${ms(c.phase_us, 1)} ${c.phase_us < 0 ? "before" : "after"} camera 0`);
  }
  if (typeof c.jitter_rms_us === "number") parts.push(`jitter ${ms(c.jitter_rms_us, 2)}`);
  if (index !== 0 && typeof c.drift_us_per_min === "number") {
    const d = c.drift_us_per_min / 1000;
    parts.push(Math.abs(d) < 0.05 ? "not drifting" : `drifting ${d > 0 ? "+" : "−"}${fmt(Math.abs(d), 1)} ms/min`);
  }
  const events = [];
  if (c.drops) events.push(`${fmt(c.drops)} dropped`);
  if (c.duplicates) events.push(`${fmt(c.duplicates)} duplicated`);
  if (c.jumps) events.push(`${fmt(c.jumps)} jump${c.jumps === 1 ? "" : "s"}`);
  if (events.length) parts.push(events.join(", "));
  return [parts.join(", "), c.jumps || c.state === "relocking" ? "bad" : ""];
}

/** What time-true tracking did with a camera's blobs (`/status` source.cameras[].bridge_ms_last,
 *  unbridged; docs/timing.md): "track carried 2.4 ms". Returns [text, bad]. */
export function bridgeWords(c) {
  const parts = [];
  if (typeof c.bridge_ms_last === "number" && Math.abs(c.bridge_ms_last) >= 0.05) {
    parts.push(`track carried ${ms(c.bridge_ms_last * 1000, 1)} ${c.bridge_ms_last < 0 ? "back" : "on"}`);
  }
  if (c.unbridged) parts.push(`${fmt(c.unbridged)} blob${c.unbridged === 1 ? "" : "s"} too far in time, left out`);
  return [parts.join(", "), Boolean(c.unbridged)];
}

/** The cells of one camera's row in the clock table: camera, fps, offset to camera 0 (ms, +
 *  after / − before), jitter (ms RMS), drift (ms/min), bridge (ms, − back / + on), events —
 *  numbers only, the units in the headers, so the row stays on one line in the side column;
 *  the whole sentence of `clockWords` and `bridgeWords` goes into the row's tooltip. Returns
 *  {cells, title, bad}: `bad` marks the events cell (a jump, re-locking, blobs left out). */
export function clockCells(index, c, cam = {}) {
  const [words, badClock] = clockWords(index, c);
  const [bridge, badBridge] = bridgeWords(cam);
  const title = bridge ? `${words}; ${bridge}` : words;
  const bad = badClock === "bad" || badBridge;
  const signed = (v, digits) => `${v < 0 ? "−" : "+"}${fmt(Math.abs(v), digits)}`;
  const cells = [`camera ${index}`];
  if (!c || c.state === "warming_up") {
    cells.push(c ? "measuring…" : "—", "—", "—", "—");
  } else {
    cells.push(typeof c.fps === "number" ? fmt(c.fps, 3) : "—");
    if (index === 0) cells.push("reference");
    else cells.push(typeof c.phase_us === "number" ? signed(c.phase_us / 1000, 1) : "—");
    cells.push(typeof c.jitter_rms_us === "number" ? fmt(c.jitter_rms_us / 1000, 2) : "—");
    if (index === 0 || typeof c.drift_us_per_min !== "number") {
      cells.push("—");
    } else {
      const d = c.drift_us_per_min / 1000;
      cells.push(Math.abs(d) < 0.05 ? "0" : signed(d, 1));
    }
  }
  const b = cam.bridge_ms_last;
  cells.push(typeof b === "number" && Math.abs(b) >= 0.05 ? signed(b, 1) : "—");
  const events = [];
  if (c && c.state === "relocking") events.push("re-locking");
  if (c && c.drops) events.push(`${fmt(c.drops)} dropped`);
  if (c && c.duplicates) events.push(`${fmt(c.duplicates)} dup.`);
  if (c && c.jumps) events.push(`${fmt(c.jumps)} jump${c.jumps === 1 ? "" : "s"}`);
  if (cam.unbridged) events.push(`${fmt(cam.unbridged)} left out`);
  cells.push(events.length ? events.join(", ") : "none");
  return { cells, title, bad };
}

/** The time mode row of the loop's health (`/status` processing.timing). */
export function timingRow(t) {
  if (!t) return ["time mode", "—"];
  const words = { accurate: "most accurate (interpolated)", low_latency: "lowest latency (extrapolated)", off: "off (blobs as seen)" };
  const bridge = t.mode === "off" ? "" : `, bridges ≤ ${fmt(t.max_bridge_ms, 0)} ms`;
  return ["time mode", `${words[t.mode] || t.mode}${bridge}`];
}

/** Rows of the active calibration's record (`/status` params.calibration, docs/calibration.md):
 *  method, age, quality; marked bad when poor or older than the configured age. */
export function calibrationRows(c) {
  if (!c) return [["calibration", "no quality record (set made before records existed, or by hand)"]];
  const when = new Date(c.calibrated_unix_s * 1000).toISOString().replace("T", " ").slice(0, 19);
  const old = c.age_days > c.max_age_days;
  const rows = [
    ["calibration", `${c.method}, ${c.tool_version}`],
    ["calibrated", `${when} UTC (${fmt(c.age_days, 0)} days ago${old ? `, older than ${fmt(c.max_age_days, 0)} days` : ""})`, old ? "bad" : "good"],
    ["calibration quality", c.verdict === "poor" ? `POOR: ${c.summary}` : "good (every limit held)", c.verdict === "poor" ? "bad" : "good"],
  ];
  if (c.rms_px && c.rms_px.length) rows.push(["reprojection RMS", c.rms_px.map((v, i) => `cam${i} ${fmt(v, 3)} px`).join(", ")]);
  return rows;
}

/** Plain words and the next step for the fault codes of docs/irtrackd.md, used when the server
 *  sends only the code. */
function faultWords(code, st) {
  const src = st.source || {};
  const proc = st.processing || {};
  switch (code) {
    case "camera_lost":
      return `A camera stopped delivering frames — check its cable and power; irtrackd keeps reopening it (${fmt(src.reconnects)} reconnect attempts so far).`;
    case "no_params":
      return "No calibration is loaded, so no position can be computed — push a parameter set with `host-tools push-params` (docs/calibration.md).";
    case "deadline_misses":
      return `Processing is slower than the frame rate (${fmt(proc.deadline_misses)} frame sets over the ${fmt(proc.deadline_us)} µs deadline) — lower the frame rate or resolution, or look for CPU load.`;
    default:
      return String(code).replace(/_/g, " ");
  }
}

/** The server's faults as {camera, text}: `fault_texts` (plain words from the board) when
 *  present, else the LED fault codes put into words here. */
export function serverFaults(st) {
  if (Array.isArray(st.fault_texts)) {
    return st.fault_texts.map((f) => ({ camera: f.camera ?? null, text: f.message || faultWords(f.code, st) }));
  }
  return (st.faults || []).map((f) => ({ camera: null, text: faultWords(f, st) }));
}

/** Problems the page sees in the camera previews, in plain words with the next step; cameras
 *  in `skip` already have a fault from the board. The words come from the board's whole-frame
 *  analysis of the previewed set (the same `advice` the status carries), so the camera cards
 *  and the fault list never tell different stories. */
export function previewWarnings(cams, skip = new Set()) {
  const out = [];
  for (const c of cams) {
    if (c.kept === null || skip.has(c.camera)) continue;
    if (c.advice) {
      out.push(c.advice.message.charAt(0).toUpperCase() + c.advice.message.slice(1) + ".");
    } else if (c.kept > 1 && !(c.owners && c.owners.length)) {
      // (Blobs that went to tools are the LEDs of 6-DOF tools: several are expected.)
      out.push(`Camera ${c.camera} keeps ${c.kept} blobs where one marker is expected — raise the threshold or cover the other light source.`);
    }
  }
  return out;
}

/** The health table's background and peak cells of one camera: the whole-frame analysis' figures
 *  when it saw the pixels; for a camera board's camera at the cluster solver (`pixels: false`)
 *  the board its pixels stay on and no figures (zeros would read as a dark camera); the loop's
 *  peak counter without an analysis. */
export function pixelCells(a, c, cluster) {
  if (a && a.pixels === false) {
    if (cluster && Array.isArray(cluster.boards)) {
      const b = cluster.boards.find((x) => Array.isArray(x.cameras) && x.cameras.includes(a.camera));
      // (An own camera without pixels is one the solver refuses: its fault says why.)
      if (b && b.name !== cluster.board) return [`on board ${b.name}`, "—"];
    }
    return ["—", "—"];
  }
  if (a && a.background) return [fmt(a.background.median_dn), fmt(a.background.peak_dn)];
  if (a) return ["—", "—"]; // a frame that could not be read (its advice says so)
  return ["—", fmt(c.peak_dn)];
}

export class Health {
  constructor() {
    this.plotData = [[], [], [], []];
    this.plot = null;
    this.lastStatusAt = 0;
    this.recordLatency = []; // [t_s, µs] since the last status
    this.lastGapMm = null;
  }

  /** Per-record latency from the live positions (one point per record, plotted with the status). */
  position(rec) {
    if (rec && typeof rec.latency_us === "number") this.recordLatency.push(rec.latency_us);
    if (rec && typeof rec.gap_mm === "number") this.lastGapMm = rec.gap_mm;
  }

  leds(st) {
    const on = (st.leds && st.leds.on) || {};
    for (const n of ["run", "track", "robot", "fault"]) {
      const e = document.querySelector(`.led[data-led=${n}]`);
      e.classList.toggle("on", !!on[n]);
    }
    const ind = st.leds && st.leds.indication;
    if (ind) {
      document.getElementById("leds").title =
        `LEDs (${st.leds.backend || "?"}): alive ${ind.alive ? "yes" : "no"}, track ${ind.track}, robot ${ind.robot}` +
        (ind.fault ? `, fault ${ind.fault}` : "");
    }
  }

  /** The banner: the board's faults first, then what the page sees in the previews. */
  faults(st, cams) {
    const box = document.getElementById("faults");
    const list = document.getElementById("fault-list");
    const server = serverFaults(st);
    const covered = new Set(server.filter((f) => f.camera !== null).map((f) => f.camera));
    const cal = (st.params || {}).calibration;
    const items = server
      .map((f) => [f.text, "fault"])
      .concat(cal && cal.warning ? [[`Calibration: ${cal.warning}`, "warn"]] : [])
      .concat(previewWarnings(cams, covered).map((t) => [t, "warn"]));
    box.hidden = items.length === 0;
    list.replaceChildren(
      ...items.map(([t, cls]) => {
        const li = document.createElement("li");
        li.className = cls;
        li.textContent = t;
        return li;
      })
    );
  }

  update(st) {
    const src = st.source || {};
    const proc = st.processing || {};
    // Cameras.
    // Blobs, background and peak from the board's whole-frame analysis (the same account the
    // camera cards show, with or without a parameter set); the loop's counters only without it.
    const analysis = Array.isArray(st.frame_analysis) ? st.frame_analysis : [];
    const tbody = document.querySelector("#camera-health tbody");
    tbody.replaceChildren(
      ...(src.cameras || []).map((c) => {
        const a = analysis.find((x) => x.camera === c.index);
        const tr = document.createElement("tr");
        tr.dataset.camera = String(c.index);
        const [background, peak] = pixelCells(a, c, st.cluster);
        if (a) {
          tr.dataset.kept = String(a.kept);
          tr.dataset.regions = String(a.regions);
          tr.dataset.pixels = a.pixels === false ? "no" : "yes";
          if (a.background) {
            tr.dataset.peak = String(a.background.peak_dn);
            tr.dataset.background = String(a.background.median_dn);
          }
          tr.dataset.advice = a.advice ? a.advice.code : "";
        }
        for (const v of [
          `camera ${c.index}`,
          fmt(c.fps, 1),
          fmt(c.frames),
          a ? `${a.kept} / ${a.regions}${a.overloaded || a.too_many_spots ? " (overloaded)" : ""}` : fmt(c.blobs_last),
          background,
          peak,
        ]) {
          const td = document.createElement("td");
          td.textContent = v;
          tr.append(td);
        }
        const size = document.createElement("td");
        size.textContent = c.width_px ? `${c.width_px}×${c.height_px}` : "—";
        tr.append(size);
        return tr;
      })
    );
    // The clock models, one row per camera (period, phase against camera 0, jitter, drift,
    // the time bridge, drops and jumps); the full sentence is the row's tooltip.
    document.querySelector("#camera-clocks tbody").replaceChildren(
      ...(src.cameras || []).map((c) => {
        const { cells, title, bad } = clockCells(c.index, c.clock, c);
        const tr = document.createElement("tr");
        tr.dataset.camera = String(c.index);
        if (c.clock) tr.dataset.clock = c.clock.state;
        tr.title = title;
        for (const v of cells) {
          const td = document.createElement("td");
          td.textContent = v;
          tr.append(td);
        }
        if (bad) tr.lastElementChild.className = "bad";
        return tr;
      })
    );
    kv(document.getElementById("source-health"), [
      ["source", src.description || "—"],
      ["sets delivered", fmt(src.sets_delivered)],
      ["sets dropped", fmt(src.sets_dropped), src.sets_dropped ? "bad" : ""],
      ["frames without partner", fmt(src.unpaired_dropped), src.unpaired_dropped ? "bad" : ""],
      ["camera reconnects", fmt(src.reconnects), src.reconnects ? "bad" : ""],
      ["pairing error now / max", `${fmt(src.pairing_error_last_us, 1)} / ${fmt(src.pairing_error_max_us, 1)} µs`],
    ]);
    const sets = proc.sets_processed || 0;
    const pct = (n) => (sets ? ` (${fmt((100 * n) / sets, 1)} %)` : "");
    kv(document.getElementById("loop-health"), [
      ["sets processed", fmt(proc.sets_processed)],
      ["tracked", fmt(proc.tracked) + pct(proc.tracked || 0)],
      ["lost (marker not seen)", fmt(proc.lost) + pct(proc.lost || 0)],
      ["refused by quality gate", fmt(proc.gated)],
      ["deadline misses", `${fmt(proc.deadline_misses)} (deadline ${fmt(proc.deadline_us)} µs)`, proc.deadline_misses ? "bad" : ""],
      timingRow(proc.timing),
      ["sets beyond the time bridge", fmt(proc.skewed_sets), proc.skewed_sets ? "bad" : ""],
      ["ray gap, last", proc.last_gap_mm === null || proc.last_gap_mm === undefined ? "—" : `${fmt(proc.last_gap_mm, 3)} mm`],
      ["stream clients", fmt((st.stream || {}).clients)],
    ].concat(
      st.viewers
        ? [["page viewers", `${fmt(st.viewers.live)} (sets copied ${fmt(st.viewers.copies)}, skipped while busy ${fmt(st.viewers.busy_skips)}; previews encoded ${fmt(st.viewers.previews_encoded)}, shared ${fmt(st.viewers.previews_shared)})`]]
        : []
    ));
    // Latency table: the loop's stages, then the robot link's share (the same split as
    // `cargo xtask bench --latency`: driver + ours + protocol wait = the sample's age).
    const lat = proc.latency_us || {};
    const row = (cells, cls) => {
      const tr = document.createElement("tr");
      if (cls) tr.className = cls;
      for (const v of cells) {
        const td = document.createElement("td");
        td.textContent = v;
        tr.append(td);
      }
      return tr;
    };
    const link = (st.robot || {}).latency_us;
    const linkRows = link && link.count > 0
      ? [
          row(["robot link: protocol wait (published → on the wire)", us(link.wait_p50_us), "—", us(link.wait_p99_us), us(link.wait_max_us), fmt(link.count)], "link-row"),
          row(["robot link: capture → on the wire (sample age)", us(link.p50_us), "—", us(link.p99_us), us(link.max_us), fmt(link.count)], "link-row"),
        ]
      : [];
    document.querySelector("#latency tbody").replaceChildren(
      ...Object.keys(STAGE_WORDS)
        .filter((k) => lat[k] && lat[k].count > 0)
        .map((k) => {
          const s = lat[k];
          return row([STAGE_WORDS[k], us(s.p50_us), us(s.p90_us), us(s.p99_us), us(s.max_us), fmt(s.count)]);
        }),
      ...linkRows
    );
    document.getElementById("latency-split").textContent = latencySplit(lat, link);
    this.params(st);
    this.plotPoint(lat);
  }

  params(st) {
    const p = st.params || {};
    const rows = [];
    if (!p.loaded) {
      rows.push(["state", "no parameter set loaded", "bad"]);
    } else {
      rows.push(["rig id", p.rig_id || "—"]);
      rows.push(["signature", p.signature || "—", p.signature === "unsigned" ? "bad" : "good"]);
      rows.push(["created", p.created_unix_s ? `${new Date(p.created_unix_s * 1000).toISOString().replace("T", " ").slice(0, 19)} UTC (${age(p.created_unix_s)})` : "—"]);
      rows.push(["came from", p.origin || "—"]);
      rows.push(["serial", p.serial ? String(p.serial) : "none (set written before serials)"]);
    }
    rows.push(["signature policy", p.signature_policy === "allow_unsigned" ? "development: unsigned sets accepted" : "signed sets only"]);
    if (p.swaps) rows.push(["swaps since start", fmt(p.swaps)]);
    // Rollbacks (docs/param-protocol.md): refused older sets, and older sets let in by
    // --allow-rollback; the last event names both sets.
    if (p.rollbacks_refused) rows.push(["older sets refused", `${fmt(p.rollbacks_refused)}`, "bad"]);
    if (p.rollbacks_allowed) rows.push(["rollbacks allowed", `${fmt(p.rollbacks_allowed)}`, "bad"]);
    if (p.last_rollback) rows.push(["last rollback", p.last_rollback, "bad"]);
    if (p.rejected) rows.push(["pushes rejected", `${fmt(p.rejected)}${p.last_rejection ? ": " + p.last_rejection : ""}`, "bad"]);
    if (p.loaded) rows.push(...calibrationRows(p.calibration));
    // The live ray gap is what the calibration achieves on the marker right now.
    rows.push([
      "ray gap now (calibration check)",
      this.lastGapMm === null || Number.isNaN(this.lastGapMm) ? "— (no position)" : `${fmt(this.lastGapMm, 3)} mm`,
    ]);
    kv(document.getElementById("params"), rows);
  }

  plotPoint(lat) {
    const now = Date.now() / 1000;
    const recs = this.recordLatency;
    this.recordLatency = [];
    const recMax = recs.length ? Math.max(...recs) : null;
    const e2e = lat.end_to_end || {};
    const d = this.plotData;
    d[0].push(now);
    d[1].push(recMax);
    d[2].push(e2e.p50_us ?? null);
    d[3].push(e2e.p99_us ?? null);
    const keep = 240; // two minutes at two reports a second
    if (d[0].length > keep) for (const a of d) a.splice(0, a.length - keep);
    this.ensurePlot();
    if (this.plot) this.plot.setData(d);
  }

  ensurePlot() {
    const box = document.getElementById("latency-plot");
    const width = Math.max(240, box.clientWidth);
    if (this.plot) {
      if (Math.abs(this.plot.width - width) > 4) this.plot.setSize({ width, height: 160 });
      return;
    }
    const axis = { stroke: "#9aa3b2", grid: { stroke: "#2a2f38" }, ticks: { stroke: "#2a2f38" } };
    this.plot = new uPlot(
      {
        width,
        height: 160,
        legend: { live: false },
        scales: { x: { time: true } },
        axes: [axis, { ...axis, label: "µs", size: 60 }],
        series: [
          {},
          { label: "record latency (max per 0.5 s)", stroke: "#5fb3ff", width: 1.5, spanGaps: true },
          { label: "p50 capture → published", stroke: "#3ecf6e", width: 1.5, spanGaps: true },
          { label: "p99 capture → published", stroke: "#ffb347", width: 1.5, spanGaps: true },
        ],
      },
      this.plotData,
      box
    );
  }
}
