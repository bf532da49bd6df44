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
    if (v && typeof v.reason === "string") return `Refused: ${v.reason}`;
  } catch (_) {
    // not JSON: the board's own sentence
  }
  return explain(status, body);
}

/** An installed job in words: "Installed 1.2.0 into slot B; reboot to start it." (the board's
 *  step says where and what next). */
export function installedText(job) {
  const step = (job.step || "").replace(/^installed\s*/, "");
  return `Installed ${job.version || "the bundle"}${step ? ` ${step}` : ""}.`;
}

/** A reboot asked for after an install (`system.reboot`) in words and its class, or null. */
export function rebootWords(r) {
  if (!r) return null;
  const into = r.slot ? ` into slot ${r.slot}${r.version ? ` (${r.version})` : ""}` : "";
  if (r.state === "failed") return [`failed${into}: ${r.detail || ""}`.trim(), "bad"];
  return [`rebooting${into}: ${r.detail || "the board goes down shortly"}; it is kept only if irtrackd comes up healthy`, ""];
}

/** Why the upload cannot be used now, with what to do about it ("" when it can). */
export function uploadBlocked(sys, session, { busy = false, uploading = false, file = null } = {}) {
  if (!sys) return "";
  if (sys.backend === "none") {
    return "Updates are off on this board: irtrackd runs no system updater ([update] backend in irtrackd.toml; see docs/updates.md).";
  }
  if (!session) return "";
  if (!session.operator_configured) {
    return "Upload is disabled: no operator password is set on this board. Make a hash with irtrackd --hash-password, put it in irtrackd.toml as [service] operator_password_hash (docs/security.md), restart irtrackd, then sign in.";
  }
  if (!session.signed_in) return "Upload is disabled until you sign in: enter the operator password at the top right.";
  if (busy) return "An update is running on the board; wait until it is done.";
  if (uploading) return "";
  if (!file) return "Choose a signed bundle (.raucb), then Upload and install.";
  return "";
}

export class SystemPanel {
  constructor() {
    this.uploading = false;
    this.busy = false;
    this.sys = null;
    this.session = null;
    // The job of this page's last upload (202's id): older jobs in a late status report
    // must not overwrite its outcome.
    this.jobId = null;
    // What the bars showed, for the browser test: upload percentages and install states.
    this.seen = { upload: [], install: [] };
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
      const reboot = rebootWords(sys.reboot);
      if (reboot) rows.push(["reboot", reboot[0], reboot[1]]);
      if (sys.backend === "simulated") rows.push(["updater", "simulated (slots in a directory, nothing flashed)"]);
    }
    kv($("system"), rows);
    const job = sys.install;
    const current = job && (this.jobId === null || job.id >= this.jobId);
    const bar = $("install-progress");
    const running = job && (job.state === "receiving" || job.state === "installing");
    if (current && job.state === "installing") {
      bar.hidden = false;
      bar.value = job.percent;
      $("install-label").textContent = `install ${job.percent}% — ${job.step}`;
      this.seen.install.push(`${job.percent}% ${job.step}`);
    } else if (current && !this.uploading) {
      bar.hidden = job.state !== "installed";
      bar.value = job.state === "installed" ? 100 : 0;
      const msg = $("update-msg");
      if (job.state === "installed") {
        $("install-label").textContent = "install 100% — done";
        msg.textContent = installedText(job);
        msg.className = "msg ok";
      } else if (job.state === "refused" && job.refusal) {
        $("install-label").textContent = "";
        msg.textContent = `Refused: ${job.refusal.reason}`;
        msg.className = "msg error";
      }
      const last = this.seen.install[this.seen.install.length - 1];
      if (last !== job.state) this.seen.install.push(job.state);
    }
    this.busy = !!running;
    this.buttons();
  }

  buttons() {
    const btn = $("update-btn");
    const input = $("update-file");
    const signedIn = !!(this.session && this.session.signed_in);
    const on = !!this.sys && this.sys.backend !== "none";
    const file = input.files[0] || null;
    const why = uploadBlocked(this.sys, this.session, { busy: this.busy, uploading: this.uploading, file });
    // Choosing a file is pointless when it cannot be sent.
    input.disabled = !signedIn || !on || this.uploading;
    $("update-reboot").disabled = input.disabled;
    btn.disabled = !signedIn || !on || !file || this.busy || this.uploading;
    btn.title = why;
    $("update-why").textContent = why;
  }

  /** Sends the chosen file; the browser reports the upload's progress. */
  upload() {
    const file = $("update-file").files[0];
    if (!file) return;
    const msg = $("update-msg");
    const bar = $("upload-progress");
    this.uploading = true;
    this.jobId = null;
    this.seen.upload = [];
    this.buttons();
    bar.hidden = false;
    bar.value = 0;
    $("install-progress").hidden = true;
    $("install-label").textContent = "";
    $("upload-label").textContent = "upload 0%";
    msg.className = "msg";
    msg.textContent = `Uploading ${file.name} (${(file.size / 1048576).toFixed(1)} MiB)…`;
    const xhr = new XMLHttpRequest();
    // reboot=1: the board restarts into the new system once it is installed (docs/updates.md).
    xhr.open("POST", $("update-reboot").checked ? "/api/update?reboot=1" : "/api/update");
    xhr.withCredentials = true;
    xhr.setRequestHeader("Content-Type", "application/octet-stream");
    xhr.upload.onprogress = (e) => {
      if (e.lengthComputable) {
        bar.value = Math.round((e.loaded * 100) / e.total);
        $("upload-label").textContent = `upload ${bar.value}%`;
        this.seen.upload.push(bar.value);
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
        bar.value = 100;
        $("upload-label").textContent = "upload 100%";
        try {
          this.jobId = JSON.parse(xhr.responseText).id ?? null;
        } catch (_) {
          this.jobId = null;
        }
        done("Bundle received; installing (the board keeps tracking meanwhile)…", "");
      } else {
        bar.hidden = true;
        $("upload-label").textContent = "";
        done(refusalText(xhr.status, xhr.responseText), "error");
      }
    };
    xhr.onerror = () => {
      bar.hidden = true;
      $("upload-label").textContent = "";
      done(explain(0, "the upload was cut off"), "error");
    };
    xhr.send(file);
  }

  /** What the panel shows, as data (the browser test reads it). */
  summary() {
    const bar = (id) => ($(id).hidden ? null : $(id).value);
    return {
      rows: Array.from(document.querySelectorAll("#system dt")).map((dt) => [dt.textContent, dt.nextElementSibling ? dt.nextElementSibling.textContent : ""]),
      file_enabled: !$("update-file").disabled,
      reboot_checked: $("update-reboot").checked,
      button_enabled: !$("update-btn").disabled,
      why: $("update-why").textContent,
      message: $("update-msg").textContent,
      message_class: $("update-msg").className,
      upload_bar: bar("upload-progress"),
      upload_label: $("upload-label").textContent,
      install_bar: bar("install-progress"),
      install_label: $("install-label").textContent,
      uploading: this.uploading,
      seen: this.seen,
    };
  }
}
