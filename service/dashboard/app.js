// The dashboard: a jobs list and a job view, refreshed by polling the /v1 API (metrics with after_step).
"use strict";
const POLL_MS = 2000;
const TERMINAL = ["succeeded", "failed", "cancelled"];
let timer = null;

// ----- the API, with the bearer token kept for this browser session --------------------------------------
function token() { return sessionStorage.getItem("leco-token") || ""; }

async function api(path, options = {}) {
  const headers = Object.assign({}, options.headers || {});
  if (token()) headers.Authorization = `Bearer ${token()}`;
  const response = await fetch(path, Object.assign({}, options, { headers }));
  if (response.status === 401) {
    await askToken(token() ? "That token was refused." : "");
    return api(path, options);
  }
  if (!response.ok) {
    let detail = response.statusText, body = null;
    try { body = (await response.json()).detail; detail = JSON.stringify(body); } catch (e) { /* not JSON */ }
    // status, the parsed `detail` and Retry-After stay on the error: a 422 is shown field by field, a 429 retried
    throw Object.assign(new Error(`${response.status}: ${detail}`), {
      status: response.status, detail: body, retryAfter: Number(response.headers.get("Retry-After")) || null });
  }
  return response;
}
// An error as a person reads it: FastAPI's 422 list as "field: message" lines (the field's path without "body").
function problem(error) {
  if (Array.isArray(error.detail)) {
    return error.detail.map(d => `${(d.loc || []).filter(l => l !== "body").join(".") || "request"}: ${d.msg}`).join("\n");
  }
  return typeof error.detail === "string" ? `${error.status}: ${error.detail}` : error.message;
}
const getJson = async path => (await api(path)).json();
// The camera paths a render menu offers (GET /v1/camera-paths, the generated ones): fetched once, never typed out.
let pathKindsPromise = null;
const pathKinds = () => (pathKindsPromise ??= getJson("/v1/camera-paths").then(p => p.items.filter(k => k.generated)));
// The method registry (GET /v1/methods): names, labels, roles and phases; fetched once, never typed out here.
let methodsPromise = null;
const methodRegistry = () => (methodsPromise ??= getJson("/v1/methods").then(m => Object.fromEntries(m.items.map(i => [i.name, i]))));
const hasOccupancyPhase = (registry, job) => (registry[job.method]?.phases || []).includes("occupancy");

let tokenWaiters = [];
function askToken(message) {
  const dialog = document.getElementById("token-dialog");
  document.getElementById("token-error").textContent = message;
  if (!dialog.open) dialog.showModal();
  return new Promise(resolve => tokenWaiters.push(resolve));
}
document.getElementById("token-form").addEventListener("submit", () => {
  sessionStorage.setItem("leco-token", document.getElementById("token-input").value.trim());
  const waiting = tokenWaiters;
  tokenWaiters = [];
  waiting.forEach(resolve => resolve());
});

// ----- helpers --------------------------------------------------------------------------------------------
const esc = s => String(s ?? "").replace(/[&<>"']/g, c => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
const fmt = (v, digits = 2) => (v === null || v === undefined ? "–" : Number(v).toFixed(digits));
const eta = s => (s === null || s === undefined ? "" : `ETA ${Math.floor(s / 60)}m${String(Math.floor(s % 60)).padStart(2, "0")}s`);
const bytes = n => (n >= 2 ** 20 ? `${(n / 2 ** 20).toFixed(1)} MB` : n >= 1024 ? `${(n / 1024).toFixed(1)} kB` : `${n} B`);
const stateBadge = s => `<span class="state ${esc(s)}" data-state="${esc(s)}">${esc(s)}</span>`;
const progressBar = p => `<span class="progress" title="${fmt(p, 0)}%"><div style="width:${Math.min(100, p)}%"></div></span> ${fmt(p, 0)}%`;
function setStatus(text) { document.getElementById("status").textContent = text; }
function schedule(fn) { clearTimeout(timer); timer = setTimeout(fn, POLL_MS); }

async function blobUrl(url) { return URL.createObjectURL(await (await api(url)).blob()); }
async function download(url, name) {
  const a = document.createElement("a");
  a.href = await blobUrl(url);
  a.download = name;
  a.click();
}

// ----- jobs list ------------------------------------------------------------------------------------------
async function showJobs() {
  const view = document.getElementById("view");
  const [jobs, scenes] = await Promise.all([getJson("/v1/jobs?trains=true&limit=100"), getJson("/v1/scenes")]);
  const sceneName = Object.fromEntries(scenes.map(s => [s.id, s.name]));
  const rows = jobs.items.map(j => {
    const psnr = (j.latest_metrics[j.phase || ""] || {}).psnr;
    return `<tr class="job-row" data-job="${j.id}">
      <td>${j.id}</td><td>${stateBadge(j.state)}</td><td>${esc(j.method)}</td><td>${esc(sceneName[j.scene_id] || j.scene_id)}</td>
      <td>${esc(j.phase || "–")}</td><td>${progressBar(j.percent)} <span class="muted">${eta(j.eta_s)}</span></td>
      <td class="psnr">${fmt(psnr)}</td></tr>`;
  }).join("");
  view.innerHTML = `<h1>Jobs</h1><table id="jobs"><thead><tr><th>job</th><th>state</th><th>method</th><th>scene</th>
    <th>phase</th><th>progress</th><th>PSNR</th></tr></thead><tbody>${rows ||
    '<tr><td colspan="7" class="muted">No jobs yet: submit one with <code>leco submit</code>.</td></tr>'}</tbody></table>`;
  // A listener, not an inline onclick: the Content-Security-Policy allows no inline script.
  document.querySelector("#jobs tbody").addEventListener("click", event => {
    const row = event.target.closest("tr.job-row");
    if (row) location.hash = `#/jobs/${row.dataset.job}`;
  });
  setStatus(`${jobs.total} jobs · updated ${new Date().toLocaleTimeString()}`);
  schedule(route);
}

// ----- one job --------------------------------------------------------------------------------------------
const jobState = { id: null, series: {}, lastStep: -1, renderId: null, plyId: null, xAxis: "step", summaryId: null, evaluation: null };

function mergeSeries(fresh) {
  for (const s of fresh) {
    const key = `${s.phase}/${s.name}`;
    const have = jobState.series[key] || (jobState.series[key] = { phase: s.phase, name: s.name, points: [] });
    const last = have.points.length ? have.points[have.points.length - 1].step : -1;
    have.points.push(...s.points.filter(p => p.step > last));
    jobState.lastStep = Math.max(jobState.lastStep, ...s.points.map(p => p.step));
  }
}

function chartCard(title, names, phases) {
  const lines = [];
  for (const phase of phases) for (const name of names) {
    const s = jobState.series[`${phase}/${name}`];
    if (s) lines.push({ label: `${name} (${phase})`, points: s.points });
  }
  const card = document.createElement("div");
  card.className = "card chart-card";
  card.innerHTML = `<h3>${esc(title)}</h3>`;
  card.appendChild(lineChart(lines, { x: jobState.xAxis }));
  card.appendChild(legend(lines.map(l => l.label)));
  return card;
}

function latestOf(phase, name) {
  const s = jobState.series[`${phase}/${name}`];
  return s && s.points.length ? s.points[s.points.length - 1].value : null;
}

function occupancyStats(job, registry) {
  if (!hasOccupancyPhase(registry, job)) return "";
  const m = job.latest_metrics.occupancy || {};
  const experts = Object.keys(m).filter(k => /^fraction_expert_\d+$/.test(k)).sort()
    .map(k => `<dt>to scene expert ${k.split("_").pop()}</dt><dd>${fmt(100 * m[k], 1)}%</dd>`).join("");
  return `<div class="card" id="occupancy-stats"><h3>Occupancy phase (the paper's Fig. 5)</h3><dl class="stats">
    <dt>to the empty expert</dt><dd id="fraction-empty">${m.fraction_empty === undefined ? "–" : fmt(100 * m.fraction_empty, 1) + "%"}</dd>${experts}
    <dt>mean density: empty / scene</dt><dd>${fmt(m.density_empty, 4)} / ${fmt(m.density_scene, 4)} (ratio ${fmt(m.density_ratio, 3)})</dd>
    <dt>mean alpha: empty / scene</dt><dd>${fmt(m.alpha_empty, 4)} / ${fmt(m.alpha_scene, 4)} (ratio ${fmt(m.alpha_ratio, 3)})</dd>
    </dl></div>`;
}

// ----- a finished job's evaluation (summary.json): recall by height layer, what reached the main network -----
const pct = v => (v === null || v === undefined ? "–" : `${fmt(100 * v, 1)}%`);

async function loadEvaluation(job, artifacts) {
  if (!job.trains) return;  // a render job's summary.json describes its video
  const summary = artifacts.find(a => a.kind === "report" && a.name === "summary.json");
  if (!summary || jobState.summaryId === summary.id) return;
  try {
    const data = await getJson(summary.url);
    let rays = data.rays || null;
    if (!rays) {  // a summary without the block: the run's eval.json has it
      const evaluation = artifacts.find(a => a.kind === "report" && a.name === "eval.json");
      if (evaluation) rays = (await getJson(evaluation.url)).rays || null;
    }
    jobState.evaluation = { occupancy: data.occupancy || null, sampling: data.sampling || null, rays };
    jobState.summaryId = summary.id;
  } catch (e) {  // the card waits for the next poll; the rest of the page does not depend on it
    jobState.evaluation = null;
  }
}

function evaluationCard() {
  const e = jobState.evaluation;
  if (!e) return null;
  const occ = e.occupancy || {}, rays = e.rays || {}, sampling = e.sampling || {};
  const card = document.createElement("div");
  card.className = "card";
  card.id = "final-occupancy";
  const surface = rays.depth_source
    ? `<dt>surface bin kept</dt><dd id="surface-bin-kept">${pct(rays.surface_bin_kept)} of ${rays.surface_rays?.toLocaleString() ?? "–"} surface rays</dd>
       <dt>foreground opacity on them</dt><dd>${fmt(rays.foreground_opacity, 3)}</dd>
       <dt>surfaces from</dt><dd class="wrap">${esc(rays.depth_source)}</dd>`
    : `<dt>surfaces</dt><dd class="wrap">${esc(rays.surface_note || "not measured")}</dd>`;
  const top1 = occ.top1_recall === undefined ? "" : `<dt>recall, O's top-1 rule</dt><dd>${fmt(occ.top1_recall, 3)}</dd>`;
  card.innerHTML = `<h3>What reaches the main network (final evaluation)</h3><dl class="stats">
    <dt>occupancy ratio, validation rays</dt><dd id="rays-occupancy-ratio">${pct(rays.occupancy_ratio)}</dd>
    <dt>occupancy ratio, training mean</dt><dd>${pct(sampling.occupancy_ratio)}</dd>
    <dt>samples per hit ray</dt><dd>${fmt(rays.samples_per_hit_ray, 1)}</dd>
    <dt>rays that cross the box</dt><dd>${pct(rays.hit_ray_fraction)}</dd>${surface}
    <dt>recall (its rule)</dt><dd>${fmt(occ.recall, 3)}</dd>${top1}
    <dt>ground recall</dt><dd id="ground-recall">${fmt(occ.ground_recall, 3)}</dd></dl>
    <div class="muted wrap">${esc(rays.selection || "no validation rays counted")}; each hit ray cut into ${rays.bins ?? "–"} coarse bins</div>`;
  if (Array.isArray(occ.layers) && occ.layers.length) {
    const title = document.createElement("h3");
    title.textContent = "Recall by height layer";
    card.append(title, layerChart(occ.layers, occ.ground_recall));
  }
  return card;
}

async function refreshImages(artifacts) {
  const renders = artifacts.filter(a => a.kind === "render").sort((a, b) => (a.step ?? 0) - (b.step ?? 0) || a.id - b.id);
  const latest = renders[renders.length - 1];
  const img = document.getElementById("render");
  if (latest && img && latest.id !== jobState.renderId) {
    img.src = await blobUrl(latest.url);
    img.dataset.artifact = latest.id;
    document.getElementById("render-caption").textContent = `${latest.name} (step ${latest.step}): prediction | ground truth | depth`;
    jobState.renderId = latest.id;
  }
  const ply = artifacts.find(a => a.kind === "pointcloud");
  if (ply && ply.id !== jobState.plyId) {
    jobState.plyId = ply.id;
    const points = parsePly(await (await api(ply.url)).arrayBuffer());
    for (const view of ["top", "oblique"]) {
      const canvas = document.getElementById(`occupancy-${view}`);
      canvas.dataset.points = String(drawOccupancy(canvas, points, view));
    }
    document.getElementById("occupancy-caption").innerHTML =
      `${points.length.toLocaleString()} points of the occupancy, coloured by the main network
       (<a href="#" id="ply-download">download ${esc(ply.name)}</a>)`;
    document.getElementById("ply-download").onclick = e => { e.preventDefault(); download(ply.url, "occupancy.ply"); };
  }
}

async function showJob(id) {
  if (jobState.id !== id) {
    Object.assign(jobState, { id, series: {}, lastStep: -1, renderId: null, plyId: null, summaryId: null, evaluation: null });
  }
  const view = document.getElementById("view");
  const [job, artifacts, fresh] = await Promise.all([
    getJson(`/v1/jobs/${id}`), getJson(`/v1/jobs/${id}/artifacts`),
    getJson(`/v1/jobs/${id}/metrics?after_step=${jobState.lastStep}&max_points=5000`)]);
  mergeSeries(fresh.series);
  const phases = job.phases.map(p => p.name);
  if (!document.getElementById("job-view") || view.dataset.job !== String(id)) {
    view.dataset.job = String(id);
    Object.assign(jobState, { renderId: null, plyId: null });  // a rebuilt page (back from another view) loads its pictures again
    view.innerHTML = `<div id="job-view">
      <h1>Job ${id} <span id="job-state"></span></h1><div id="job-summary" class="muted"></div>
      <div class="toolbar"><button id="cancel" class="danger">Cancel job</button>
        <label>x axis <select id="x-axis"><option value="step">step</option><option value="wall_time_s">training time</option></select></label></div>
      <p id="job-error" class="error"></p>
      <table id="phases"><thead><tr><th>phase</th><th>state</th><th>progress</th></tr></thead><tbody></tbody></table>
      <div class="grid" id="charts"></div>
      <h2>Occupancy and throughput</h2><div class="grid" id="stats"></div>
      <div id="work-area"></div>
      <h2>Latest validation render</h2><div class="card"><img id="render" class="render" alt="no render yet"><div id="render-caption" class="muted">no render yet</div></div>
      <h2>Learned occupancy</h2><div class="grid"><div class="card"><h3>From above</h3><canvas id="occupancy-top" class="occupancy" width="480" height="360"></canvas></div>
        <div class="card"><h3>Oblique</h3><canvas id="occupancy-oblique" class="occupancy" width="480" height="360"></canvas></div></div>
      <div id="occupancy-caption" class="muted">no point cloud yet (written when the job finishes)</div>
      <h2>Artifacts</h2><table id="artifacts"><thead><tr><th>kind</th><th>name</th><th>step</th><th>size</th><th></th></tr></thead><tbody></tbody></table>
    </div>`;
    document.getElementById("x-axis").value = jobState.xAxis;
    document.getElementById("x-axis").onchange = e => { jobState.xAxis = e.target.value; showJob(id); };
    document.getElementById("cancel").onclick = async () => {
      document.getElementById("cancel").disabled = true;
      try { await api(`/v1/jobs/${id}/cancel`, { method: "POST" }); } catch (e) { document.getElementById("job-error").textContent = e.message; }
      showJob(id);
    };
  }
  document.getElementById("job-state").innerHTML = stateBadge(job.state);
  const parent = !job.trains && job.parent_id ? `${esc(job.kind)} of <a href="#/jobs/${job.parent_id}">job ${job.parent_id}</a> · ` : "";
  document.getElementById("job-summary").innerHTML = `${parent}${esc(job.method)} · profile ${esc(job.profile)} · phase ${esc(job.phase || "–")} ·
    step ${job.step}/${job.total_steps} · ${progressBar(job.percent)} ${eta(job.eta_s)} · attempt ${job.attempts}
    ${job.cancel_requested && !TERMINAL.includes(job.state) ? " · stopping (cancel requested)" : ""}`;
  document.getElementById("job-error").textContent = job.error ? `Error: ${job.error}` : "";
  // each phase (a training phase, or a poses job's stage) with its own share done
  document.querySelector("#phases tbody").innerHTML = job.phases.map(p => `<tr data-phase="${esc(p.name)}"><td>${esc(p.name)}</td>
    <td>${stateBadge(p.state)}</td><td>${progressBar(100 * p.step / Math.max(p.steps_total, 1))} <span class="muted">${p.step}/${p.steps_total}</span></td></tr>`).join("");
  document.getElementById("cancel").disabled = TERMINAL.includes(job.state) || job.cancel_requested;

  const charts = document.getElementById("charts");
  charts.replaceChildren(chartCard("Loss", ["loss"], phases), chartCard("PSNR (training batch)", ["psnr"], phases),
    chartCard("Throughput (rays/s)", ["rays_per_s"], phases), chartCard("Main-network samples per ray", ["samples_per_ray"], ["main"]));
  const registry = await methodRegistry();
  if (hasOccupancyPhase(registry, job)) charts.appendChild(chartCard("Fraction of points to the empty expert", ["fraction_empty"], ["occupancy"]));
  await loadEvaluation(job, artifacts);
  document.getElementById("stats").innerHTML = occupancyStats(job, registry) + `<div class="card" id="throughput"><h3>Throughput</h3><dl class="stats">
    <dt>rays/s (${esc(job.phase || "–")})</dt><dd>${fmt(job.rays_per_s, 0)}</dd>
    <dt>main-network samples per ray</dt><dd>${fmt(latestOf("main", "samples_per_ray"), 1)}</dd>
    <dt>occupancy ratio</dt><dd>${fmt(latestOf("main", "occupancy_ratio"), 3)}</dd>
    <dt>peak memory</dt><dd>${fmt(latestOf(job.phase || "main", "peak_memory_mb"), 0)} MB</dd></dl></div>`;
  const evaluation = evaluationCard();
  if (evaluation) document.getElementById("stats").appendChild(evaluation);
  document.querySelector("#artifacts tbody").innerHTML = artifacts.map(a => `<tr><td>${esc(a.kind)}</td><td>${esc(a.name)}</td>
    <td>${a.step ?? ""}</td><td>${bytes(a.size)}</td><td><a href="#" data-url="${esc(a.url)}" data-name="${esc(a.name.split("/").pop())}" class="dl">download</a></td></tr>`).join("");
  document.querySelectorAll("#artifacts a.dl").forEach(a => { a.onclick = e => { e.preventDefault(); download(a.dataset.url, a.dataset.name); }; });
  await refreshImages(artifacts);
  let rendering = false;
  if (job.trains && job.state === "succeeded") {  // renders and the viewer: of a finished training job only
    if (!document.getElementById("renders-card")) await buildWork(job);
    rendering = await refreshRenders();
  }
  setStatus(`job ${id} · updated ${new Date().toLocaleTimeString()}`);
  const evaluating = job.trains && job.state === "succeeded" && !jobState.summaryId;
  if (!TERMINAL.includes(job.state) || !jobState.plyId || rendering || evaluating) schedule(route);
}

// ----- a finished training job: renders (videos along a camera path) and the viewer -------------------------
// Media come as blobs (the API needs the token) and are shown through object URLs, revoked when the page
// leaves the job. The viewer keeps at most one view request in flight: a newer camera replaces a waiting one.
const VIEW_LOW = [80, 60], VIEW_SHARP = [320, 240], VIEW_REST_MS = 300, VIEW_FOV = 50;
const SIZES = ["160x120", "320x240", "640x480"];
const work = { jobId: null, urls: [], viewer: null, path: [] };

function keepUrl(url) { work.urls.push(url); return url; }

function leaveWork() {
  const v = work.viewer;
  if (v) {
    v.alive = false;
    clearTimeout(v.rest);
    clearTimeout(v.retry);
    if (v.url) URL.revokeObjectURL(v.url);
  }
  work.urls.forEach(url => URL.revokeObjectURL(url));
  Object.assign(work, { jobId: null, urls: [], viewer: null, path: [] });
}

async function buildWork(job) {
  // The cards are written before anything is awaited: a poll arriving meanwhile finds them and builds nothing.
  leaveWork();
  work.jobId = job.id;
  document.getElementById("work-area").innerHTML = `<h2>Renders and viewer</h2><div class="work">
    <div class="card" id="renders-card"><h3>Renders</h3>
      <form id="render-form">
        <label>path <select name="kind"></select></label>
        <label>frames <input name="frames" type="number" min="2" max="1200" step="1" value="120" required></label>
        <label>size <select name="size">${SIZES.map(s => `<option value="${s}"${s === "320x240" ? " selected" : ""}>${s}</option>`).join("")}</select></label>
        <label>fps <input name="fps" type="number" min="1" max="60" step="1" value="24" required></label>
        <label class="check"><input name="depth" type="checkbox"> depth video</label>
        <button type="submit">Render</button>
      </form>
      <p id="render-error" class="error"></p>
      <div id="render-list"><p class="muted">no renders yet</p></div>
    </div>
    <div class="card" id="viewer"><h3>Viewer</h3>
      <img id="viewer-image" alt="loading the view…" draggable="false" data-frames="0" data-size="">
      <div id="viewer-info" class="muted">drag to orbit, wheel to zoom</div>
      <div class="toolbar"><button id="add-camera" type="button">Add camera to path</button>
        <button id="render-path" type="button" disabled>Render path</button>
        <button id="clear-path" type="button">Clear path</button><button id="viewer-reset" type="button">Reset view</button></div>
      <ol id="path-cameras"></ol>
      <p id="path-hint" class="muted">Add two or more cameras: the path passes through them (the render's frames,
        size and fps are the form's).</p>
      <p id="path-error" class="error"></p>
    </div></div>`;
  const form = document.getElementById("render-form");
  pathKinds().then(kinds => {
    form.elements.kind.innerHTML = kinds.map(k => `<option value="${esc(k.kind)}" title="${esc(k.description)}">${esc(k.kind)}</option>`).join("");
  }).catch(e => { document.getElementById("render-error").textContent = problem(e); });
  form.addEventListener("submit", event => {
    event.preventDefault();
    submitRender(job.id, { path: { kind: form.elements.kind.value } }, "render-error");
  });
  document.getElementById("add-camera").addEventListener("click", () => {
    const v = work.viewer;
    if (!v) return;
    work.path.push(Object.assign(viewCamera(v), { orbit: Object.assign({}, v.orbit) }));
    showPath();
  });
  document.getElementById("clear-path").addEventListener("click", () => { work.path = []; showPath(); });
  document.getElementById("path-cameras").addEventListener("click", event => {
    const button = event.target.closest("button.remove-camera");
    if (!button) return;
    work.path.splice(Number(button.dataset.index), 1);
    showPath();
  });
  document.getElementById("render-path").addEventListener("click", () => submitRender(job.id, {
    path: { kind: "cameras", frame: "world", interpolate: true,
            cameras: work.path.map(c => ({ c2w: c.c2w, fov_deg: c.fov_deg })) } }, "path-error"));
  document.getElementById("render-list").addEventListener("click", event => {
    const cancel = event.target.closest("button.cancel-render");
    if (cancel) { cancelRender(Number(cancel.dataset.render)); return; }
    const link = event.target.closest("a.dl");
    if (link) { event.preventDefault(); download(link.dataset.url, link.dataset.name); }
  });
  showPath();
  let renders, layout;
  try {
    [renders, layout] = await Promise.all([
      getJson(`/v1/jobs/${job.id}/renders?limit=50`),
      getJson(`/v1/scenes/${job.scene_id}/cameras`).catch(() => null)]);  // without it: the unit box
  } catch (error) {  // the next poll builds the cards again
    if (work.jobId === job.id) { document.getElementById("work-area").innerHTML = ""; work.jobId = null; }
    throw error;
  }
  if (work.jobId !== job.id) return;
  renders.items.slice().reverse().forEach(addRenderItem);
  startViewer(job.id, layout);
}

// The form's settings (size, frames, fps, depth) with a path, POSTed as a render job of this training job.
async function submitRender(jobId, body, errorId) {
  const form = document.getElementById("render-form"), error = document.getElementById(errorId);
  const [width, height] = form.elements.size.value.split("x").map(Number);
  error.textContent = "";
  document.getElementById(errorId === "render-error" ? "path-error" : "render-error").textContent = "";
  const config = Object.assign({ frames: Number(form.elements.frames.value), width, height,
                                 fps: Number(form.elements.fps.value), appearance: "mean",
                                 depth_video: form.elements.depth.checked }, body);
  try {
    const render = await (await api(`/v1/jobs/${jobId}/renders`, {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(config) })).json();
    if (work.jobId !== jobId) return;
    addRenderItem(render);
    schedule(route);  // poll while it runs
  } catch (e) {
    error.textContent = problem(e);
  }
}

async function cancelRender(renderId) {
  const item = document.querySelector(`#render-list [data-render="${renderId}"]`);
  item.querySelector("button.cancel-render").disabled = true;
  try {
    await api(`/v1/jobs/${renderId}/cancel`, { method: "POST" });
  } catch (e) {
    item.querySelector(".render-error").textContent = problem(e);
  }
  schedule(route);
}

function describeRender(r) {
  const c = r.config || {}, path = c.path || {};
  return `${esc(path.kind)} · ${r.total_steps} frames · ${c.width}x${c.height} · ${c.fps} fps${c.depth_video ? " · depth" : ""}`;
}

function addRenderItem(r) {
  const list = document.getElementById("render-list");
  if (!list || list.querySelector(`[data-render="${r.id}"]`)) return;
  list.querySelector("p.muted")?.remove();
  const item = document.createElement("div");
  item.className = "render-item";
  item.dataset.render = String(r.id);
  item.innerHTML = `<div class="render-head"><a href="#/jobs/${r.id}">render ${r.id}</a> <span class="render-state"></span>
      <span class="muted">${describeRender(r)}</span></div>
    <div class="render-progress"></div><p class="error render-error"></p><div class="render-media"></div>`;
  list.prepend(item);  // newest first, as the API lists them
  updateRenderItem(item, r);
}

function updateRenderItem(item, r) {
  item.dataset.state = r.state;
  item.querySelector(".render-state").innerHTML = stateBadge(r.state);
  const spf = (r.latest_metrics.render || {}).seconds_per_frame;
  const perFrame = spf === undefined ? "" : ` · ${fmt(spf, 2)} s/frame`;
  const running = !TERMINAL.includes(r.state);
  item.querySelector(".render-progress").innerHTML = running
    ? `${progressBar(r.percent)} frame ${r.step}/${r.total_steps} <span class="muted">${eta(r.eta_s)}${perFrame}</span>
       <button class="cancel-render danger" type="button" data-render="${r.id}"${r.cancel_requested ? " disabled" : ""}>Cancel</button>
       ${r.cancel_requested ? '<span class="muted">stopping</span>' : ""}`
    : `<span class="muted">${r.step}/${r.total_steps} frames${perFrame}</span>`;
  item.querySelector(".render-error").textContent = r.error ? `Error: ${r.error}` : "";
}

// Polls the renders still running (GET /v1/jobs/{id}) and loads the video of each that succeeded; true while
// any is still queued or running.
async function refreshRenders() {
  const items = [...document.querySelectorAll("#render-list .render-item")];
  await Promise.all(items.filter(item => !TERMINAL.includes(item.dataset.state)).map(async item => {
    updateRenderItem(item, await getJson(`/v1/jobs/${item.dataset.render}`));
  }));
  for (const item of items) {
    if (item.dataset.state === "succeeded" && !item.dataset.media) {
      item.dataset.media = "loading";
      loadRenderMedia(item).then(() => { item.dataset.media = "loaded"; }, e => {
        item.dataset.media = "failed";
        item.querySelector(".render-error").textContent = `could not load the video: ${problem(e)}`;
      });
    }
  }
  return items.some(item => !TERMINAL.includes(item.dataset.state));
}

async function loadRenderMedia(item) {
  const jobId = work.jobId;
  const artifacts = await getJson(`/v1/jobs/${item.dataset.render}/artifacts`);
  const mp4 = artifacts.find(a => a.content_type === "video/mp4" && !a.name.endsWith(".depth.mp4"));
  const poster = artifacts.find(a => a.name.endsWith(".poster.png"));
  const media = item.querySelector(".render-media");
  if (mp4) {
    const [posterUrl, videoUrl] = await Promise.all([poster ? blobUrl(poster.url) : null, blobUrl(mp4.url)]);
    if (work.jobId !== jobId || !item.isConnected) {  // the page moved on meanwhile
      [posterUrl, videoUrl].forEach(u => u && URL.revokeObjectURL(u));
      return;
    }
    const video = document.createElement("video");
    video.className = "render-video";
    Object.assign(video, { controls: true, loop: true, muted: true, defaultMuted: true, playsInline: true, preload: "auto" });
    video.setAttribute("playsinline", "");
    if (posterUrl) video.poster = keepUrl(posterUrl);
    video.src = keepUrl(videoUrl);
    media.appendChild(video);
  }
  const links = document.createElement("div");
  links.className = "links";
  links.innerHTML = artifacts.map(a => `<span><a href="#" class="dl" data-url="${esc(a.url)}"
    data-name="${esc(a.name.split("/").pop())}">${esc(a.name)}</a> <span class="muted">${bytes(a.size)}</span></span>`).join("");
  media.appendChild(links);
}

// ----- the viewer: orbit (azimuth, elevation, distance) around the centre of the scene's foreground box -----
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = a => { const n = Math.hypot(...a) || 1; return a.map(x => x / n); };
const rad = deg => deg * Math.PI / 180;

// OpenGL camera axes in the normalised world (z up): back from the target to the camera, right = z x back,
// up = back x right; c2w's columns are right, up, back and the centre.
function viewCamera(v) {
  const { azimuth, elevation, distance } = v.orbit;
  const back = [Math.cos(rad(elevation)) * Math.cos(rad(azimuth)), Math.cos(rad(elevation)) * Math.sin(rad(azimuth)),
                Math.sin(rad(elevation))];
  const centre = v.target.map((t, i) => t + distance * back[i]);
  const right = unit(cross([0, 0, 1], back)), up = cross(back, right);
  return { c2w: [0, 1, 2].map(i => [right[i], up[i], back[i], centre[i]]), fov_deg: v.fov };
}

function startViewer(jobId, layout) {
  const [lo, hi] = layout ? layout.aabb : [[-1, -1, -1], [1, 1, 1]];
  const target = lo.map((l, i) => (l + hi[i]) / 2);
  const halfDiagonal = Math.hypot(...lo.map((l, i) => (hi[i] - l) / 2));
  // Start from the side the training cameras are on (their mean centre), 35° above the horizon.
  const train = layout ? layout.cameras.filter(c => c.split === "train") : [];
  const mean = [0, 1].map(i => train.reduce((s, c) => s + c.center[i] - target[i], 0) / (train.length || 1));
  const azimuth = Math.hypot(...mean) > 0.05 * halfDiagonal ? Math.atan2(mean[1], mean[0]) * 180 / Math.PI : -90;
  const home = { azimuth, elevation: 35, distance: 1.6 * halfDiagonal / Math.sin(rad(VIEW_FOV / 2)) };
  const v = { jobId, target, fov: VIEW_FOV, home, orbit: Object.assign({}, home), alive: true, img: document.getElementById("viewer-image"),
              info: document.getElementById("viewer-info"), seq: 0, shownSeq: 0, busy: false, pending: null,
              lastKey: null, rest: null, retry: null, drag: null, frames: 0, url: null };
  work.viewer = v;
  const img = v.img;
  img.addEventListener("pointerdown", event => {
    if (event.button !== 0) return;
    event.preventDefault();
    img.setPointerCapture(event.pointerId);
    img.classList.add("dragging");
    v.drag = { x: event.clientX, y: event.clientY };
  });
  img.addEventListener("pointermove", event => {
    if (!v.drag) return;
    const dx = event.clientX - v.drag.x, dy = event.clientY - v.drag.y;
    v.drag = { x: event.clientX, y: event.clientY };
    v.orbit.azimuth = (v.orbit.azimuth - 0.4 * dx) % 360;
    v.orbit.elevation = Math.max(-85, Math.min(85, v.orbit.elevation + 0.3 * dy));
    interact(v);
  });
  const release = () => { if (v.drag) { v.drag = null; img.classList.remove("dragging"); interact(v, false); } };
  img.addEventListener("pointerup", release);
  img.addEventListener("pointercancel", release);
  img.addEventListener("wheel", event => {
    event.preventDefault();
    const d = v.orbit.distance * Math.exp(0.0015 * Math.max(-300, Math.min(300, event.deltaY)));
    v.orbit.distance = Math.max(0.05 * v.home.distance, Math.min(10 * v.home.distance, d));
    interact(v);
  }, { passive: false });
  document.getElementById("viewer-reset").addEventListener("click", () => {
    v.orbit = Object.assign({}, v.home);
    interact(v, false);
  });
  requestView(v, VIEW_SHARP);
}

// While the camera moves: low-resolution frames; once it has rested VIEW_REST_MS, a sharp one.
function interact(v, moving = true) {
  if (moving) requestView(v, VIEW_LOW);
  clearTimeout(v.rest);
  v.rest = setTimeout(() => requestView(v, VIEW_SHARP), moving ? VIEW_REST_MS : 0);
}

function requestView(v, [width, height]) {
  const camera = viewCamera(v), key = JSON.stringify([camera, width, height]);
  if (!v.alive || key === v.lastKey) return;  // that very frame is already asked for
  v.lastKey = key;
  v.pending = { camera, key, cameraKey: JSON.stringify(camera), width, height, sharp: width >= VIEW_SHARP[0], seq: ++v.seq };
  if (!v.busy) pumpView(v);
}

async function pumpView(v) {
  if (!v.alive || !v.pending || v.busy) return;
  const want = v.pending;
  v.pending = null;
  v.busy = true;
  let wait = 0;
  try {
    const response = await api(`/v1/jobs/${v.jobId}/view`, { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ camera: want.camera, frame: "world", width: want.width, height: want.height }) });
    const png = await response.blob();
    // Stale answers are dropped: one older than the frame shown, for a page that moved on, or a sharp frame of
    // a camera the user has since moved away from (its low-resolution successor is on its way).
    const moved = v.pending && v.pending.cameraKey !== want.cameraKey;
    if (v.alive && want.seq > v.shownSeq && !(want.sharp && moved)) {
      await showFrame(v, want, png, Number(response.headers.get("X-Render-Seconds")));
    }
  } catch (error) {
    if (error.status === 429) {  // the renderers are busy: ask again (for the newest camera) after Retry-After
      wait = 1000 * (error.retryAfter || 1);
      if (!v.pending) v.pending = want;
      if (v.alive) v.info.textContent = "the view renderers are busy: trying again…";
    } else if (v.alive) {
      v.info.textContent = `view failed: ${problem(error)}`;
      v.lastKey = null;  // the same camera may be asked for again
    }
  }
  if (wait) {
    v.retry = setTimeout(() => { v.busy = false; pumpView(v); }, wait);
    return;
  }
  v.busy = false;
  pumpView(v);
}

async function showFrame(v, want, png, seconds) {
  const url = URL.createObjectURL(png);
  v.img.src = url;
  try {
    await v.img.decode();
  } catch (e) {
    URL.revokeObjectURL(url);
    return;
  }
  if (!v.alive) { URL.revokeObjectURL(url); return; }
  if (v.url) URL.revokeObjectURL(v.url);
  v.url = url;
  v.shownSeq = want.seq;
  v.frames += 1;
  v.img.dataset.frames = String(v.frames);
  v.img.dataset.size = `${want.width}x${want.height}`;
  v.img.alt = `the view from azimuth ${fmt(v.orbit.azimuth, 0)}°, elevation ${fmt(v.orbit.elevation, 0)}°`;
  v.info.textContent = `${want.width}x${want.height} rendered in ${fmt(seconds, 3)} s · azimuth ${fmt(v.orbit.azimuth, 0)}°,
    elevation ${fmt(v.orbit.elevation, 0)}°, distance ${fmt(v.orbit.distance, 2)} · drag to orbit, wheel to zoom`;
}

function showPath() {
  document.getElementById("path-cameras").innerHTML = work.path.map((c, i) => `<li>camera ${i + 1}: azimuth
    ${fmt(c.orbit.azimuth, 0)}°, elevation ${fmt(c.orbit.elevation, 0)}°, distance ${fmt(c.orbit.distance, 2)}
    <button class="remove-camera" type="button" data-index="${i}" title="remove">×</button></li>`).join("");
  document.getElementById("render-path").disabled = work.path.length < 2;
}

// ----- scenes: list, cameras and bounds from above, and a comparison of the jobs on one scene ---------------
async function showScenes() {
  const scenes = await getJson("/v1/scenes");
  document.getElementById("view").innerHTML = `<h1>Scenes</h1><table id="scenes"><thead><tr><th>scene</th><th>state</th>
    <th>format</th><th>cameras</th><th>source</th><th></th></tr></thead><tbody>${scenes.map(s => `<tr data-scene="${s.id}">
    <td><a href="#/scenes/${s.id}">${esc(s.name)}</a></td><td>${stateBadge(s.state)}</td><td>${esc(s.format || "–")}</td>
    <td>${s.cameras ?? "–"}</td><td>${esc(s.source)}${s.poses_job ? ` (<a href="#/jobs/${s.poses_job}">poses job ${s.poses_job}</a>)` : ""}</td>
    <td><a href="#/compare/${s.id}">compare jobs</a></td></tr>`).join("")}</tbody></table>`;
  setStatus(`${scenes.length} scenes · updated ${new Date().toLocaleTimeString()}`);
  if (scenes.some(s => s.state === "generating" || s.state === "posing")) schedule(route);
}

async function showScene(id) {
  const [scene, layout] = await Promise.all([getJson(`/v1/scenes/${id}`), getJson(`/v1/scenes/${id}/cameras`)]);
  const [lo, hi] = layout.aabb;
  const xs = layout.cameras.map(c => c.center[0]).concat([lo[0], hi[0]]);
  const ys = layout.cameras.map(c => c.center[1]).concat([lo[1], hi[1]]);
  const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const pad = 0.08 * Math.max(x1 - x0, y1 - y0), size = 560;
  const scale = size / (Math.max(x1 - x0, y1 - y0) + 2 * pad);
  const sx = x => (x - x0 + pad) * scale, sy = y => (y1 - y + pad) * scale;  // north up
  const arrows = layout.cameras.map(c => {
    const [x, y] = [sx(c.center[0]), sy(c.center[1])], len = Math.hypot(c.forward[0], c.forward[1]) || 1;
    const [dx, dy] = [c.forward[0] / len * 14, -c.forward[1] / len * 14];
    const colour = c.split === "train" ? "#2f6fde" : "#d9480f";
    return `<g class="camera" data-split="${esc(c.split)}"><circle cx="${x.toFixed(1)}" cy="${y.toFixed(1)}" r="3" fill="${colour}"/>
      <line x1="${x.toFixed(1)}" y1="${y.toFixed(1)}" x2="${(x + dx).toFixed(1)}" y2="${(y + dy).toFixed(1)}" stroke="${colour}"/></g>`;
  }).join("");
  const box = `<rect id="bounds" x="${sx(lo[0])}" y="${sy(hi[1])}" width="${(hi[0] - lo[0]) * scale}" height="${(hi[1] - lo[1]) * scale}"
    fill="rgba(31,138,76,.08)" stroke="#1f8a4c" stroke-dasharray="4 3"/>`;
  const splits = [...new Set(layout.cameras.map(c => c.split))];
  document.getElementById("view").innerHTML = `<h1>Scene ${esc(scene.name)} ${stateBadge(scene.state)}</h1>
    <p class="muted">${esc(scene.format)} · ${scene.cameras} cameras · ${esc(scene.source)} ·
      <a href="#/compare/${scene.id}">compare the jobs on this scene</a></p>
    <div class="card" style="max-width:${size + 40}px"><h3>From above: cameras (${splits.map(s => `${s} ${s === "train" ? "blue" : "orange"}`).join(", ")})
      and the automatic foreground box (green)</h3>
      <svg id="scene-map" viewBox="0 0 ${(x1 - x0 + 2 * pad) * scale} ${(y1 - y0 + 2 * pad) * scale}" style="width:100%">${box}${arrows}</svg>
      <p class="muted">${esc(layout.frame)}; box z from ${fmt(lo[2], 3)} to ${fmt(hi[2], 3)}</p></div>
    <h2>Bounds</h2><div class="card" id="bounds-info"><dl class="stats">
      <dt>size (source units)</dt><dd>${(scene.bounds.size_source || []).map(v => fmt(v, 1)).join(" x ")}</dd>
      <dt>evidence</dt><dd>${esc(scene.bounds.evidence)} (${scene.bounds.evidence_points ?? "–"} points)</dd>
      <dt>rays hitting the box</dt><dd>${fmt(100 * ((scene.bounds.rays || {}).fraction_hitting_foreground ?? NaN), 1)}%</dd>
      <dt>rule</dt><dd class="wrap">${esc(scene.bounds.rule)}</dd></dl></div>`;
  setStatus(`scene ${scene.name}`);
}

// Moving average over `k` points: the training-batch PSNR is noisy, and "first time it reaches X" must not
// be decided by one lucky batch.
function smooth(points, k = 5) {
  return points.map((p, i) => {
    const window = points.slice(Math.max(0, i - k + 1), i + 1);
    return Object.assign({}, p, { value: window.reduce((s, q) => s + q.value, 0) / window.length });
  });
}

async function showCompare(sceneId) {
  const [scene, jobs] = await Promise.all([getJson(`/v1/scenes/${sceneId}`), getJson(`/v1/jobs?trains=true&scene=${sceneId}&limit=200`)]);
  // Validation PSNR (jobs submitted with eval_every_s) when every job has it; else the training batch's, smoothed.
  const fetched = [];
  for (const job of jobs.items) {
    const series = name => getJson(`/v1/jobs/${job.id}/metrics?phase=main&name=${name}&max_points=2000`).then(m => m.series[0]);
    const [val, train, samples, speed] = await Promise.all(["val_psnr", "psnr", "samples_per_ray", "rays_per_s"].map(series));
    const mean = s => s && s.points.length ? s.points.reduce((a, p) => a + p.value, 0) / s.points.length : NaN;
    fetched.push({ job, val: val && val.points.length ? val.points : null, train: train && train.points.length ? train.points : null,
                   samplesPerRay: mean(samples), raysPerS: mean(speed) });
  }
  const useVal = fetched.some(f => f.train) && fetched.every(f => f.val || !f.train);
  const runs = fetched.filter(f => useVal ? f.val : f.train)
    .map(f => ({ job: f.job, points: useVal ? f.val : smooth(f.train), samplesPerRay: f.samplesPerRay, raysPerS: f.raysPerS }));
  // Equal PSNR: the best smoothed PSNR that every run reached; each run's first training time at or above it.
  const target = runs.length ? Math.min(...runs.map(r => Math.max(...r.points.map(p => p.value)))) : null;
  const reach = r => (r.points.find(p => p.value >= target) || {}).wall_time_s ?? null;
  const registry = await methodRegistry();
  // each family has its own "ours" (LeCO on Switch-NeRF, on hash grids): the first one compared here
  const ours = Object.values(registry).find(m => m.role === "ours" && runs.some(r => r.job.method === m.name));
  const leco = ours && runs.find(r => r.job.method === ours.name);
  const rows = runs.map(r => {
    const t = reach(r), speedup = leco && t && reach(leco) ? t / reach(leco) : null;
    return `<tr data-job="${r.job.id}"><td><a href="#/jobs/${r.job.id}">${r.job.id}</a></td><td>${esc(r.job.method)}</td>
      <td>${stateBadge(r.job.state)}</td><td>${fmt(r.points[r.points.length - 1].value)}</td><td>${fmt(t, 1)}</td>
      <td class="speedup">${r === leco || speedup === null ? "–" : `${fmt(speedup, 2)}x`}</td></tr>`;
  }).join("");
  const view = document.getElementById("view");
  view.innerHTML = `<h1>Compare jobs on ${esc(scene.name)}</h1>
    <p class="muted">${useVal ? "Validation PSNR of the main phase (jobs submitted with eval_every_s; Mega-NeRF's protocol: " +
        "right halves of the validation views scored, their appearance embeddings fitted on the left halves)"
      : "Training-batch PSNR of the main phase (moving average of 5 points; submit with eval_every_s for validation PSNR)"}
      against training time; LeCO's time includes its occupancy phase, as in the paper's Fig. 9.</p>
    <div class="card" id="compare-chart"><h3>PSNR against training time (s)</h3></div>
    <h2>Speed against error</h2>
    <p class="muted">Each job's last PSNR against its mean main-network samples per ray and rays/s (log scale); jobs of
      one method at different sampling budgets (<code>leco bench --sweep</code> settings) trace its Pareto curve.</p>
    <div class="row"><div class="card" id="pareto-samples"><h3>PSNR against samples per ray</h3></div>
      <div class="card" id="pareto-speed"><h3>PSNR against rays/s</h3></div></div>
    <h2>Speed-up at equal PSNR${target === null ? "" : ` (${fmt(target)} dB, the best all runs reached)`}</h2>
    <table id="compare"><thead><tr><th>job</th><th>method</th><th>state</th><th>last PSNR</th><th>time to ${fmt(target)} dB (s)</th>
      <th>LeCO's speed-up</th></tr></thead><tbody>${rows || '<tr><td colspan="6" class="muted">no jobs with main-phase metrics yet</td></tr>'}</tbody></table>`;
  const card = document.getElementById("compare-chart");
  card.appendChild(lineChart(runs.map(r => ({ label: `${r.job.method} (job ${r.job.id})`, points: r.points })), { x: "wall_time_s" }));
  card.appendChild(legend(runs.map(r => `${r.job.method} (job ${r.job.id})`)));
  const methods = [...new Set(runs.map(r => r.job.method))];
  for (const [id, key, xLabel] of [["pareto-samples", "samplesPerRay", "samples per ray"], ["pareto-speed", "raysPerS", "rays/s"]]) {
    const points = runs.map(r => ({ x: r[key], y: r.points[r.points.length - 1].value, group: r.job.method,
                                    label: `${r.job.method} (job ${r.job.id}): ${fmt(r[key], 1)} ${xLabel}, ${fmt(r.points[r.points.length - 1].value)} dB` }));
    const box = document.getElementById(id);
    box.appendChild(scatterChart(points, { xLabel: `${xLabel} (log)`, logX: true, groups: methods }));
    box.appendChild(legend(methods));
  }
  setStatus(`${runs.length} runs on ${scene.name} · updated ${new Date().toLocaleTimeString()}`);
  if (runs.some(r => !TERMINAL.includes(r.job.state))) schedule(route);
}

// ----- routing --------------------------------------------------------------------------------------------
async function route() {
  clearTimeout(timer);
  const hash = location.hash, id = (hash.match(/\/(\d+)$/) || [])[1];
  if (!(hash.startsWith("#/jobs/") && Number(id) === work.jobId)) leaveWork();
  try {
    if (hash.startsWith("#/jobs/") && id) await showJob(Number(id));
    else if (hash.startsWith("#/scenes/") && id) await showScene(Number(id));
    else if (hash.startsWith("#/scenes")) await showScenes();
    else if (hash.startsWith("#/compare/") && id) await showCompare(Number(id));
    else await showJobs();
  } catch (error) {
    setStatus(`error: ${error.message} (retrying)`);
    schedule(route);
  }
}
window.addEventListener("hashchange", route);
route();
