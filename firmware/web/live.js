// The live WebSocket (`/api/live`): subscribes, reconnects, and pairs each JSON header
// ("preview", "zoom") with the binary message that follows it.

const RECONNECT_MIN_MS = 500;
const RECONNECT_MAX_MS = 5000;

export class Live {
  /**
   * @param {object} handlers onStatus(obj), onPreview(header, ArrayBuffer), onZoom(header,
   *   ArrayBuffer), onPosition(record), onState("connecting"|"open"|"closed", detail)
   */
  constructor(handlers) {
    this.h = handlers;
    this.subscription = { type: "subscribe", preview_fps: 5, preview_max_width_px: 640, zoom_px: 48, positions: true, blobs: false };
    this.pending = null; // header waiting for its binary message
    this.delayMs = RECONNECT_MIN_MS;
    this.ws = null;
    this.messages = 0;
  }

  url() {
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    return `${scheme}//${location.host}/api/live`;
  }

  connect() {
    this.h.onState("connecting", "");
    let ws;
    try {
      ws = new WebSocket(this.url());
    } catch (e) {
      this.h.onState("closed", String(e));
      this.retry();
      return;
    }
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => {
      this.delayMs = RECONNECT_MIN_MS;
      this.pending = null;
      this.h.onState("open", "");
      ws.send(JSON.stringify(this.subscription));
    };
    ws.onmessage = (ev) => this.dispatch(ev.data);
    ws.onclose = (ev) => {
      this.ws = null;
      this.h.onState("closed", ev.reason || `code ${ev.code}`);
      this.retry();
    };
    // A failed connection also fires close, which retries; nothing to add here.
    ws.onerror = () => {};
  }

  retry() {
    const d = this.delayMs;
    this.delayMs = Math.min(RECONNECT_MAX_MS, this.delayMs * 2);
    setTimeout(() => this.connect(), d);
  }

  /** Changes the subscription (sent now if connected, else on the next connect). */
  subscribe(changes) {
    Object.assign(this.subscription, changes);
    if (this.ws && this.ws.readyState === WebSocket.OPEN) this.ws.send(JSON.stringify(this.subscription));
  }

  dispatch(data) {
    this.messages += 1;
    if (data instanceof ArrayBuffer) {
      const head = this.pending;
      this.pending = null;
      if (!head) return; // binary without a header: ignore rather than misattribute
      if (head.type === "preview") this.h.onPreview(head, data);
      else if (head.type === "zoom") this.h.onZoom(head, data);
      return;
    }
    let msg;
    try {
      msg = JSON.parse(data);
    } catch (e) {
      console.warn("irtrack: non-JSON text message ignored", e);
      return;
    }
    switch (msg.type) {
      case "status":
        this.h.onStatus(msg);
        break;
      case "preview":
      case "zoom":
        this.pending = msg;
        break;
      case "position":
        this.h.onPosition(msg.record, msg.tools || [], msg.loose || []);
        break;
      case "error":
        this.h.onError(String(msg.message || "error"));
        break;
      default:
        break; // newer server message types are ignored
    }
  }
}
