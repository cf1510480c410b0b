// The job list and the upload form (GET /v1/jobs, POST /v1/jobs), live over each unfinished job's event stream.

import {
  AuthError,
  TERMINAL,
  TimeLeft,
  api,
  el,
  followEvents,
  formatAge,
  formatBytes,
  formatPsnr,
  formatRatio,
  keyRefused,
  setupKeyPanel,
} from "./app.js";

const LIMIT = 20;
// Browsers open about six connections per server over HTTP/1.1; leave some for the page's other requests.
const MAX_STREAMS = 4;
const REFRESH_MS = 10000;
const NUMERIC_PARAMS = [
  "psnr_budget", "max_levels", "iterations", "resolution", "eval_resolution", "train_views", "fit_views", "eval_views",
];

const query = new URLSearchParams(location.search);
const view = {
  state: query.get("state") || "",
  offset: Math.max(0, parseInt(query.get("offset") || "0", 10) || 0),
  total: 0,
};
const rows = new Map(); // job id -> {tr, cells, time}
const streams = new Map(); // job id -> AbortController
const tbody = document.querySelector("#jobs tbody");
const listStatus = document.getElementById("list-status");
const askKey = setupKeyPanel(() => {
  forgetJobs();
  load();
});

function closeStreams() {
  for (const controller of streams.values()) controller.abort();
  streams.clear();
}

// The list shows only what the tab's current key may see: a key forgotten, replaced or refused takes its jobs away.
function forgetJobs() {
  closeStreams();
  for (const row of rows.values()) row.tr.remove();
  rows.clear();
  document.getElementById("page-info").textContent = "";
}

function progressCell(jobId, label) {
  const bar = el("progress", { max: 1, "aria-label": `Progress of ${label}`, "data-job-id": jobId });
  const text = el("span", { className: "pct" });
  const left = el("span", { className: "eta" });
  return { td: el("td", { className: "progress-cell" }, bar, text, left), bar, text, left: new TimeLeft(left) };
}

function newRow(job) {
  const label = job.scene.filename;
  // <bdi>: a name's direction marks (a right-to-left override, say) end with it, and cannot reverse the id beside it.
  const link = el("a", { href: `/jobs/${encodeURIComponent(job.id)}` }, el("bdi", {}, label));
  const progress = progressCell(job.id, label);
  const cells = {
    scene: el("td", {}, link, el("span", { className: "job-id" }, job.id.slice(0, 8))),
    state: el("td", {}, el("span", { className: "badge" })),
    stage: el("td", { className: "stage" }),
    progress: progress.td,
    input: el("td", { className: "num" }),
    ratio: el("td", { className: "num" }),
    psnr: el("td", { className: "num" }),
    age: el("td", { className: "age" }),
  };
  // On a narrow screen each row is a card: its cells name their column themselves (see style.css).
  const headers = document.querySelectorAll("#jobs thead th");
  Object.values(cells).forEach((td, i) => td.setAttribute("data-label", headers[i].textContent));
  const tr = el("tr", { "data-job-id": job.id }, ...Object.values(cells));
  return { tr, cells, bar: progress.bar, pct: progress.text, left: progress.left, time: 0, created: job.created_at };
}

function setState(row, state) {
  const badge = row.cells.state.firstChild;
  badge.textContent = state;
  badge.className = `badge state-${state}`;
  row.tr.dataset.state = state;
}

function setProgress(row, state, progress, stage, message, etaSeconds) {
  if (state === "queued") row.bar.removeAttribute("value"); // indeterminate until a worker takes it
  else row.bar.value = progress;
  row.pct.textContent = state === "queued" ? "waiting" : `${Math.round(progress * 100)}%`;
  row.left.set(state, etaSeconds);
  row.cells.stage.textContent = stage || "\u2013";
  row.cells.stage.title = message || "";
}

function showJob(job) {
  let row = rows.get(job.id);
  if (!row) {
    row = newRow(job);
    rows.set(job.id, row);
  }
  if (job.updated_at < row.time) return row; // the event stream already showed something newer
  row.time = job.updated_at;
  setState(row, job.state);
  const stage = job.state === "failed" ? job.error?.code : job.stage;
  setProgress(row, job.state, job.progress, stage, job.message, job.eta_s);
  row.cells.input.textContent = formatBytes(job.scene.bytes);
  const m = job.metrics;
  row.cells.ratio.textContent = m ? formatRatio(m.ratio_to_ply) : "\u2013";
  row.cells.psnr.textContent = m ? formatPsnr(m.psnr) : "\u2013";
  row.cells.age.textContent = formatAge(job.created_at);
  return row;
}

function onEvent(jobId, event) {
  const row = rows.get(jobId);
  if (!row || event.time < row.time) return;
  row.time = event.time;
  setState(row, event.state);
  setProgress(row, event.state, event.progress, event.stage, event.message, event.eta_s);
}

function follow(jobId) {
  const controller = new AbortController();
  streams.set(jobId, controller);
  followEvents(jobId, (event) => onEvent(jobId, event), controller.signal)
    .then(async (how) => {
      if (how === "aborted") return;
      streams.delete(jobId);
      // The final event has no metrics: read the job once more for its ratio and PSNR.
      if (how === "finished" && rows.has(jobId)) showJob(await api(`/v1/jobs/${encodeURIComponent(jobId)}`));
      syncStreams();
    })
    .catch((err) => {
      streams.delete(jobId);
      if (err instanceof AuthError) askKey(keyRefused());
    });
}

// Follow the newest unfinished jobs on this page; stop following jobs no longer on it.
function syncStreams() {
  for (const [jobId, controller] of streams) {
    if (!rows.has(jobId)) {
      controller.abort();
      streams.delete(jobId);
    }
  }
  for (const [jobId, row] of rows) {
    if (streams.size >= MAX_STREAMS) break;
    if (!TERMINAL.has(row.tr.dataset.state) && !streams.has(jobId)) follow(jobId);
  }
}

function updateAddress() {
  const params = new URLSearchParams();
  if (view.state) params.set("state", view.state);
  if (view.offset) params.set("offset", String(view.offset));
  const search = params.toString();
  history.replaceState(null, "", search ? `?${search}` : location.pathname);
}

function showPage(page) {
  if (!page.items.length && page.offset > 0 && page.total > 0) {
    // Past the end (an old address, or the last page's jobs deleted meanwhile): show the last page instead.
    view.offset = Math.floor((page.total - 1) / LIMIT) * LIMIT;
    updateAddress();
    load();
    return;
  }
  view.total = page.total;
  const ids = new Set(page.items.map((job) => job.id));
  for (const id of [...rows.keys()]) {
    if (!ids.has(id)) {
      rows.get(id).tr.remove();
      rows.delete(id);
    }
  }
  page.items.forEach((job, index) => {
    const row = showJob(job);
    if (tbody.children[index] !== row.tr) tbody.insertBefore(row.tr, tbody.children[index] || null);
  });
  document.getElementById("jobs-empty").hidden = page.items.length > 0;
  const first = page.items.length ? page.offset + 1 : 0;
  document.getElementById("page-info").textContent = `${first}\u2013${page.offset + page.items.length} of ${page.total}`;
  document.getElementById("prev").disabled = page.offset === 0;
  document.getElementById("next").disabled = page.next_offset == null;
  syncStreams();
}

let loading = null; // the page request in flight
let queued = null; // one more request, to start when that one ends
// Show the current page; the promise resolves with a list fetched after this call (a request already in flight
// may predate a job just submitted, or a filter just chosen).
function load() {
  if (!loading) {
    loading = fetchPage().finally(() => {
      loading = null;
    });
    return loading;
  }
  queued ??= loading.then(() => {
    queued = null;
    return load();
  });
  return queued;
}

function fetchPage() {
  const params = new URLSearchParams({ offset: String(view.offset), limit: String(LIMIT) });
  if (view.state) params.set("state", view.state);
  return api(`/v1/jobs?${params}`)
    .then((page) => {
      listStatus.textContent = "";
      showPage(page);
      if (!presetsShown) showPresets();
    })
    .catch((err) => {
      if (err instanceof AuthError) {
        forgetJobs();
        askKey(keyRefused());
      } else {
        listStatus.textContent = `Could not load jobs: ${err.message}`;
      }
    });
}

function params(form) {
  const out = { preset: form.preset.value, device: form.device.value };
  for (const name of NUMERIC_PARAMS) {
    const value = form.elements[name].value.trim();
    if (value !== "") out[name] = Number(value);
  }
  return out;
}

async function submit(event) {
  event.preventDefault();
  const form = event.target;
  const status = document.getElementById("submit-status");
  const button = document.getElementById("submit-button");
  const body = new FormData();
  body.append("scene", form.scene.files[0]);
  if (form.images.files.length) body.append("images", form.images.files[0]);
  body.append("params", JSON.stringify(params(form)));
  button.disabled = true;
  status.textContent = "Uploading\u2026";
  status.classList.remove("error");
  try {
    const job = await api("/v1/jobs", { method: "POST", body });
    status.replaceChildren(
      "Submitted: ",
      el("a", { href: `/jobs/${encodeURIComponent(job.id)}` }, el("bdi", {}, job.scene.filename),
        ` (${job.id.slice(0, 8)})`),
      ` is ${job.state}.`,
    );
    form.scene.value = "";
    form.images.value = "";
    view.offset = 0;
    updateAddress();
    await load();
  } catch (err) {
    if (err instanceof AuthError) askKey("The server asks for an API key before it takes a scene.");
    status.textContent = `Not submitted: ${err.message}`;
    status.classList.add("error");
  } finally {
    button.disabled = false;
  }
}

// The presets, their promises and the default come from the server: one list, decided in one place. They are
// asked for once the server has accepted the page's key (the job list loaded).
let presetsShown = false;
async function loadPresets() {
  presetsShown = true;
  const select = document.getElementById("preset");
  const hint = document.getElementById("preset-hint");
  const presets = await api("/v1/presets");
  select.replaceChildren(...presets.map((p) => el("option", { value: p.name, selected: p.default }, p.name)));
  const describe = () => {
    hint.textContent = presets.find((p) => p.name === select.value)?.summary ?? "";
  };
  select.addEventListener("change", describe);
  describe();
}

function showPresets() {
  loadPresets().catch((err) => {
    presetsShown = false;
    document.getElementById("preset-hint").textContent = `Could not load the presets: ${err.message}`;
  });
}

function init() {
  const filter = document.getElementById("state-filter");
  filter.value = view.state;
  filter.addEventListener("change", () => {
    view.state = filter.value;
    view.offset = 0;
    updateAddress();
    load();
  });
  document.getElementById("refresh").addEventListener("click", () => load());
  document.getElementById("prev").addEventListener("click", () => {
    view.offset = Math.max(0, view.offset - LIMIT);
    updateAddress();
    load();
  });
  document.getElementById("next").addEventListener("click", () => {
    view.offset += LIMIT;
    updateAddress();
    load();
  });
  document.getElementById("submit-form").addEventListener("submit", submit);
  // New jobs from other clients, and jobs beyond the followed ones, show up on a slow refresh.
  setInterval(() => {
    if (!document.hidden) load();
  }, REFRESH_MS);
  setInterval(() => {
    for (const row of rows.values()) row.cells.age.textContent = formatAge(row.created);
  }, 5000);
  setInterval(() => {
    for (const row of rows.values()) row.left.render();
  }, 1000);
  load();
}

init();
