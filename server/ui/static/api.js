// The REST API and WebSockets as the page uses them: one bearer token, entered once and kept
// for this browser tab (sessionStorage), sent on every call.

const TOKEN_KEY = "burrforce.token";
// The API relative to the page (/ui/ → /v1/), so a proxy that mounts the server under a
// prefix keeps working.
const API = new URL("../v1", document.baseURI);
const apiUrl = (path) => `${API.pathname}${path}`;

export class ApiError extends Error {
  constructor(status, detail) {
    super(`${status}: ${detail}`);
    this.status = status;
    this.detail = detail;
  }
}

/** Takes a token from the URL's fragment (#token=…, as `burrforce serve` prints the link),
 * keeps it for the tab and removes it from the address bar (and from the history). */
export function adoptTokenFromUrl() {
  const params = new URLSearchParams(window.location.hash.slice(1));
  const token = params.get("token");
  if (token) {
    setToken(token);
    params.delete("token");
    const rest = params.toString();
    history.replaceState(null, "", window.location.pathname + window.location.search
      + (rest ? `#${rest}` : ""));
  }
}

export function getToken() {
  return sessionStorage.getItem(TOKEN_KEY) || "";
}

export function setToken(token) {
  if (token) sessionStorage.setItem(TOKEN_KEY, token);
  else sessionStorage.removeItem(TOKEN_KEY);
}

function detailText(body, status) {
  if (body && typeof body === "object" && "detail" in body) {
    const d = body.detail;
    if (typeof d === "string") return d;
    // FastAPI's validation errors: [{loc, msg}, ...]
    if (Array.isArray(d)) return d.map((e) => `${(e.loc || []).slice(1).join(".")}: ${e.msg}`).join("; ");
    return JSON.stringify(d);
  }
  return `HTTP ${status}`;
}

/** A JSON call: resolves to the parsed body, rejects with ApiError carrying the server's detail. */
export async function call(method, path, body) {
  const headers = { Authorization: `Bearer ${getToken()}` };
  const init = { method, headers };
  if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(apiUrl(path), init);
  const text = await response.text();
  let parsed = null;
  try { parsed = text ? JSON.parse(text) : null; } catch { parsed = text; }
  if (!response.ok) throw new ApiError(response.status, detailText(parsed, response.status));
  return parsed;
}

/** A GET of a file with the token: the response, or ApiError with the server's detail. */
async function getFile(path) {
  const response = await fetch(apiUrl(path), { headers: { Authorization: `Bearer ${getToken()}` } });
  if (!response.ok) {
    let body = null;
    try { body = await response.json(); } catch { /* not JSON */ }
    throw new ApiError(response.status, detailText(body, response.status));
  }
  return response;
}

/** A binary GET: resolves to an ArrayBuffer, rejects with ApiError. */
export async function fetchBinary(path) {
  return (await getFile(path)).arrayBuffer();
}

/** Fetches a file (an export, a report) with the token and hands it to the browser as a
 * download or a new tab: a plain link cannot carry the Authorization header. */
export async function download(path, filename, { open = false } = {}) {
  const response = await getFile(path);
  const blob = await response.blob();
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  if (open) a.target = "_blank";
  else a.download = filename;
  a.rel = "noopener";
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
  return blob.size;
}

/** A subprotocol may only hold an HTTP token's characters (RFC 6455). */
const PROTOCOL_SAFE = /^[A-Za-z0-9!#$%&'*+.^_`|~-]+$/;

/** A WebSocket on the API. A browser cannot set its headers: the token goes as the
 * subprotocol `bearer.TOKEN` beside `burrforce`, out of the URL and so out of access logs;
 * only a token with other characters goes in the query. */
export function socket(path, query = {}) {
  const token = getToken();
  const inUrl = !PROTOCOL_SAFE.test(token);
  const q = new URLSearchParams(inUrl ? { ...query, token } : query);
  const scheme = window.location.protocol === "https:" ? "wss" : "ws";
  const url = `${scheme}://${window.location.host}${apiUrl(path)}?${q}`;
  return inUrl ? new WebSocket(url) : new WebSocket(url, ["burrforce", `bearer.${token}`]);
}
