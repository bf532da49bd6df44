// Robot panel: link state, last target and hold reason from the status report; enable,
// disable and a hold-to-press deadman only when the board allows control and the operator is
// signed in.

import { post } from "./api.js";
import { fmt, kv } from "./format.js";

const STATE_WORDS = {
  disconnected: "not connected (irtrackd keeps retrying)",
  connecting: "connecting…",
  holding: "connected, holding still",
  moving: "connected, following the marker",
};

export class Robot {
  constructor() {
    this.dl = document.getElementById("robot");
    this.buttons = document.getElementById("robot-buttons");
    this.msg = document.getElementById("robot-msg");
    this.session = null;
    this.hasLink = false;
    this.lastLink = null;
    document.getElementById("robot-enable").addEventListener("click", () => this.send("/robot/enable"));
    document.getElementById("robot-disable").addEventListener("click", () => this.send("/robot/disable"));
    const dm = document.getElementById("robot-deadman");
    // Pressed only while held: releasing, leaving the button or losing the page releases it.
    const press = (e) => {
      e.preventDefault();
      dm.classList.add("held");
      this.send("/robot/deadman?pressed=1");
    };
    const release = () => {
      if (!dm.classList.contains("held")) return;
      dm.classList.remove("held");
      this.send("/robot/deadman?pressed=0");
    };
    dm.addEventListener("pointerdown", press);
    for (const ev of ["pointerup", "pointerleave", "pointercancel"]) dm.addEventListener(ev, release);
    window.addEventListener("blur", release);
  }

  setSession(s) {
    this.session = s;
    this.updateButtons();
  }

  updateButtons() {
    const s = this.session || {};
    this.buttons.hidden = !(s.control_allowed && s.signed_in && this.hasLink);
  }

  async send(path) {
    try {
      const link = await post(path);
      if (link && typeof link === "object") this.lastLink = link;
      this.msg.textContent = `${path.replace("/robot/", "").replace("?pressed=", " ")}: done`;
      this.msg.className = "msg ok";
    } catch (e) {
      this.msg.textContent = e.message;
      this.msg.className = "msg error";
    }
  }

  /** Updates from a status report (`robot` is absent when the config has no [robot]). */
  update(status, session) {
    const r = status.robot || this.lastLink;
    const rows = [];
    if (!r) {
      this.hasLink = false;
      rows.push(["link", "no robot configured (no [robot] section in the config)"]);
    } else {
      this.hasLink = true;
      const state = r.state || "unknown";
      rows.push(["link", STATE_WORDS[state] || state, state === "disconnected" ? "bad" : state === "moving" ? "good" : ""]);
      if (r.robot_name) rows.push(["robot", r.robot_name]);
      rows.push(["hold reason", r.hold_reason ? plainHold(r.hold_reason) : state === "moving" ? "none" : "—"]);
      const target = r.last_target_mm || r.target_mm;
      rows.push(["last target", target ? `(${target.map((v) => fmt(v, 1)).join(", ")}) mm` : "none sent yet"]);
      if (r.robot_pos_mm) rows.push(["robot at", `(${r.robot_pos_mm.map((v) => fmt(v, 1)).join(", ")}) mm`]);
      if (r.targets_sent !== undefined) rows.push(["targets sent", fmt(r.targets_sent)]);
      if (r.rejects) rows.push(["rejected by robot", fmt(r.rejects), "bad"]);
      if (r.last_error) rows.push(["last error", r.last_error, "bad"]);
      if (r.deadman_flag_pressed !== undefined && r.deadman_flag_pressed !== null)
        rows.push(["deadman", r.deadman_flag_pressed ? "pressed" : "released"]);
    }
    const s = session || {};
    if (!s.control_allowed) rows.push(["control", "off on this board ([service] control = false): view only"]);
    else if (!s.signed_in) rows.push(["control", "allowed; sign in to use the buttons"]);
    kv(this.dl, rows);
    this.updateButtons();
  }
}

/** Hold reasons arrive as Rust enum names (e.g. "NotEnabled", "StaleSample"); split the words. */
function plainHold(reason) {
  return String(reason)
    .replace(/([a-z])([A-Z])/g, "$1 $2")
    .replace(/_/g, " ")
    .toLowerCase();
}
