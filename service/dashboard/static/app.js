// Shared by the dashboard's pages: the API client (API key, errors, event streams, authenticated files),
// formatting, and the API key panel. Only the public /v1 API is used.

const KEY_STORAGE = "symgs.apiKey";
export const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);
// Colours of mirror levels: the same list, in the same order, as symgs_core/pictures/palette.py.
export const LEVEL_COLOURS = ["#E69F00", "#56B4E9", "#009E73", "#CC79A7", "#F0E442", "#D55E00", "#0072B2", "#FFFFFF"];

export class AuthError extends Error {}

export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

// The key lives in sessionStorage: it stays with this tab and is gone when the tab closes.
export function apiKey() {
  return sessionStorage.getItem(KEY_STORAGE) || "";
}

export function setApiKey(key) {
  if (key) sessionStorage.setItem(KEY_STORAGE, key);
  else sessionStorage.removeItem(KEY_STORAGE);
}

// What the key panel says when the API answers 401: no key yet, or a key it refused (wrong or revoked).
export const keyRefused = () => (apiKey() ? "That API key was not accepted." : "This server asks for an API key.");

// fetch() refuses a header holding a character beyond Latin-1 (a pasted smart quote, say) with a TypeError that
// names no key; printable Latin-1 is all a Bearer token can carry.
const KEY_CHARACTERS = /^[\x20-\x7e\xa0-\xff]*$/;

export function authHeaders(extra = {}) {
  const key = apiKey();
  return key ? { ...extra, Authorization: `Bearer ${key}` } : { ...extra };
}

async function failure(response) {
  if (response.status === 401) return new AuthError("a valid API key is required");
  let code = "error";
  let message = `${response.status} ${response.statusText}`;
  try {
    const body = await response.json();
    code = body.error.code;
    message = body.error.message;
  } catch {
    // not the API's error body (a proxy's page, say): keep the status line
  }
  return new ApiError(response.status, code, message);
}

// fetch() a /v1 path with the API key; the parsed JSON, or throws AuthError / ApiError.
export async function api(path, options = {}) {
  const response = await fetch(path, { ...options, headers: authHeaders(options.headers || {}), cache: "no-store" });
  if (!response.ok) throw await failure(response);
  return response.status === 204 ? null : response.json();
}

// An object URL of a file the API serves (a chart, a download): an <img> or a link cannot send the API key.
export async function blobUrl(path) {
  const response = await fetch(path, { headers: authHeaders(), cache: "no-store" });
  if (!response.ok) throw await failure(response);
  return URL.createObjectURL(await response.blob());
}

// The bytes of a file the API serves, for code that reads it itself (the 3D view).
export async function fileBytes(path) {
  const response = await fetch(path, { headers: authHeaders(), cache: "no-store" });
  if (!response.ok) throw await failure(response);
  return response.arrayBuffer();
}

const sleep = (ms, signal) =>
  new Promise((resolve) => {
    const timer = setTimeout(resolve, ms);
    signal?.addEventListener("abort", () => {
      clearTimeout(timer);
      resolve();
    });
  });

// Parse one response body of Server-Sent Events; `dispatch({id, event, data})` returns true to stop reading.
// Returns true when stopped that way, false when the server closed the stream.
async function readEvents(body, dispatch) {
  const reader = body.getReader();
  const decoder = new TextDecoder();
  let buffer = "";
  let fields = { data: [] };
  let ended = false;
  try {
    for (;;) {
      const { value, done } = await reader.read();
      if (done) {
        ended = true;
        return false;
      }
      buffer += decoder.decode(value, { stream: true });
      for (;;) {
        const end = /\r\n|\r|\n/.exec(buffer);
        // A lone "\r" at the end may be the first half of "\r\n": wait for the next chunk.
        if (!end || (end[0] === "\r" && end.index === buffer.length - 1)) break;
        const line = buffer.slice(0, end.index);
        buffer = buffer.slice(end.index + end[0].length);
        if (line === "") {
          if (fields.data.length && dispatch({ id: fields.id, event: fields.event, data: fields.data.join("\n") })) {
            // The server ends the stream after the final event: read to its end, as cancelling a response
            // midway is reported by the browser as a network error.
            while (!(await reader.read()).done);
            ended = true;
            return true;
          }
          fields = { data: [], id: fields.id };
          continue;
        }
        if (line.startsWith(":")) continue; // a keep-alive comment
        const colon = line.indexOf(":");
        const name = colon < 0 ? line : line.slice(0, colon);
        const text = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
        if (name === "data") fields.data.push(text);
        else if (name === "id") fields.id = text;
        else if (name === "event") fields.event = text;
      }
    }
  } finally {
    if (!ended) reader.cancel().catch(() => {});
  }
}

// Follow a job's events (GET /v1/jobs/{id}/events) until the event of a final state, calling onEvent(JobEvent).
// EventSource cannot send an Authorization header, so this reads the stream with fetch(), and on a dropped
// connection resumes with Last-Event-ID as EventSource would. Resolves "finished", "gone" (404) or "aborted".
export async function followEvents(jobId, onEvent, signal) {
  let lastId = "";
  let delay = 500;
  while (!signal.aborted) {
    let response;
    try {
      const headers = authHeaders({ Accept: "text/event-stream" });
      if (lastId) headers["Last-Event-ID"] = lastId;
      response = await fetch(`/v1/jobs/${encodeURIComponent(jobId)}/events`, { headers, signal, cache: "no-store" });
    } catch (err) {
      if (signal.aborted) break;
      await sleep(delay, signal);
      delay = Math.min(2 * delay, 10000);
      continue;
    }
    if (response.status === 404) return "gone";
    if (!response.ok) {
      const error = await failure(response);
      if (error instanceof AuthError) throw error;
      await sleep(delay, signal);
      delay = Math.min(2 * delay, 10000);
      continue;
    }
    delay = 500;
    let finished = false;
    try {
      finished = await readEvents(response.body, (message) => {
        if (message.id) lastId = message.id;
        const event = JSON.parse(message.data);
        onEvent(event);
        return event.kind === "state" && TERMINAL.has(event.state);
      });
    } catch (err) {
      if (signal.aborted) break;
    }
    if (finished) return "finished";
  }
  return "aborted";
}

// ---- formatting -------------------------------------------------------------------------------------------

export function formatBytes(bytes) {
  if (bytes == null) return "\u2013";
  const units = ["B", "kB", "MB", "GB", "TB"];
  let value = bytes;
  let unit = 0;
  while (value >= 1000 && unit < units.length - 1) {
    value /= 1000;
    unit += 1;
  }
  return `${unit === 0 ? value : value.toFixed(value < 10 ? 2 : 1)} ${units[unit]}`;
}

export const formatRatio = (ratio) => (ratio == null ? "\u2013" : `${ratio.toFixed(2)}\u00d7`);

// The API reports an infinite PSNR (a result identical to its reference) as null.
export const formatPsnr = (psnr) => (psnr == null ? "\u221e dB" : `${psnr.toFixed(2)} dB`);

export const formatSeconds = (s) => (s == null ? "\u2013" : s < 10 ? `${s.toFixed(2)} s` : `${s.toFixed(1)} s`);

// "3:05 left" / "1:02:03 left" for the worker's estimate of the time left (eta_s); "" when unknown.
export function formatLeft(seconds) {
  if (seconds == null) return "";
  const s = Math.max(0, Math.ceil(seconds));
  const [h, m, sec] = [Math.floor(s / 3600), Math.floor((s % 3600) / 60), s % 60];
  const pad = (x) => String(x).padStart(2, "0");
  return `${h ? `${h}:${pad(m)}` : m}:${pad(sec)} left`;
}

// The time left of a running job in an element, counted down between the worker's reports (which can be minutes
// apart within a long step). The count starts when the report arrives here, so the two clocks need not agree.
export class TimeLeft {
  constructor(node) {
    this.node = node;
    this.eta = null;
    this.at = 0;
  }

  set(state, etaSeconds) {
    this.eta = state === "running" && etaSeconds != null ? etaSeconds : null;
    this.at = performance.now();
    this.render();
  }

  render() {
    this.node.textContent = this.eta == null ? "" : formatLeft(this.eta - (performance.now() - this.at) / 1000);
  }
}

export function formatAge(unixSeconds, now = Date.now() / 1000) {
  const s = Math.max(0, Math.round(now - unixSeconds));
  if (s < 60) return `${s} s ago`;
  if (s < 3600) return `${Math.floor(s / 60)} min ago`;
  if (s < 86400) return `${Math.floor(s / 3600)} h ago`;
  return `${Math.floor(s / 86400)} d ago`;
}

export const formatTime = (unixSeconds) => (unixSeconds == null ? "\u2013" : new Date(unixSeconds * 1000).toLocaleString());

// A small element builder: el("td", {className: "num"}, "text", child, ...). Text is never parsed as HTML.
export function el(tag, props = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(props)) {
    if (value == null) continue;
    if (name in node && !name.startsWith("aria") && !name.startsWith("data")) node[name] = value;
    else node.setAttribute(name, value);
  }
  for (const child of children) {
    if (child != null) node.append(child);
  }
  return node;
}

// ---- the API key panel ------------------------------------------------------------------------------------

// Wires the header's key button and the key panel; `onChange()` runs after a key is saved or forgotten.
// Returns ask(message): shows the panel (when the API answered 401).
export function setupKeyPanel(onChange) {
  const panel = document.getElementById("key-panel");
  const form = document.getElementById("key-form");
  const input = document.getElementById("key-input");
  const note = document.getElementById("key-note");
  const toggle = document.getElementById("key-toggle");
  const forget = document.getElementById("key-forget");

  const refresh = () => {
    const set = Boolean(apiKey());
    toggle.textContent = set ? "API key: set" : "API key";
    forget.hidden = !set;
  };
  const show = (message) => {
    panel.hidden = false;
    toggle.setAttribute("aria-expanded", "true");
    note.textContent = message || "";
    input.focus();
  };
  toggle.addEventListener("click", () => {
    if (panel.hidden) show("");
    else {
      panel.hidden = true;
      toggle.setAttribute("aria-expanded", "false");
    }
  });
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    const key = input.value.trim();
    if (!KEY_CHARACTERS.test(key)) {
      note.textContent = "That is not an API key: it holds a character that an HTTP header cannot carry.";
      input.focus();
      return;
    }
    setApiKey(key);
    input.value = "";
    panel.hidden = true;
    toggle.setAttribute("aria-expanded", "false");
    refresh();
    onChange();
  });
  forget.addEventListener("click", () => {
    setApiKey("");
    refresh();
    onChange();
  });
  refresh();
  return (message) => {
    refresh();
    show(message);
  };
}
