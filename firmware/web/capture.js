// "Save frame set": the newest full-resolution frame of every camera (`GET /api/frameset`,
// docs/http-api.md), saved by the browser as one PGM per camera — the views `host-tools
// calibrate` reads (put them in cam0/, cam1/, ...), plus `timestamps.csv` with every set saved
// in this session (`frame,camera,timestamp_ns,dropped`, what irtrackd's replay reads to keep the
// recorded intervals). For many views, `host-tools capture` does the same with a board check
// and coverage per camera.

import { explain } from "./api.js";

/** Splits an `application/x-irtrack-frameset` body into its JSON head and one PGM per camera,
 *  checking each PGM's header against the head. Throws an Error naming what is wrong. */
export function parseFrameset(buf) {
  const bytes = new Uint8Array(buf);
  const nl = bytes.indexOf(10);
  if (nl < 0) throw new Error("no JSON head line in the frame set");
  const head = JSON.parse(new TextDecoder().decode(bytes.subarray(0, nl)));
  if (!Array.isArray(head.cameras) || head.cameras.length === 0) {
    throw new Error("the frame set lists no cameras");
  }
  let at = nl + 1;
  const frames = head.cameras.map((c) => {
    const end = at + c.pgm_bytes;
    if (!(c.pgm_bytes > 0) || end > bytes.length) {
      throw new Error(`camera ${c.camera}: frame set ends before its ${c.pgm_bytes} bytes`);
    }
    const pgm = bytes.subarray(at, end);
    at = end;
    const text = new TextDecoder("ascii").decode(pgm.subarray(0, Math.min(40, pgm.length)));
    const [magic, w, h] = text.split(/\s+/);
    if (magic !== "P5" || Number(w) !== c.width_px || Number(h) !== c.height_px) {
      throw new Error(`camera ${c.camera}: PGM header "${magic} ${w} ${h}" does not match ${c.width_px}×${c.height_px}`);
    }
    return { camera: c.camera, width: c.width_px, height: c.height_px, bits: c.bit_depth, pgm };
  });
  if (at !== bytes.length) throw new Error(`${bytes.length - at} bytes after the last frame`);
  return { head, frames };
}

/** `timestamps.csv` rows of one set: the set index is the frame number of the file names. */
export function timestampRows(head) {
  return head.cameras.map((c, i) => `${head.set_index},${i},${c.timestamp_ns},0\n`).join("");
}

function download(name, data, type = "image/x-portable-graymap") {
  const url = URL.createObjectURL(new Blob([data], { type }));
  const a = document.createElement("a");
  a.href = url;
  a.download = name;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10_000);
}

export class Capture {
  constructor(button, msg) {
    this.button = button;
    this.msg = msg;
    this.saved = 0;
    this.timestamps = ""; // rows of every set saved in this session
    button.addEventListener("click", () => this.save());
  }

  show(text, error) {
    this.msg.textContent = text;
    this.msg.classList.toggle("error", !!error);
  }

  async save() {
    this.button.disabled = true;
    this.show("Taking the newest frame set…");
    try {
      const resp = await fetch("/api/frameset", { credentials: "same-origin" });
      if (!resp.ok) throw new Error(explain(resp.status, await resp.text()));
      const { head, frames } = parseFrameset(await resp.arrayBuffer());
      const index = String(head.set_index).padStart(6, "0");
      const names = frames.map((f) => `cam${f.camera}_${index}.pgm`);
      frames.forEach((f, i) => download(names[i], f.pgm));
      this.timestamps += timestampRows(head);
      download("timestamps.csv", "frame,camera,timestamp_ns,dropped\n" + this.timestamps, "text/csv");
      this.saved += 1;
      const f0 = frames[0];
      this.show(
        `Saved set ${head.set_index}: ${names.join(", ")} (${f0.width}×${f0.height}, ${f0.bits}-bit, ` +
          `pairing error ${Math.round((head.pairing_error_ns || 0) / 1000)} µs). ` +
          `Move each into cam0/, cam1/, … of one folder (as NNNNNN.pgm) with the newest timestamps.csv ` +
          `(all ${this.saved} set(s) of this session); irtrackd replays such a folder at the recorded pace.`,
      );
    } catch (e) {
      this.show(`Frame set not saved: ${e.message}`, true);
    } finally {
      this.button.disabled = false;
    }
  }
}
