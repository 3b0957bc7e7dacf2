// Line charts as plain SVG (no library, works offline): lineChart(series, {x: "step" | "wall_time_s", title}).
"use strict";
const COLORS = ["#2f6fde", "#d9480f", "#1f8a4c", "#862e9c", "#b7791f", "#0b7285", "#c0392b", "#5c677d"];

function niceNumber(v) {
  if (v === null || v === undefined || !isFinite(v)) return "–";
  const a = Math.abs(v);
  if (a !== 0 && (a >= 1e5 || a < 1e-3)) return v.toExponential(2);
  return a >= 100 ? v.toFixed(0) : a >= 1 ? v.toFixed(2) : v.toFixed(4);
}

function lineChart(series, options) {
  const W = 420, H = 220, L = 52, R = 10, T = 10, B = 30;
  const xKey = options.x || "step";
  const lines = series.map(s => ({ label: s.label, points: s.points.filter(p => p[xKey] !== null && isFinite(p.value)) }))
                      .filter(s => s.points.length);
  const all = lines.flatMap(s => s.points);
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.setAttribute("class", "chart");
  svg.dataset.points = String(all.length);
  if (!all.length) {
    svg.innerHTML = `<text x="${W / 2}" y="${H / 2}" text-anchor="middle">no points yet</text>`;
    return svg;
  }
  let [x0, x1] = [Math.min(...all.map(p => p[xKey])), Math.max(...all.map(p => p[xKey]))];
  let [y0, y1] = [Math.min(...all.map(p => p.value)), Math.max(...all.map(p => p.value))];
  if (x1 === x0) x1 = x0 + 1;
  if (y1 === y0) { y0 -= 0.5; y1 += 0.5; }
  const sx = x => L + (x - x0) / (x1 - x0) * (W - L - R), sy = y => H - B - (y - y0) / (y1 - y0) * (H - T - B);
  let body = `<line x1="${L}" y1="${H - B}" x2="${W - R}" y2="${H - B}" stroke="#ccc"/><line x1="${L}" y1="${T}" x2="${L}" y2="${H - B}" stroke="#ccc"/>`;
  for (const f of [0, 0.5, 1]) {
    const yv = y0 + f * (y1 - y0), xv = x0 + f * (x1 - x0);
    body += `<text x="${L - 4}" y="${sy(yv) + 3}" text-anchor="end">${niceNumber(yv)}</text>`;
    body += `<text x="${sx(xv)}" y="${H - B + 14}" text-anchor="middle">${niceNumber(xv)}</text>`;
  }
  body += `<text x="${(L + W - R) / 2}" y="${H - 3}" text-anchor="middle">${xKey === "step" ? "step" : "training time (s)"}</text>`;
  lines.forEach((s, i) => {
    const d = s.points.map(p => `${sx(p[xKey]).toFixed(1)},${sy(p.value).toFixed(1)}`).join(" ");
    body += `<polyline fill="none" stroke="${COLORS[i % COLORS.length]}" stroke-width="1.6" points="${d}"><title>${s.label}</title></polyline>`;
  });
  svg.innerHTML = body;
  return svg;
}

// Points as markers, one colour per group: scatterChart(points [{x, y, group, label}], {xLabel, logX, groups}).
function scatterChart(points, options) {
  const W = 420, H = 220, L = 52, R = 10, T = 10, B = 30;
  const shown = points.filter(p => isFinite(p.x) && isFinite(p.y) && (!options.logX || p.x > 0));
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.setAttribute("class", "chart scatter");
  svg.dataset.points = String(shown.length);
  if (!shown.length) {
    svg.innerHTML = `<text x="${W / 2}" y="${H / 2}" text-anchor="middle">no finished points yet</text>`;
    return svg;
  }
  const fx = options.logX ? Math.log10 : x => x;
  let [x0, x1] = [Math.min(...shown.map(p => fx(p.x))), Math.max(...shown.map(p => fx(p.x)))];
  let [y0, y1] = [Math.min(...shown.map(p => p.y)), Math.max(...shown.map(p => p.y))];
  if (x1 === x0) { x0 -= 0.5; x1 += 0.5; }
  if (y1 === y0) { y0 -= 0.5; y1 += 0.5; }
  const sx = x => L + (fx(x) - x0) / (x1 - x0) * (W - L - R - 20) + 10;
  const sy = y => H - B - 8 - (y - y0) / (y1 - y0) * (H - T - B - 16);
  let body = `<line x1="${L}" y1="${H - B}" x2="${W - R}" y2="${H - B}" stroke="#ccc"/><line x1="${L}" y1="${T}" x2="${L}" y2="${H - B}" stroke="#ccc"/>`;
  for (const f of [0, 0.5, 1]) {
    const yv = y0 + f * (y1 - y0), xv = x0 + f * (x1 - x0);
    body += `<text x="${L - 4}" y="${sy(yv) + 3}" text-anchor="end">${niceNumber(yv)}</text>`;
    body += `<text x="${L + 10 + f * (W - L - R - 20)}" y="${H - B + 14}" text-anchor="middle">${niceNumber(options.logX ? 10 ** xv : xv)}</text>`;
  }
  body += `<text x="${(L + W - R) / 2}" y="${H - 3}" text-anchor="middle">${options.xLabel}</text>`;
  const groups = options.groups || [...new Set(shown.map(p => p.group))];
  for (const p of shown) {
    const colour = COLORS[groups.indexOf(p.group) % COLORS.length];
    body += `<circle cx="${sx(p.x).toFixed(1)}" cy="${sy(p.y).toFixed(1)}" r="4" fill="${colour}"><title>${p.label}</title></circle>`;
  }
  svg.innerHTML = body;
  return svg;
}

function legend(labels) {
  const div = document.createElement("div");
  div.className = "legend";
  div.innerHTML = labels.map((l, i) => `<span><i style="background:${COLORS[i % COLORS.length]}"></i>${l}</span>`).join("");
  return div;
}

// The occupied points of a binary little-endian PLY (x, y, z float32; r, g, b, a uint8), as in occupancy.ply.
function parsePly(buffer) {
  const bytes = new Uint8Array(buffer);
  const text = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 2048)));
  const end = text.indexOf("end_header\n");
  const count = Number((text.match(/element vertex (\d+)/) || [])[1] || 0);
  if (end < 0 || !count) return [];
  const view = new DataView(buffer, end + "end_header\n".length);
  const points = [];
  for (let i = 0; i < count; i++) {
    const o = i * 16;
    points.push([view.getFloat32(o, true), view.getFloat32(o + 4, true), view.getFloat32(o + 8, true),
                 view.getUint8(o + 12), view.getUint8(o + 13), view.getUint8(o + 14), view.getUint8(o + 15)]);
  }
  return points;
}

// Top-down (x, y) or oblique projection of the points on a canvas; z is up (the scenes' world convention).
function drawOccupancy(canvas, points, view) {
  const ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height;
  ctx.fillStyle = "#10131a";
  ctx.fillRect(0, 0, W, H);
  const shown = points;  // the PLY holds only points the occupancy keeps; alpha sets how solid each looks
  if (!shown.length) return 0;
  const project = view === "top" ? p => [p[0], -p[1], p[2]]
    : p => [p[0] * 0.8 - p[1] * 0.6, -(p[2] * 0.9 + (p[0] * 0.6 + p[1] * 0.8) * 0.35), p[0] * 0.6 + p[1] * 0.8];
  const xy = shown.map(project);
  const xs = xy.map(q => q[0]), ys = xy.map(q => q[1]);
  const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const scale = 0.92 * Math.min(W / ((x1 - x0) || 1), H / ((y1 - y0) || 1));
  const order = xy.map((q, i) => i).sort((a, b) => (view === "top" ? shown[a][2] - shown[b][2] : xy[b][2] - xy[a][2]));
  for (const i of order) {
    const p = shown[i], q = xy[i];
    ctx.fillStyle = `rgba(${p[3]},${p[4]},${p[5]},${Math.max(0.25, p[6] / 255)})`;
    ctx.fillRect(W / 2 + (q[0] - (x0 + x1) / 2) * scale, H / 2 + (q[1] - (y0 + y1) / 2) * scale, 2, 2);
  }
  return shown.length;
}

// Recall by height layer as horizontal bars, the top layer at the top (z is up): layerChart(layers, ground).
// `layers`: [{z_min, z_max, reference_cells, recall}] bottom first, as summary.json's occupancy.layers.
function layerChart(layers, ground) {
  const W = 420, L = 92, R = 46, T = 8, ROW = 20, B = 26;
  const H = T + ROW * layers.length + B;
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.setAttribute("class", "chart layers");
  svg.dataset.layers = String(layers.length);
  const sx = r => L + r * (W - L - R);
  let body = `<line x1="${L}" y1="${T}" x2="${L}" y2="${H - B}" stroke="#ccc"/><line x1="${L}" y1="${H - B}" x2="${W - R}" y2="${H - B}" stroke="#ccc"/>`;
  for (const f of [0, 0.5, 1]) {
    body += `<line x1="${sx(f)}" y1="${T}" x2="${sx(f)}" y2="${H - B}" stroke="#eee"/><text x="${sx(f)}" y="${H - B + 12}" text-anchor="middle">${f}</text>`;
  }
  body += `<text x="${(L + W - R) / 2}" y="${H - 3}" text-anchor="middle">recall of occupied, observed cells${ground === null || ground === undefined ? "" : ` · ground ${ground.toFixed(2)}`}</text>`;
  layers.slice().reverse().forEach((layer, i) => {
    const y = T + i * ROW, label = `z ${layer.z_min.toFixed(2)}–${layer.z_max.toFixed(2)}`;
    body += `<text x="${L - 4}" y="${y + ROW / 2 + 3}" text-anchor="end">${label}</text>`;
    if (layer.recall === null || layer.recall === undefined) {  // no reference cell at that height
      body += `<text x="${L + 4}" y="${y + ROW / 2 + 3}">–</text>`;
      return;
    }
    const width = Math.max(0.5, sx(layer.recall) - L);
    body += `<rect x="${L}" y="${y + 3}" width="${width.toFixed(1)}" height="${ROW - 6}" fill="${COLORS[0]}"><title>${label}: ${layer.predicted_cells ?? "?"} of ${layer.reference_cells} cells</title></rect>`;
    body += `<text x="${(L + width + 4).toFixed(1)}" y="${y + ROW / 2 + 3}" class="layer-recall">${layer.recall.toFixed(2)}</text>`;
  });
  svg.innerHTML = body;
  return svg;
}
