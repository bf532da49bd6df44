// Small formatting helpers shared by the panels.

/** A number with `digits` decimals, or "—" when absent. */
export function fmt(v, digits = 0) {
  if (v === null || v === undefined || Number.isNaN(v)) return "—";
  if (typeof v !== "number") return String(v);
  return v.toLocaleString("en-US", { minimumFractionDigits: digits, maximumFractionDigits: digits });
}

/** Fills a <dl> with [term, value, class] rows (replacing what it had). */
export function kv(dl, rows) {
  const nodes = [];
  for (const [k, v, cls] of rows) {
    const dt = document.createElement("dt");
    dt.textContent = k;
    const dd = document.createElement("dd");
    dd.textContent = v;
    if (cls) dd.className = cls;
    nodes.push(dt, dd);
  }
  dl.replaceChildren(...nodes);
}

/** "3 min 12 s ago"-style age from a Unix time in seconds. */
export function age(unixS) {
  if (!unixS) return "—";
  let s = Math.max(0, Math.round(Date.now() / 1000 - unixS));
  const d = Math.floor(s / 86400);
  s -= d * 86400;
  const h = Math.floor(s / 3600);
  s -= h * 3600;
  const m = Math.floor(s / 60);
  s -= m * 60;
  if (d) return `${d} d ${h} h ago`;
  if (h) return `${h} h ${m} min ago`;
  if (m) return `${m} min ${s} s ago`;
  return `${s} s ago`;
}
