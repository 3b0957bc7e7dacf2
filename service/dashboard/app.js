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
    let detail = response.statusText;
    try { detail = JSON.stringify((await response.json()).detail); } catch (e) { /* not JSON */ }
    throw new Error(`${response.status}: ${detail}`);
  }
  return response;
}
const getJson = async path => (await api(path)).json();

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
  const [jobs, scenes] = await Promise.all([getJson("/v1/jobs?limit=100"), getJson("/v1/scenes")]);
  const sceneName = Object.fromEntries(scenes.map(s => [s.id, s.name]));
  const rows = jobs.items.map(j => {
    const psnr = (j.latest_metrics[j.phase || ""] || {}).psnr;
    return `<tr class="job-row" data-job="${j.id}" onclick="location.hash='#/jobs/${j.id}'">
      <td>${j.id}</td><td>${stateBadge(j.state)}</td><td>${esc(j.method)}</td><td>${esc(sceneName[j.scene_id] || j.scene_id)}</td>
      <td>${esc(j.phase || "–")}</td><td>${progressBar(j.percent)} <span class="muted">${eta(j.eta_s)}</span></td>
      <td class="psnr">${fmt(psnr)}</td></tr>`;
  }).join("");
  view.innerHTML = `<h1>Jobs</h1><table id="jobs"><thead><tr><th>job</th><th>state</th><th>method</th><th>scene</th>
    <th>phase</th><th>progress</th><th>PSNR</th></tr></thead><tbody>${rows ||
    '<tr><td colspan="7" class="muted">No jobs yet: submit one with <code>leco submit</code>.</td></tr>'}</tbody></table>`;
  setStatus(`${jobs.total} jobs · updated ${new Date().toLocaleTimeString()}`);
  schedule(route);
}

// ----- one job --------------------------------------------------------------------------------------------
const jobState = { id: null, series: {}, lastStep: -1, renderId: null, plyId: null, xAxis: "step" };

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

function occupancyStats(job) {
  if (job.method !== "leco") return "";
  const m = job.latest_metrics.occupancy || {};
  const experts = Object.keys(m).filter(k => /^fraction_expert_\d+$/.test(k)).sort()
    .map(k => `<dt>to scene expert ${k.split("_").pop()}</dt><dd>${fmt(100 * m[k], 1)}%</dd>`).join("");
  return `<div class="card" id="occupancy-stats"><h3>Occupancy phase (the paper's Fig. 5)</h3><dl class="stats">
    <dt>to the empty expert</dt><dd id="fraction-empty">${m.fraction_empty === undefined ? "–" : fmt(100 * m.fraction_empty, 1) + "%"}</dd>${experts}
    <dt>mean density: empty / scene</dt><dd>${fmt(m.density_empty, 4)} / ${fmt(m.density_scene, 4)} (ratio ${fmt(m.density_ratio, 3)})</dd>
    <dt>mean alpha: empty / scene</dt><dd>${fmt(m.alpha_empty, 4)} / ${fmt(m.alpha_scene, 4)} (ratio ${fmt(m.alpha_ratio, 3)})</dd>
    </dl></div>`;
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
  if (jobState.id !== id) Object.assign(jobState, { id, series: {}, lastStep: -1, renderId: null, plyId: null });
  const view = document.getElementById("view");
  const [job, artifacts, fresh] = await Promise.all([
    getJson(`/v1/jobs/${id}`), getJson(`/v1/jobs/${id}/artifacts`),
    getJson(`/v1/jobs/${id}/metrics?after_step=${jobState.lastStep}&max_points=5000`)]);
  mergeSeries(fresh.series);
  const phases = job.phases.map(p => p.name);
  if (!document.getElementById("job-view") || view.dataset.job !== String(id)) {
    view.dataset.job = String(id);
    view.innerHTML = `<div id="job-view">
      <h1>Job ${id} <span id="job-state"></span></h1><div id="job-summary" class="muted"></div>
      <div class="toolbar"><button id="cancel" class="danger">Cancel job</button>
        <label>x axis <select id="x-axis"><option value="step">step</option><option value="wall_time_s">training time</option></select></label></div>
      <p id="job-error" class="error"></p>
      <div class="grid" id="charts"></div>
      <h2>Occupancy and throughput</h2><div class="grid" id="stats"></div>
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
  document.getElementById("job-summary").innerHTML = `${esc(job.method)} · profile ${esc(job.profile)} · phase ${esc(job.phase || "–")} ·
    step ${job.step}/${job.total_steps} · ${progressBar(job.percent)} ${eta(job.eta_s)} · attempt ${job.attempts}
    ${job.cancel_requested && !TERMINAL.includes(job.state) ? " · stopping (cancel requested)" : ""}`;
  document.getElementById("job-error").textContent = job.error ? `Error: ${job.error}` : "";
  document.getElementById("cancel").disabled = TERMINAL.includes(job.state) || job.cancel_requested;

  const charts = document.getElementById("charts");
  charts.replaceChildren(chartCard("Loss", ["loss"], phases), chartCard("PSNR (training batch)", ["psnr"], phases),
    chartCard("Throughput (rays/s)", ["rays_per_s"], phases), chartCard("Main-network samples per ray", ["samples_per_ray"], ["main"]));
  if (job.method === "leco") charts.appendChild(chartCard("Fraction of points to the empty expert", ["fraction_empty"], ["occupancy"]));
  document.getElementById("stats").innerHTML = occupancyStats(job) + `<div class="card" id="throughput"><h3>Throughput</h3><dl class="stats">
    <dt>rays/s (${esc(job.phase || "–")})</dt><dd>${fmt(job.rays_per_s, 0)}</dd>
    <dt>main-network samples per ray</dt><dd>${fmt(latestOf("main", "samples_per_ray"), 1)}</dd>
    <dt>occupancy ratio</dt><dd>${fmt(latestOf("main", "occupancy_ratio"), 3)}</dd>
    <dt>peak memory</dt><dd>${fmt(latestOf(job.phase || "main", "peak_memory_mb"), 0)} MB</dd></dl></div>`;
  document.querySelector("#artifacts tbody").innerHTML = artifacts.map(a => `<tr><td>${esc(a.kind)}</td><td>${esc(a.name)}</td>
    <td>${a.step ?? ""}</td><td>${bytes(a.size)}</td><td><a href="#" data-url="${esc(a.url)}" data-name="${esc(a.name.split("/").pop())}" class="dl">download</a></td></tr>`).join("");
  document.querySelectorAll("#artifacts a.dl").forEach(a => { a.onclick = e => { e.preventDefault(); download(a.dataset.url, a.dataset.name); }; });
  await refreshImages(artifacts);
  setStatus(`job ${id} · updated ${new Date().toLocaleTimeString()}`);
  if (!TERMINAL.includes(job.state) || !jobState.plyId) schedule(route);
}

// ----- routing --------------------------------------------------------------------------------------------
async function route() {
  clearTimeout(timer);
  const match = location.hash.match(/^#\/jobs\/(\d+)/);
  try {
    if (match) await showJob(Number(match[1])); else await showJobs();
  } catch (error) {
    setStatus(`error: ${error.message} (retrying)`);
    schedule(route);
  }
}
window.addEventListener("hashchange", route);
route();
