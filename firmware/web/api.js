// HTTP calls to irtrackd (docs/http-api.md) and the sentences the page shows for their errors.

/** An HTTP answer that was not 2xx, with the sentence to show the operator. */
export class ApiError extends Error {
  constructor(status, message, body) {
    super(message);
    this.status = status;
    this.body = (body || "").trim(); // the server's own text
  }
}

/** What the operator reads for a refused change: the server's own sentence, except 401. */
export function explain(status, body) {
  const text = (body || "").trim();
  if (status === 401) {
    return "Sign in to change settings" + (text ? ` (the board says: ${text})` : ".");
  }
  if (status === 0) return `irtrackd did not answer: ${text || "network error"}`;
  return text || `the board answered HTTP ${status} without an explanation`;
}

async function call(method, path, body) {
  let resp;
  try {
    resp = await fetch(path, {
      method,
      credentials: "same-origin",
      headers: body === undefined ? {} : { "Content-Type": "application/json" },
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (e) {
    throw new ApiError(0, explain(0, String(e && e.message ? e.message : e)));
  }
  const text = await resp.text();
  if (!resp.ok) throw new ApiError(resp.status, explain(resp.status, text), text);
  const type = resp.headers.get("Content-Type") || "";
  if (type.includes("json") && text.trim()) {
    try {
      return JSON.parse(text);
    } catch (e) {
      throw new ApiError(resp.status, `the board sent invalid JSON for ${path}: ${e.message}`);
    }
  }
  return text;
}

export const getJson = (path) => call("GET", path);
export const postJson = (path, body) => call("POST", path, body);
export const post = (path) => call("POST", path);
