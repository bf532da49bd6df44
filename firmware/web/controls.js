// Live tuning controls (threshold, blob area, per-camera exposure and gain), Save, the
// operator sign-in, and the robot buttons. Every change goes to the board at once; a refused
// change shows the board's sentence and the control snaps back to the board's value.

import { ApiError, getJson, post, postJson } from "./api.js";

const SEND_DELAY_MS = 120; // coalesce slider drags into a few requests

function $(id) {
  return document.getElementById(id);
}

function say(node, text, kind) {
  node.textContent = text;
  node.className = "msg" + (kind ? " " + kind : "");
}

/** A slider and a number field bound to one numeric field of the tuning document. */
class Pair {
  constructor(range, number, onChange) {
    this.range = range;
    this.number = number;
    range.addEventListener("input", () => {
      number.value = range.value;
      onChange(Number(range.value));
    });
    number.addEventListener("change", () => {
      if (number.value === "" || !Number.isFinite(Number(number.value))) return;
      if (Number(number.value) <= Number(range.max)) range.value = number.value;
      onChange(Number(number.value));
    });
  }

  set(v) {
    // Never overwrite what the operator is typing into or dragging.
    if (document.activeElement !== this.number) this.number.value = String(v);
    if (document.activeElement !== this.range) this.range.value = String(v);
  }

  enable(on) {
    this.range.disabled = !on;
    this.number.disabled = !on;
  }
}

export class Controls {
  constructor(onSession) {
    this.onSession = onSession;
    this.session = { signed_in: false, operator_configured: false, control_allowed: false };
    this.tuning = null;
    this.pendingBody = {};
    this.timer = null;
    this.msg = $("tuning-msg");
    this.pairs = {};
    this.changesSent = 0;
    this.changesRefused = 0;
    for (const f of ["threshold_dn", "min_area_px", "max_area_px"]) {
      this.pairs[f] = new Pair($(`${f}-range`), $(f), (v) => this.queue({ [f]: v }));
    }
    this.cameraPairs = [];
    $("save-btn").addEventListener("click", () => this.save());
    $("signin").addEventListener("submit", (e) => {
      e.preventDefault();
      this.signIn();
    });
    $("signout-btn").addEventListener("click", () => this.signOut());
    this.suggestion = null; // the last suggestion shown (board's answer)
    $("suggest-btn").addEventListener("click", () => this.suggest());
    $("suggest-apply").addEventListener("click", () => this.applySuggestion());
    $("suggest-close").addEventListener("click", () => {
      $("suggestion").hidden = true;
    });
  }

  /** Asks the board for a threshold (operator only); shows it and its reasoning, applies
   *  nothing until "Apply" is pressed. */
  async suggest() {
    const box = $("suggestion");
    $("suggest-note").textContent = "computing from the newest frame set…";
    try {
      const s = await post("/api/tuning/suggest");
      this.showSuggestion(s, "Suggested");
      $("suggest-note").textContent = "";
    } catch (e) {
      box.hidden = true;
      $("suggest-note").textContent = `No suggestion: ${e.message}`;
      if (e.status === 401) await this.refreshSession();
    }
  }

  /** Shows a suggestion (`POST /api/tuning/suggest`, or the board's first-start one). */
  showSuggestion(s, label) {
    this.suggestion = s;
    const box = $("suggestion");
    const v = s.threshold_dn;
    $("suggestion-head").textContent =
      v === null || v === undefined
        ? `${label}: no threshold can be given for this frame set (now ${s.current_threshold_dn} DN).`
        : `${label}: threshold ${v} DN (now ${s.current_threshold_dn} DN)` +
          (s.keeps_only_marker ? " — in this frame set it keeps exactly the marker in every camera." : " — check the prediction below.");
    const lines = [];
    for (const c of s.cameras || []) for (const r of c.reasoning || []) lines.push(`camera ${c.camera}: ${r}`);
    for (const r of s.reasoning || []) lines.push(r);
    for (const r of s.predicted || []) lines.push(`prediction: ${r}`);
    $("suggestion-why").replaceChildren(
      ...lines.map((t) => {
        const li = document.createElement("li");
        li.textContent = t;
        return li;
      })
    );
    const apply = $("suggest-apply");
    apply.hidden = v === null || v === undefined;
    apply.textContent = `Apply ${v} DN`;
    apply.disabled = !this.session.signed_in;
    apply.title = this.session.signed_in ? "" : "sign in to apply";
    box.hidden = false;
    box.dataset.threshold = v === null || v === undefined ? "" : String(v);
  }

  /** The board's first-start suggestion from the status report, shown once until dismissed. */
  showStartupSuggestion(s) {
    if (!s || this.startupShown || !$("suggestion").hidden) return;
    this.startupShown = true;
    this.showSuggestion(s, "Suggested at first start");
  }

  applySuggestion() {
    const v = this.suggestion && this.suggestion.threshold_dn;
    if (v === null || v === undefined) return;
    this.pairs.threshold_dn.set(v);
    this.queue({ threshold_dn: v });
    // The reasoning stays in view next to the result; the button says it was sent.
    const apply = $("suggest-apply");
    apply.disabled = true;
    apply.textContent = `Applied ${v} DN`;
  }

  async start() {
    await Promise.all([this.refreshSession(), this.refreshTuning()]);
  }

  async refreshSession() {
    try {
      this.session = await getJson("/api/session");
    } catch (e) {
      $("session-text").textContent = `sign-in state unknown: ${e.message}`;
      return;
    }
    this.showSession();
  }

  showSession() {
    const s = this.session;
    const text = $("session-text");
    const pw = $("password");
    const inBtn = $("signin-btn");
    const outBtn = $("signout-btn");
    if (!s.operator_configured) {
      text.textContent =
        "Viewing only: no operator password is set on the board (irtrackd --hash-password, see docs/security.md).";
      pw.hidden = inBtn.hidden = true;
      outBtn.hidden = true;
    } else if (s.signed_in) {
      text.textContent = "Signed in as operator: changes are allowed.";
      pw.hidden = inBtn.hidden = true;
      outBtn.hidden = false;
    } else {
      text.textContent = "Viewing. Sign in to change settings:";
      pw.hidden = inBtn.hidden = false;
      outBtn.hidden = true;
    }
    document.body.dataset.signedIn = String(!!s.signed_in);
    // Suggesting is an operator action (it takes a frame set from the loop).
    const sb = $("suggest-btn");
    sb.disabled = !s.signed_in;
    sb.title = s.signed_in
      ? "computes a threshold from each camera's histogram and the marker's peak; shows it before applying"
      : "sign in as operator to get a threshold suggestion";
    $("suggest-apply").disabled = !s.signed_in;
    this.onSession(s);
  }

  async signIn() {
    const pw = $("password");
    try {
      await postJson("/api/login", { password: pw.value });
      pw.value = "";
      say(this.msg, "Signed in.", "ok");
    } catch (e) {
      say(this.msg, e.status === 401 ? `Sign-in refused: ${e.body || "wrong password"}` : e.message, "error");
    }
    await this.refreshSession();
  }

  async signOut() {
    try {
      await post("/api/logout");
      say(this.msg, "Signed out.", "ok");
    } catch (e) {
      say(this.msg, e.message, "error");
    }
    await this.refreshSession();
  }

  async refreshTuning() {
    try {
      this.show(await getJson("/api/tuning"));
    } catch (e) {
      say(this.msg, `Could not read the current settings: ${e.message}`, "error");
    }
  }

  /** Values from a status report: the board's truth, also after changes made elsewhere. */
  showLive(t) {
    if (this.timer && Object.keys(this.pendingBody).length) return; // our own change is on its way
    this.show(t);
  }

  /** Shows the board's current values (answer of GET or POST /api/tuning). */
  show(t) {
    this.tuning = t;
    for (const f of ["threshold_dn", "min_area_px", "max_area_px"]) {
      if (t[f] !== undefined) this.pairs[f].set(t[f]);
    }
    this.buildCameraControls(t.cameras || []);
    (t.cameras || []).forEach((c, i) => {
      const p = this.cameraPairs[i];
      if (!p) return;
      // null: this camera has no such control.
      p.exposure.enable(c.exposure !== null && c.exposure !== undefined);
      p.gain.enable(c.gain !== null && c.gain !== undefined);
      if (c.exposure !== null && c.exposure !== undefined) p.exposure.set(c.exposure);
      if (c.gain !== null && c.gain !== undefined) p.gain.set(c.gain);
    });
    const cameraError = $("camera-error");
    cameraError.textContent = t.last_error ? `A camera refused a change: ${t.last_error}` : "";
    cameraError.hidden = !t.last_error;
    $("unsaved").hidden = !t.unsaved_changes;
    $("saved-to").textContent =
      (t.saved_to ? `Save writes ${t.saved_to}` : "") + (t.loaded_from_file ? " (values loaded from it at start)" : "");
  }

  buildCameraControls(cams) {
    if (this.cameraPairs.length === cams.length) return;
    const box = $("camera-controls");
    box.replaceChildren();
    this.cameraPairs = cams.map((c, i) => {
      const head = document.createElement("div");
      head.className = "cam-ctl-head";
      head.textContent = `Camera ${c.camera ?? i}`;
      box.append(head);
      if (c.supported === false) {
        const note = document.createElement("div");
        note.className = "note";
        note.textContent =
          "no exposure or gain control here: the camera has none, or it is on a camera board (set them in that board's own set-up view)";
        box.append(note);
      }
      const mk = (name, label, range) => {
        const row = document.createElement("div");
        row.className = "ctl";
        const id = `cam${i}-${name}`;
        const lab = document.createElement("label");
        lab.htmlFor = id;
        lab.textContent = label;
        const r = document.createElement("input");
        r.type = "range";
        r.min = String(range ? range[0] : 0);
        r.max = String(range ? range[1] : 1000);
        r.step = "1";
        r.setAttribute("aria-label", `${label} slider`);
        const n = document.createElement("input");
        n.type = "number";
        n.id = id;
        n.min = r.min;
        n.max = r.max;
        n.step = "1";
        row.append(lab, r, n);
        box.append(row);
        const pair = new Pair(r, n, (v) => this.queueCamera(i, name, v));
        pair.enable(c.supported !== false);
        return pair;
      };
      return {
        exposure: mk("exposure", "exposure (100 µs units)", c.exposure_range),
        gain: mk("gain", "gain", c.gain_range),
      };
    });
  }

  queue(partial) {
    Object.assign(this.pendingBody, partial);
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.send(), SEND_DELAY_MS);
  }

  queueCamera(i, field, v) {
    const cams = (this.tuning && this.tuning.cameras) || [];
    const list = this.pendingBody.cameras || [];
    let entry = list.find((c) => c.camera === (cams[i] ? cams[i].camera : i));
    if (!entry) {
      entry = { camera: cams[i] ? cams[i].camera : i };
      list.push(entry);
    }
    entry[field] = v;
    this.queue({ cameras: list });
  }

  async send() {
    const body = this.pendingBody;
    this.pendingBody = {};
    if (!Object.keys(body).length) return;
    this.changesSent += 1;
    try {
      const t = await postJson("/api/tuning", body);
      if (t && typeof t === "object") this.show(t);
      say(this.msg, `Applied: ${describe(body)}.`, "ok");
    } catch (e) {
      this.changesRefused += 1;
      say(this.msg, `Not applied (${describe(body)}): ${e.message}`, "error");
      if (e instanceof ApiError && e.status === 401) await this.refreshSession();
      await this.refreshTuning(); // snap back to what the board really uses
    }
  }

  async save() {
    try {
      const r = await post("/api/tuning/save");
      const where = r && r.saved_to ? r.saved_to : this.tuning && this.tuning.saved_to;
      say(this.msg, `Saved${where ? " to " + where : ""}; irtrackd loads these values at its next start.`, "ok");
    } catch (e) {
      say(this.msg, `Not saved: ${e.message}`, "error");
      if (e.status === 401) await this.refreshSession();
    }
    await this.refreshTuning();
  }
}

function describe(body) {
  const parts = [];
  for (const [k, v] of Object.entries(body)) {
    if (k === "cameras") {
      for (const c of v) {
        for (const [ck, cv] of Object.entries(c)) if (ck !== "camera") parts.push(`camera ${c.camera} ${ck} ${cv}`);
      }
    } else {
      parts.push(`${k.replace(/_/g, " ")} ${v}`);
    }
  }
  return parts.join(", ");
}
