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
  const [jobs, scenes] = await Promise.all([getJson("/v1/jobs?limit=100"), getJson("/v1/scenes")]);
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
  const registry = await methodRegistry();
  if (hasOccupancyPhase(registry, job)) charts.appendChild(chartCard("Fraction of points to the empty expert", ["fraction_empty"], ["occupancy"]));
  document.getElementById("stats").innerHTML = occupancyStats(job, registry) + `<div class="card" id="throughput"><h3>Throughput</h3><dl class="stats">
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

// ----- scenes: list, cameras and bounds from above, and a comparison of the jobs on one scene ---------------
async function showScenes() {
  const scenes = await getJson("/v1/scenes");
  document.getElementById("view").innerHTML = `<h1>Scenes</h1><table id="scenes"><thead><tr><th>scene</th><th>state</th>
    <th>format</th><th>cameras</th><th>source</th><th></th></tr></thead><tbody>${scenes.map(s => `<tr data-scene="${s.id}">
    <td><a href="#/scenes/${s.id}">${esc(s.name)}</a></td><td>${stateBadge(s.state)}</td><td>${esc(s.format || "–")}</td>
    <td>${s.cameras ?? "–"}</td><td>${esc(s.source)}</td><td><a href="#/compare/${s.id}">compare jobs</a></td></tr>`).join("")}</tbody></table>`;
  setStatus(`${scenes.length} scenes · updated ${new Date().toLocaleTimeString()}`);
  if (scenes.some(s => s.state === "generating")) schedule(route);
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
  const [scene, jobs] = await Promise.all([getJson(`/v1/scenes/${sceneId}`), getJson(`/v1/jobs?scene=${sceneId}&limit=200`)]);
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
  const ours = Object.values(registry).find(m => m.role === "ours");
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
