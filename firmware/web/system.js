// "System" panel: the slot running now and the other one, the last update's outcome, an
// install in progress (`/status` → system, docs/updates.md), and the upload of a bundle by a
// signed-in operator (`POST /api/update`, raw bytes; progress of the upload from the browser,
// of the install from the status reports).

import { explain } from "./api.js";
import { kv } from "./format.js";

const $ = (id) => document.getElementById(id);

/** A slot in words: "B · 1.2.0 (abc123.20261128T0300Z) · good". */
export function slotWords(s) {
  if (!s) return "—";
  const parts = [s.slot];
  if (s.version) parts.push(s.version + (s.build ? ` (${s.build})` : ""));
  parts.push(s.state === "empty" ? "empty (no update installed yet)" : s.state);
  return parts.join(" · ");
}

/** The last update in words and its class: "refused 2026-11-28 03:10 UTC: wrong signature …". */
export function lastUpdateWords(u) {
  if (!u) return ["none recorded", ""];
  const when = u.time ? u.time.replace("T", " ").replace(/:\d\dZ$/, " UTC") : "";
  const what = u.outcome === "rolled-back" ? "rolled back" : u.outcome;
  const version = u.version ? ` ${u.version}` : "";
  const slot = u.slot ? ` → slot ${u.slot}` : "";
  return [`${what}${version}${slot}${when ? `, ${when}` : ""}: ${u.detail || ""}`.trim(), u.ok ? "good" : "bad"];
}

/** The reason of a refused upload answer (JSON `reason`, else the text). */
export function refusalText(status, body) {
  try {
    const v = JSON.parse(body);
    if (v && typeof v.reason === "string") return `refused: ${v.reason}`;
  } catch (_) {
    // not JSON: the board's own sentence
  }
  return explain(status, body);
}

export class SystemPanel {
  constructor() {
    this.uploading = false;
    this.sys = null;
    this.session = null;
    $("update-btn").addEventListener("click", () => this.upload());
    $("update-file").addEventListener("change", () => this.buttons());
  }

  /** Each status report (`st.system`) and the sign-in state. */
  update(st, session) {
    this.session = session;
    const sys = st.system || { backend: "none" };
    this.sys = sys;
    const rows = [];
    if (sys.backend === "none") {
      rows.push(["updates", "off on this board ([update] backend, docs/updates.md)"]);
    } else {
      rows.push(["running", slotWords(sys.running)]);
      rows.push(["other slot", slotWords(sys.other)]);
      if (sys.boot_next) rows.push(["boots next", sys.boot_next]);
      const [last, cls] = lastUpdateWords(sys.last_update);
      rows.push(["last update", last, cls]);
      if (sys.slots_error) rows.push(["slots", sys.slots_error, "bad"]);
      if (sys.backend === "simulated") rows.push(["updater", "simulated (slots in a directory, nothing flashed)"]);
    }
    kv($("system"), rows);
    const job = sys.install;
    const bar = $("install-progress");
    const running = job && (job.state === "receiving" || job.state === "installing");
    if (job && job.state === "installing") {
      bar.hidden = false;
      bar.value = job.percent;
      $("install-label").textContent = `install ${job.percent}% — ${job.step}`;
    } else if (job && !this.uploading) {
      bar.hidden = job.state !== "installed";
      bar.value = job.state === "installed" ? 100 : 0;
      const msg = $("update-msg");
      if (job.state === "installed") {
        $("install-label").textContent = "";
        msg.textContent = `Installed ${job.version || ""} — ${job.step}.`;
        msg.className = "msg ok";
      } else if (job.state === "refused" && job.refusal) {
        $("install-label").textContent = "";
        msg.textContent = `Refused: ${job.refusal.reason}`;
        msg.className = "msg error";
      }
    }
    this.busy = !!running;
    this.buttons();
  }

  buttons() {
    const btn = $("update-btn");
    const signedIn = !!(this.session && this.session.signed_in);
    const on = this.sys && this.sys.backend !== "none";
    const file = $("update-file").files[0];
    btn.disabled = !signedIn || !on || !file || this.busy || this.uploading;
    btn.title = !on ? "this board has no system updater" : !signedIn ? "sign in to upload" : this.busy ? "an update is running" : !file ? "choose a bundle (.raucb) first" : "";
  }

  /** Sends the chosen file; the browser reports the upload's progress. */
  upload() {
    const file = $("update-file").files[0];
    if (!file) return;
    const msg = $("update-msg");
    const bar = $("upload-progress");
    this.uploading = true;
    this.buttons();
    bar.hidden = false;
    bar.value = 0;
    msg.className = "msg";
    msg.textContent = `Uploading ${file.name} (${(file.size / 1048576).toFixed(1)} MiB)…`;
    const xhr = new XMLHttpRequest();
    xhr.open("POST", "/api/update");
    xhr.withCredentials = true;
    xhr.setRequestHeader("Content-Type", "application/octet-stream");
    xhr.upload.onprogress = (e) => {
      if (e.lengthComputable) {
        bar.value = Math.round((e.loaded * 100) / e.total);
        $("upload-label").textContent = `upload ${bar.value}%`;
      }
    };
    const done = (text, cls) => {
      this.uploading = false;
      msg.textContent = text;
      msg.className = `msg ${cls}`;
      this.buttons();
    };
    xhr.onload = () => {
      if (xhr.status === 202) {
        $("upload-label").textContent = "upload 100%";
        done("Bundle received; installing (the board keeps tracking meanwhile)…", "");
      } else {
        bar.hidden = true;
        $("upload-label").textContent = "";
        done(refusalText(xhr.status, xhr.responseText), "error");
      }
    };
    xhr.onerror = () => {
      bar.hidden = true;
      done(explain(0, "the upload was cut off"), "error");
    };
    xhr.send(file);
  }
}
