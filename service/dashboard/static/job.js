// One job: live progress per stage and mirror level, then its metrics, mirrors, charts, pictures and downloads.

import {
  ApiError,
  AuthError,
  LEVEL_COLOURS,
  TERMINAL,
  TimeLeft,
  api,
  blobUrl,
  el,
  fileBytes,
  followEvents,
  formatBytes,
  formatPsnr,
  formatRatio,
  formatSeconds,
  formatTime,
  keyRefused,
  setupKeyPanel,
} from "./app.js";

const jobId = decodeURIComponent(location.pathname.split("/").pop());
const jobPath = `/v1/jobs/${encodeURIComponent(jobId)}`;
const $ = (id) => document.getElementById(id);
const CHARTS = {
  rate_distortion:
    "Rate and distortion: PSNR against archive size for the input, each mirror level, each later stage and the final archive",
  speed_accuracy: "Speed and accuracy: PSNR against the seconds since the job started, stage by stage",
};
const STEP = /step (\d+)\/(\d+)/; // the pipeline's level messages: "level 0: step 80/200 loss 0.0123"

const timeLeft = new TimeLeft(document.getElementById("overall-eta"));
setInterval(() => timeLeft.render(), 1000);
let resultsShown = false;
const stages = []; // {name, li, bar, status, start}
const levels = []; // {level, li, bar, status}

// Another key (or none) may see another job, or none: start the page afresh rather than mix what two keys saw.
const askKey = setupKeyPanel(() => location.reload());

function setBadge(state) {
  const badge = $("state");
  badge.textContent = state;
  badge.className = `badge state-${state}`;
}

function setOverall(state, progress, message, etaSeconds) {
  timeLeft.set(state, etaSeconds);
  setBadge(state);
  const bar = $("overall");
  if (state === "queued") bar.removeAttribute("value");
  else bar.value = progress;
  $("overall-pct").textContent = state === "queued" ? "waiting for a worker" : `${Math.round(progress * 100)}%`;
  $("message").textContent = message || "";
  $("cancel").hidden = TERMINAL.has(state);
}

function step(item, name, label) {
  const bar = el("progress", { max: 1, "aria-label": `Progress of ${label}` });
  const status = el("span", { className: "step-status" });
  const li = el("li", { "data-name": name }, el("span", { className: "step-name" }, label), bar, status);
  return { name, li, bar, status, ...item };
}

function finish(item, how, seconds) {
  if (!item || item.done) return;
  item.done = true;
  if (how === "done") item.bar.value = 1;
  else if (item.bar.position < 0) item.bar.value = 0; // an indeterminate bar stops moving
  item.status.textContent = how === "done" ? `done${seconds == null ? "" : ` in ${formatSeconds(seconds)}`}` : how;
  item.li.dataset.done = how;
}

function onStage(event) {
  if (!event.stage || event.stage === "done") return;
  let current = stages[stages.length - 1];
  if (!current || current.name !== event.stage) {
    if (current) finish(current, "done", event.time - current.start);
    current = step({ start: event.time }, event.stage, event.stage);
    stages.push(current);
    $("stages").append(current.li);
  }
  current.status.textContent = event.message || "running";
}

function onLevel(event) {
  if (event.level == null) return;
  let current = levels[levels.length - 1];
  if (!current || current.level !== event.level) {
    if (current) finish(current, "done", event.time - current.start);
    current = step({ level: event.level, start: event.time }, `level-${event.level}`, `level ${event.level}`);
    levels.push(current);
    $("levels").append(current.li);
    $("levels-empty").hidden = true;
  }
  const match = STEP.exec(event.message || "");
  if (match) current.bar.value = Number(match[1]) / Math.max(Number(match[2]), 1);
  current.status.textContent = event.message || "";
}

function onEvent(event) {
  setOverall(event.state, event.progress, event.message, event.eta_s);
  if (event.kind === "progress") {
    // Leaving the level stage ends its last level.
    if (event.stage !== "levels" && event.level == null) finish(levels[levels.length - 1], "done", null);
    onStage(event);
    onLevel(event);
  } else if (TERMINAL.has(event.state)) {
    const how = event.state === "succeeded" ? "done" : event.state;
    const last = stages[stages.length - 1];
    finish(last, how, last ? event.time - last.start : null);
    finish(levels[levels.length - 1], how, null);
    noLevelTried(event.state);
  }
}

function fact(list, term, value) {
  list.append(el("dt", {}, term), el("dd", {}, value));
}

// A finished job that tried no level says so, rather than that none has started yet.
function noLevelTried(state) {
  if (TERMINAL.has(state) && !levels.length) $("levels-empty").textContent = "No mirror level was tried.";
}

function showJob(job) {
  noLevelTried(job.state);
  document.title = `${job.scene.filename} \u00b7 SymGS`;
  $("title").textContent = `${job.scene.filename}`;
  $("progress-section").hidden = false;
  setOverall(job.state, job.progress, job.message, job.eta_s);
  if (job.cancel_requested && !TERMINAL.has(job.state)) $("message").textContent = "Cancelling\u2026";
  const error = $("error");
  error.hidden = !job.error;
  error.textContent = job.error ? `${job.error.code}: ${job.error.message}` : "";
  const facts = $("facts");
  facts.replaceChildren();
  const p = job.params;
  fact(facts, "Job", job.id);
  fact(facts, "Scene", `${formatBytes(job.scene.bytes)}, ${job.scene.gaussians} Gaussians, SH degree ${job.scene.sh_degree}`);
  fact(facts, "Images", job.images ? `${job.images.images} (${job.images.layout})` : "none: judged against renders of the input");
  // Parameters left out take the preset's values.
  const set = Object.entries(p).filter(([name, value]) => value != null && name !== "device");
  const settings = set.map(([name, value]) => `${name.replaceAll("_", " ")} ${value}`).join(", ");
  fact(facts, "Settings", `${settings}; device ${p.device}`);
  fact(facts, "Queue", job.queue);
  fact(facts, "Created", formatTime(job.created_at));
  if (job.started_at) fact(facts, "Started", formatTime(job.started_at));
  if (job.finished_at) fact(facts, "Finished", formatTime(job.finished_at));
  if (job.attempts > 1) fact(facts, "Attempts", String(job.attempts));
}

function row(table, label, value) {
  table.append(el("tr", {}, el("th", { scope: "row" }, label), el("td", { className: "num" }, value)));
}

function showMetrics(job, report) {
  const notes = $("notes");
  notes.replaceChildren(...(report.notes || []).map((note) => el("li", {}, note)));
  notes.hidden = !notes.children.length;
  const t = document.querySelector("#metrics tbody");
  t.replaceChildren();
  row(t, "Input (PLY)", report.input_bytes ? formatBytes(report.input_bytes) : "\u2013");
  row(t, "Archive", formatBytes(report.output_bytes));
  row(t, "Baseline archive (plain codec)", formatBytes(report.baseline_bytes));
  row(t, "Ratio to PLY", formatRatio(report.ratio_to_ply));
  row(t, "Ratio to baseline", formatRatio(report.ratio_to_baseline));
  const evaluation = report.cameras.evaluation;
  const against = `${evaluation.count} evaluation cameras, against ${evaluation.source}`;
  row(t, `PSNR, full frame (${against})`, formatPsnr(report.fidelity.psnr));
  row(t, "PSNR, the object's own pixels", formatPsnr(report.fidelity.psnr_object));
  row(t, "SSIM", report.fidelity.ssim.toFixed(4));
  row(t, "PSNR floor (the preset's promise)", formatPsnr(report.psnr_floor));
  if (report.psnr_mirror_floor != null && report.psnr_mirror_floor > report.psnr_floor) {
    row(t, "PSNR every mirror level held (the plain archive's own)", formatPsnr(report.psnr_mirror_floor));
  }
  const g = report.gaussians;
  row(t, "Gaussians: input / stored / decoded", `${g.input} / ${g.stored} / ${g.decoded}`);
  row(t, "Device", report.device);
  const s = document.querySelector("#seconds tbody");
  s.replaceChildren();
  for (const [stage, seconds] of Object.entries(report.seconds)) row(s, stage, formatSeconds(seconds));
  // Stages may nest (encoding times its reductions too), so the wall time is the job's, not a sum.
  if (job.started_at && job.finished_at) row(s, "wall time of the job", formatSeconds(job.finished_at - job.started_at));
  $("metrics-section").hidden = false;
}

function unit(normal) {
  const norm = Math.hypot(...normal) || 1;
  return normal.map((v) => v / norm);
}

function showMirrors(report) {
  const body = document.querySelector("#mirrors tbody");
  body.replaceChildren();
  for (const level of report.levels) {
    const swatch = el("span", { className: "swatch", "aria-hidden": "true" });
    if (level.accepted) swatch.style.background = LEVEL_COLOURS[level.level % LEVEL_COLOURS.length];
    const n = unit(level.normal).map((v) => (v + 0).toFixed(3)).join(", ");
    const share = report.gaussians.input ? `${((100 * level.right) / report.gaussians.input).toFixed(1)}%` : "\u2013";
    body.append(
      el(
        "tr",
        { "data-accepted": String(level.accepted) },
        el("td", {}, swatch, ` ${level.level}`),
        el("td", { className: "mono" }, `(${n})`),
        el("td", { className: "num" }, level.offset.toFixed(4)),
        el("td", { className: "num" }, String(level.right)),
        el("td", { className: "num" }, share),
        el("td", { className: "num" }, formatPsnr(level.psnr_after)),
        el("td", {}, level.accepted ? "accepted" : `rolled back${level.reason ? `: ${level.reason}` : ""}`),
      ),
    );
  }
  if (!report.levels.length) {
    body.append(el("tr", {}, el("td", { colSpan: 7 }, "No mirror was found in this scene.")));
  }
  $("mirrors-section").hidden = false;
}

function pictureCaption(name) {
  if (CHARTS[name]) return CHARTS[name];
  if (name === "mirrors") return "The accepted mirror planes over the input scene, one colour per level (as in the table)";
  const compare = /^compare_(\d+)$/.exec(name);
  if (compare) {
    return `Held-out view ${Number(compare[1]) + 1}: the uncompressed scene, the decoded scene and their difference`;
  }
  return name.replaceAll("_", " ");
}

async function figure(container, name) {
  const caption = pictureCaption(name);
  const img = el("img", { alt: caption, "data-name": name });
  container.append(el("figure", {}, img, el("figcaption", {}, caption)));
  try {
    img.src = await blobUrl(`${jobPath}/charts/${encodeURIComponent(name)}.png`);
  } catch (err) {
    img.alt = `${caption} (could not be loaded: ${err.message})`;
  }
}

function showPictures(job) {
  const names = job.artifacts.filter((a) => /^charts\/[A-Za-z0-9_-]+\.png$/.test(a)).map((a) => a.slice(7, -4));
  const order = (n) => (CHARTS[n] ? 0 : n === "mirrors" ? 1 : 2);
  names.sort((a, b) => order(a) - order(b) || a.localeCompare(b, undefined, { numeric: true }));
  $("charts").replaceChildren();
  $("pictures").replaceChildren();
  for (const name of names) figure(CHARTS[name] ? $("charts") : $("pictures"), name);
  $("charts-section").hidden = !names.some((n) => CHARTS[n]);
  $("pictures-section").hidden = !names.some((n) => !CHARTS[n]);
}

// What each artifact is, and where the API serves it (the job's links name every export format).
function download(job, name) {
  if (name === "result.symgs") return ["Compressed archive (.symgs)", job.links.result];
  if (name === "report.json") return ["Metrics report (JSON)", job.links.report];
  const exported = Object.values(job.links.exports).find((href) => href.endsWith(`/${name}`));
  if (exported) return [`Decoded scene (${name.slice("result".length)})`, exported];
  if (name.startsWith("charts/")) return [`${name.slice(7)}`, `${jobPath}/${name}`];
  return null;
}

function showDownloads(job) {
  const list = $("downloads");
  list.replaceChildren();
  const rank = (n) => (n === "result.symgs" ? 0 : n.startsWith("result.") ? 1 : n === "report.json" ? 2 : 3);
  for (const name of [...job.artifacts].sort((a, b) => rank(a) - rank(b) || a.localeCompare(b))) {
    const entry = download(job, name);
    if (!entry) continue;
    const [label, href] = entry;
    const filename = `${job.id}-${name.replace("/", "-")}`;
    const link = el("a", { href, download: filename }, label);
    // A plain link cannot send the API key: fetch the file with it and hand the browser the bytes.
    link.addEventListener("click", async (event) => {
      if (!sessionStorage.getItem("symgs.apiKey")) return;
      event.preventDefault();
      try {
        const url = await blobUrl(href);
        const a = el("a", { href: url, download: filename });
        document.body.append(a);
        a.click();
        a.remove();
        setTimeout(() => URL.revokeObjectURL(url), 60000);
      } catch (err) {
        $("job-status").textContent = `Download failed: ${err.message}`;
      }
    });
    list.append(el("li", {}, link));
  }
  $("downloads-section").hidden = !list.children.length;
}

// ---- the 3D view: the decoded result (.sog) or the upload (.ply), with the accepted mirror planes ----------

const viewer = { instance: null, loads: {}, scenes: {} };

function viewerStatus(text) {
  $("viewer-status").textContent = text;
}

function describeScene(name) {
  const { bytes, gaussians, label } = viewer.scenes[name];
  return `${label}: ${formatBytes(bytes)}, ${gaussians} Gaussians`;
}

// Loads scene `name` once (a second choice while it loads waits for the same load), then shows it.
async function showScene(name) {
  const scene = viewer.scenes[name];
  const canvas = $("viewer");
  canvas.dataset.state = "loading";
  if (!viewer.loads[name]) {
    viewerStatus(`Loading ${scene.label}${scene.bytes ? ` (${formatBytes(scene.bytes)})` : ""}\u2026`);
    viewer.loads[name] = fileBytes(scene.href).then((bytes) => {
      scene.bytes = bytes.byteLength;
      return viewer.instance.load(name, bytes, scene.filename);
    });
  }
  try {
    await viewer.loads[name];
  } catch (err) {
    delete viewer.loads[name];
    canvas.dataset.state = "failed";
    viewerStatus(`Could not load ${scene.label}: ${err.message}`);
    return;
  }
  if (document.querySelector('input[name="scene"]:checked').value !== name) return; // chosen away meanwhile
  viewer.instance.show(name);
  canvas.dataset.shown = name;
  canvas.dataset.state = "ready";
  viewerStatus(`Showing ${describeScene(name)}.`);
}

async function showViewer(job, report) {
  const sog = job.links.exports.sog;
  if (!sog || !job.artifacts.includes("result.sog") || viewer.instance) return;
  viewer.scenes = {
    compressed: {
      href: sog, filename: "result.sog", label: "the compressed result (.sog)",
      bytes: null, gaussians: report ? report.gaussians.decoded : "?",
    },
    original: {
      href: job.links.scene, filename: "scene.ply", label: "the original upload (.ply)",
      bytes: job.scene.bytes, gaussians: job.scene.gaussians,
    },
  };
  $("viewer-section").hidden = false;
  viewerStatus("Starting the 3D view\u2026");
  try {
    const { SplatViewer } = await import("./viewer.js");
    viewer.instance = SplatViewer.create($("viewer"));
  } catch (err) {
    $("viewer").dataset.state = "failed";
    $("scene-choice").disabled = true;
    viewerStatus(`This browser cannot show the 3D view (it needs WebGL 2): ${err.message}`);
    return;
  }
  const planes = job.mirrors.map((m) => ({
    normal: m.normal, offset: m.offset, colour: LEVEL_COLOURS[m.level % LEVEL_COLOURS.length],
  }));
  viewer.instance.setMirrors(planes);
  $("planes-choice").hidden = planes.length === 0;
  for (const input of document.querySelectorAll('input[name="scene"]')) {
    input.addEventListener("change", () => showScene(input.value));
  }
  $("show-planes").addEventListener("change", (event) => viewer.instance.setPlanesVisible(event.target.checked));
  await showScene("compressed");
}

async function showResults(job) {
  if (resultsShown || job.state !== "succeeded") return;
  resultsShown = true;
  let report = null;
  try {
    report = await api(`${jobPath}/report`);
    showMetrics(job, report);
    showMirrors(report);
  } catch (err) {
    $("job-status").textContent = `Could not load the report: ${err.message}`;
  }
  showPictures(job);
  showDownloads(job);
  await showViewer(job, report);
}

function showSecondsAsStages(job, report) {
  // A finished job shows its stages from the report (the event stream is not replayed for it).
  for (const [stage, seconds] of Object.entries(report.seconds)) {
    const item = step({ start: 0 }, stage, stage);
    stages.push(item);
    $("stages").append(item.li);
    finish(item, "done", seconds);
  }
  for (const level of report.levels) {
    const item = step({ level: level.level, start: 0 }, `level-${level.level}`, `level ${level.level}`);
    levels.push(item);
    $("levels").append(item.li);
    finish(item, level.accepted ? "done" : "rolled back", level.seconds);
  }
  $("levels-empty").hidden = report.levels.length > 0;
}

// Reads the job; null, with the reason shown (`notFound` for a 404), when it cannot.
async function fetchJob(notFound) {
  try {
    return await api(jobPath);
  } catch (err) {
    if (err instanceof AuthError) askKey(keyRefused());
    else if (err instanceof ApiError && err.status === 404) {
      $("job-status").textContent = notFound;
      $("cancel").hidden = true;
      timeLeft.set(null, null);
    } else $("job-status").textContent = `Could not load the job: ${err.message}`;
    return null;
  }
}

async function followLive() {
  try {
    await followEvents(jobId, onEvent, new AbortController().signal);
  } catch (err) {
    if (!(err instanceof AuthError)) throw err;
    askKey(keyRefused()); // revoked while the page followed the job
    return;
  }
  // The stream ends with the job's final event, or with the job itself: a deleted job has no state left to show.
  const job = await fetchJob("This job was deleted.");
  if (!job) return;
  showJob(job);
  await showResults(job);
}

async function load() {
  const job = await fetchJob(`There is no job ${jobId} (or it belongs to another API key).`);
  if (!job) return;
  $("job-status").textContent = "";
  showJob(job);
  if (!TERMINAL.has(job.state)) {
    followLive().catch((err) => {
      $("job-status").textContent = `Could not show the job: ${err.message}`;
    });
  } else if (job.state === "succeeded") {
    try {
      showSecondsAsStages(job, await api(`${jobPath}/report`));
    } catch {
      // the report is shown (or its error) by showResults
    }
    await showResults(job);
  }
}

$("cancel").addEventListener("click", async () => {
  const button = $("cancel");
  button.disabled = true;
  try {
    const job = await api(`${jobPath}:cancel`, { method: "POST" });
    $("message").textContent = job.state === "cancelled" ? "Cancelled." : "Cancelling\u2026";
  } catch (err) {
    $("job-status").textContent = `Could not cancel: ${err.message}`;
  } finally {
    button.disabled = false;
  }
});

load();
