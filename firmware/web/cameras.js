// Camera cards: the preview JPEG with the blob overlay and the threshold tint drawn in the
// browser, the full-resolution zoom around the marker, and the blob list with reasons.

const KEPT = "#3ecf6e";
const REJECTED = "#ff5a5a";
const TINT = [255, 61, 242];
const REASON_WORDS = {
  area: "area",
  roundness: "roundness",
  edge: "cut by edge",
  gate: "gate",
  window: "outside the tracking window",
};

function el(tag, cls, text) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
}

/** Plain words for why a blob was rejected. */
/** Colours of tools 0..7, shared with the 3-D view. */
export const TOOL_COLORS = ["#4fc3f7", "#ffb74d", "#ce93d8", "#aed581", "#f06292", "#fff176", "#90a4ae", "#bcaaa4"];
let toolNames = [];
/** Names of the set's tools by id (from the live position messages). */
export function setToolNames(names) {
  toolNames = names;
}
/** Which tool a blob went to, in words: the tool's name, "loose LED", or null. */
export function blobOwner(b) {
  if (b.tool !== null && b.tool !== undefined) return toolNames[b.tool] || `tool ${b.tool}`;
  return b.loose ? "loose LED" : null;
}

export function reasonWords(reason) {
  return REASON_WORDS[reason] || (reason ? String(reason) : "rejected");
}

/**
 * Draws `labels` ({text, color, x, y, c: clearance from the anchor}) where they cover no
 * earlier label: right-above, right-below, left-above, left-below the anchor, else moved down
 * until free. Returns the boxes drawn (canvas pixels).
 */
function placeLabels(ctx, labels, lw, width, height) {
  const placed = [];
  const h = 12 * lw;
  const hits = (r) => placed.some((p) => r.x < p.x + p.w && r.x + r.w > p.x && r.y < p.y + p.h && r.y + r.h > p.y);
  for (const l of labels) {
    const w = ctx.measureText(l.text).width + 4;
    const clampX = (x) => Math.max(0, Math.min(x, width - w));
    const clampY = (y) => Math.max(0, Math.min(y, height - h));
    const tries = [
      [l.x + l.c, l.y - l.c - h],
      [l.x + l.c, l.y + l.c],
      [l.x - l.c - w, l.y - l.c - h],
      [l.x - l.c - w, l.y + l.c],
    ].map(([x, y]) => ({ x: clampX(x), y: clampY(y), w, h }));
    let box = tries.find((r) => !hits(r));
    if (!box) {
      box = { ...tries[0] };
      while (hits(box) && box.y + h < height) box.y += h / 2;
    }
    placed.push({ ...box, text: l.text });
    ctx.fillStyle = "rgba(0,0,0,.65)";
    ctx.fillRect(box.x, box.y, w, h);
    ctx.fillStyle = l.color;
    ctx.fillText(l.text, box.x + 2, box.y + h - 3 * lw);
  }
  return placed;
}

class CameraCard {
  constructor(index, parent) {
    this.index = index;
    this.shown = 0; // previews drawn (the browser test watches this advance)
    this.zooms = 0;
    this.last = null; // header of the last drawn preview
    this.busy = false; // decoding a JPEG
    this.queued = null; // newest preview that arrived while decoding (latest-only)
    this.zoomHead = null;

    this.root = el("article", "cam");
    this.root.id = `cam-${index}`;
    this.root.dataset.camera = String(index);
    const head = el("div", "cam-head");
    head.append(el("strong", "", `Camera ${index}`));
    this.stats = el("span", "stats", "no frame yet");
    head.append(this.stats);
    this.view = el("div", "cam-view");
    this.canvas = el("canvas", "preview");
    this.canvas.width = 640;
    this.canvas.height = 480;
    this.view.append(this.canvas);
    const foot = el("div", "cam-foot");
    const zoomBox = el("div", "zoom-box");
    this.zoom = el("canvas");
    this.zoom.width = 48;
    this.zoom.height = 48;
    this.zoomLabel = el("span", "", "zoom: no marker");
    zoomBox.append(this.zoom, this.zoomLabel);
    this.blobList = el("div", "blob-list");
    this.summary = el("div", "summary", "");
    this.list = el("ul");
    this.advice = el("div", "advice", "");
    this.blobList.append(this.summary, this.advice, this.list);
    foot.append(zoomBox, this.blobList);
    this.root.append(head, this.view, foot);
    parent.append(this.root);
    this.ctx = this.canvas.getContext("2d", { willReadFrequently: true });
    this.zctx = this.zoom.getContext("2d");
  }

  /** A preview header and its JPEG; decodes at most one at a time, keeping only the newest. */
  preview(head, jpeg, opts) {
    if (this.busy) {
      this.queued = { head, jpeg };
      return;
    }
    this.busy = true;
    createImageBitmap(new Blob([jpeg], { type: "image/jpeg" }))
      .then((bmp) => {
        this.draw(head, bmp, opts());
        bmp.close();
      })
      .catch((e) => {
        this.stats.textContent = `preview ${head.set_index} could not be decoded: ${e.message || e}`;
      })
      .finally(() => {
        this.busy = false;
        const q = this.queued;
        this.queued = null;
        if (q) this.preview(q.head, q.jpeg, opts);
      });
  }

  draw(head, bmp, opts) {
    const w = bmp.width;
    const h = bmp.height;
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    const ctx = this.ctx;
    ctx.drawImage(bmp, 0, 0);
    if (opts.thresholdView) this.tint(head, w, h);
    // Blob coordinates are full-resolution pixels; the JPEG is the frame scaled by `scale`.
    this.overlay(head, w / Math.max(1, head.width_px / (head.scale || 1)));
    this.shown += 1;
    this.last = head;
    this.root.dataset.shown = String(this.shown);
    this.describe(head, opts.fps);
  }

  /** Tints pixels whose value is above the threshold, in the 8-bit scale of the JPEG. */
  tint(head, w, h) {
    const maxDn = head.bit_depth && head.bit_depth > 8 ? (1 << head.bit_depth) - 1 : 255;
    const t = (head.threshold_dn * 255) / maxDn;
    const img = this.ctx.getImageData(0, 0, w, h);
    const d = img.data;
    for (let i = 0; i < d.length; i += 4) {
      if (d[i] > t) {
        d[i] = TINT[0];
        d[i + 1] = TINT[1];
        d[i + 2] = TINT[2];
      }
    }
    this.ctx.putImageData(img, 0, 0);
  }

  overlay(head, scale) {
    const ctx = this.ctx;
    const lw = Math.max(1.5, this.canvas.width / 400);
    ctx.lineWidth = lw;
    ctx.font = `${Math.round(10 * lw)}px system-ui, sans-serif`;
    // Labels: one per tool (at its topmost blob) rather than one per blob, so a tool's 3-4 LEDs
    // carry its name once; "kept" and reasons per blob. Placed after all circles, avoiding
    // each other.
    const labels = [];
    const byOwner = new Map();
    for (const b of head.blobs || []) {
      const x = b.x_px * scale;
      const y = b.y_px * scale;
      const r = Math.max(4 * lw, Math.sqrt(Math.max(b.area_px, 1) / Math.PI) * scale * 1.6);
      const owner = blobOwner(b);
      const color = b.kept ? (b.tool !== null && b.tool !== undefined ? TOOL_COLORS[b.tool % TOOL_COLORS.length] : KEPT) : REJECTED;
      ctx.strokeStyle = color;
      ctx.beginPath();
      ctx.arc(x, y, r, 0, 2 * Math.PI);
      ctx.stroke();
      const c = r + 4 * lw;
      ctx.beginPath();
      ctx.moveTo(x - c, y);
      ctx.lineTo(x - r * 0.4, y);
      ctx.moveTo(x + r * 0.4, y);
      ctx.lineTo(x + c, y);
      ctx.moveTo(x, y - c);
      ctx.lineTo(x, y - r * 0.4);
      ctx.moveTo(x, y + r * 0.4);
      ctx.lineTo(x, y + c);
      ctx.stroke();
      const text = b.kept ? owner || "kept" : reasonWords(b.reason);
      const item = { text, color, x, y, c };
      if (b.kept && owner && owner !== "loose LED") {
        const prev = byOwner.get(owner);
        if (!prev || y < prev.y) byOwner.set(owner, item);
      } else {
        labels.push(item);
      }
    }
    labels.unshift(...byOwner.values());
    this.labelBoxes = placeLabels(ctx, labels, lw, this.canvas.width, this.canvas.height);
  }

  describe(head, fps) {
    const blobs = head.blobs || [];
    const kept = blobs.filter((b) => b.kept);
    const rejected = blobs.filter((b) => !b.kept);
    const fullW = Math.round(head.width_px / (head.scale || 1));
    const fullH = Math.round(head.height_px / (head.scale || 1));
    const a = head.analysis;
    // A camera board's camera seen from the cluster solver: its blobs arrive, its pixels stay
    // on the board (aim it and set its exposure on that board's own set-up view).
    const blobsOnly = head.pixels === false;
    this.root.dataset.pixels = blobsOnly ? "blobs-only" : "";
    // No zoom crop comes for such a camera: say why instead of "no marker".
    if (blobsOnly) this.zoomLabel.textContent = "no zoom: the pixels stay on its camera board";
    this.stats.textContent =
      (blobsOnly ? "blobs only: the pixels stay on its camera board (its own set-up view shows them) · " : "") +
      `${fullW}×${fullH} · set ${head.set_index} · ` +
      (a && a.background && !blobsOnly ? `background ${a.background.median_dn} DN · ` : "") +
      `peak ${head.peak_dn} DN · threshold ${head.threshold_dn} · previews shown ${this.shown}` +
      (fps !== undefined ? ` at ≤ ${fps} fps` : "");
    this.advice.textContent = a && a.advice ? a.advice.message : "";
    this.root.dataset.advice = a && a.advice ? a.advice.code : "";
    const why = {};
    for (const b of rejected) why[reasonWords(b.reason)] = (why[reasonWords(b.reason)] || 0) + 1;
    const whyText = Object.entries(why)
      .map(([k, n]) => `${n} for ${k}`)
      .join(", ");
    // Regions the list has no room for (and an overloaded frame's uncounted ones) are
    // still counted: the analysis saw them.
    const regions = a ? a.regions : blobs.length;
    const unlisted = Math.max(0, regions - blobs.length);
    this.summary.textContent =
      `${kept.length} kept, ${rejected.length + unlisted} rejected` +
      (whyText ? ` (${whyText}${unlisted ? `, ${unlisted} not listed` : ""})` : unlisted ? ` (${unlisted} not listed)` : "") +
      (a && (a.overloaded || a.too_many_spots) ? " — overloaded" : "");
    this.root.dataset.kept = String(kept.length);
    this.root.dataset.rejected = String(rejected.length);
    this.list.replaceChildren(
      ...blobs.slice(0, 12).map((b) => {
        const li = el("li", b.kept ? "kept" : "rejected");
        li.textContent =
          `(${b.x_px.toFixed(1)}, ${b.y_px.toFixed(1)}) px · area ${b.area_px} px · ` +
          `round ${Number(b.roundness).toFixed(2)} · peak ${b.peak_dn}` +
          (b.kept ? " · kept" : ` · rejected: ${reasonWords(b.reason)}`) +
          (blobOwner(b) ? ` · ${blobOwner(b)}` : "");
        return li;
      })
    );
  }

  zoomImage(head, png) {
    createImageBitmap(new Blob([png], { type: "image/png" }))
      .then((bmp) => {
        const s = head.size_px;
        if (this.zoom.width !== s) {
          this.zoom.width = s;
          this.zoom.height = s;
        }
        this.zctx.imageSmoothingEnabled = false;
        this.zctx.drawImage(bmp, 0, 0);
        bmp.close();
        // The centroid of the kept blob in the crop, from the last preview of the same set.
        const p = this.last && this.last.set_index === head.set_index ? (this.last.blobs || []).find((b) => b.kept) : null;
        if (p) {
          const x = p.x_px - head.x0_px;
          const y = p.y_px - head.y0_px;
          this.zctx.strokeStyle = KEPT;
          this.zctx.lineWidth = 0.25;
          this.zctx.beginPath();
          this.zctx.moveTo(x - 3, y);
          this.zctx.lineTo(x + 3, y);
          this.zctx.moveTo(x, y - 3);
          this.zctx.lineTo(x, y + 3);
          this.zctx.stroke();
        }
        this.zooms += 1;
        this.zoomLabel.textContent = `zoom ${s}×${s} px at (${head.x0_px}, ${head.y0_px}), full resolution`;
      })
      .catch((e) => {
        this.zoomLabel.textContent = `zoom could not be decoded: ${e.message || e}`;
      });
  }
}

export class Cameras {
  constructor(container, opts) {
    this.container = container;
    this.opts = opts; // () => {thresholdView, fps}
    this.cards = [];
  }

  card(i) {
    if (!this.cards.length) this.container.replaceChildren();
    while (this.cards.length <= i) this.cards.push(new CameraCard(this.cards.length, this.container));
    return this.cards[i];
  }

  /** Ensures one card per camera the status reports (also before the first preview). */
  ensure(count) {
    if (count > 0) this.card(count - 1);
  }

  preview(head, jpeg) {
    this.card(head.camera).preview(head, jpeg, this.opts);
  }

  zoom(head, png) {
    this.card(head.camera).zoomImage(head, png);
  }

  /** Per camera: frames drawn, kept and rejected blobs of the last drawn preview. */
  summary() {
    return this.cards.map((c) => ({
      camera: c.index,
      shown: c.shown,
      zooms: c.zooms,
      set_index: c.last ? c.last.set_index : null,
      threshold_dn: c.last ? c.last.threshold_dn : null,
      peak_dn: c.last ? c.last.peak_dn : null,
      pixels: c.last ? c.last.pixels !== false : null,
      background_dn: c.last && c.last.analysis && c.last.analysis.background ? c.last.analysis.background.median_dn : null,
      regions: c.last && c.last.analysis ? c.last.analysis.regions : null,
      advice: c.last && c.last.analysis ? c.last.analysis.advice : null,
      kept: c.last ? (c.last.blobs || []).filter((b) => b.kept).length : null,
      rejected: c.last ? (c.last.blobs || []).filter((b) => !b.kept).length : null,
      reasons: c.last ? (c.last.blobs || []).filter((b) => !b.kept).map((b) => b.reason) : [],
      owners: c.last ? (c.last.blobs || []).map((b) => blobOwner(b)).filter((o) => o) : [],
      labels: c.labelBoxes || [],
    }));
  }
}
