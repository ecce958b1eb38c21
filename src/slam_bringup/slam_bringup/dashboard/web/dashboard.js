// The SLAM dashboard page: merges the sections the server sends over /ws and draws them.
'use strict';

const state = {};
const COLORS = {
  static: '#1f6fd1', moveable: '#d62728', seen: '#ff9f1c', path: '#555555',
  dynamic: '#d62728', pending: '#ffbf00', unknown: '#9e9e9e',
};
let lastUpdate = null;

function $(id) { return document.getElementById(id); }

function connect() {
  const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
  const socket = new WebSocket(`${scheme}://${location.host}/ws`);
  socket.onopen = () => { $('connection').textContent = 'live'; $('connection').className = 'good'; };
  socket.onmessage = (event) => {
    const message = JSON.parse(event.data);
    Object.assign(state, message.sections);
    lastUpdate = new Date();
    render(Object.keys(message.sections));
  };
  socket.onclose = () => {
    $('connection').textContent = 'disconnected: retrying';
    $('connection').className = 'bad';
    setTimeout(connect, 2000);
  };
}

// --- plots ----------------------------------------------------------------------------
// A view that fits the points (metres) into the canvas with equal axes and a margin.
function fitView(canvas, points, margin = 40) {
  let [x0, x1, y0, y1] = [Infinity, -Infinity, Infinity, -Infinity];
  for (const [x, y] of points) {
    x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
  }
  if (!isFinite(x0)) { [x0, x1, y0, y1] = [-1, 1, -1, 1]; }
  const span = Math.max(x1 - x0, y1 - y0, 1.0) * 1.1;
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  const scale = Math.min(canvas.width - 2 * margin, canvas.height - 2 * margin) / span;
  return {
    scale, margin,
    px: (x) => canvas.width / 2 + (x - cx) * scale,
    py: (y) => canvas.height / 2 - (y - cy) * scale,
    x0: cx - (canvas.width / 2) / scale, x1: cx + (canvas.width / 2) / scale,
    y0: cy - (canvas.height / 2) / scale, y1: cy + (canvas.height / 2) / scale,
  };
}

function niceStep(span) {
  const raw = span / 6, power = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const f of [1, 2, 5, 10]) { if (f * power >= raw) return f * power; }
  return 10 * power;
}

function drawAxes(ctx, view, xLabel, yLabel) {
  const canvas = ctx.canvas;
  ctx.strokeStyle = '#eeeeee'; ctx.fillStyle = '#777777'; ctx.lineWidth = 1;
  ctx.font = '11px sans-serif';
  const step = niceStep(Math.max(view.x1 - view.x0, view.y1 - view.y0));
  for (let x = Math.ceil(view.x0 / step) * step; x <= view.x1; x += step) {
    const p = view.px(x);
    ctx.beginPath(); ctx.moveTo(p, 0); ctx.lineTo(p, canvas.height); ctx.stroke();
    ctx.fillText(`${+x.toFixed(3)}`, p + 2, canvas.height - 4);
  }
  for (let y = Math.ceil(view.y0 / step) * step; y <= view.y1; y += step) {
    const p = view.py(y);
    ctx.beginPath(); ctx.moveTo(0, p); ctx.lineTo(canvas.width, p); ctx.stroke();
    ctx.fillText(`${+y.toFixed(3)}`, 2, p - 2);
  }
  const label = (text, x, y) => {
    const width = ctx.measureText(text).width;
    ctx.fillStyle = 'rgba(255, 255, 255, 0.9)'; ctx.fillRect(x - 2, y - 11, width + 4, 14);
    ctx.fillStyle = '#333333'; ctx.fillText(text, x, y);
  };
  label(xLabel, canvas.width - ctx.measureText(xLabel).width - 6, canvas.height - 18);
  label(yLabel, 6, 14);
}

function drawLine(ctx, view, points, color, width) {
  if (!points || points.length < 2) return;
  ctx.strokeStyle = color; ctx.lineWidth = width; ctx.beginPath();
  points.forEach(([x, y], i) => (i ? ctx.lineTo(view.px(x), view.py(y)) : ctx.moveTo(view.px(x), view.py(y))));
  ctx.stroke();
}

function drawMap() {
  const canvas = $('map-canvas'), ctx = canvas.getContext('2d');
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const landmarks = state.map ? state.map.landmarks : [];
  const path = state.path ? state.path.points : [];
  const moveable = state.moveable || [];
  const all = landmarks.map((l) => [l.x, l.y]).concat(path);
  moveable.forEach((m) => all.push(...m.seen));
  const view = fitView(canvas, all);
  drawAxes(ctx, view, 'x (m)', 'y (m)');
  drawLine(ctx, view, path, COLORS.path, 1.5);
  if (!landmarks.length) {
    ctx.fillStyle = '#777777'; ctx.fillText('no EM-SAM map yet (em_sam/landmarks)', 30, 40);
  }
  ctx.fillStyle = COLORS.seen;
  for (const m of moveable) {
    for (const [x, y] of m.seen) { ctx.beginPath(); ctx.arc(view.px(x), view.py(y), 3, 0, 2 * Math.PI); ctx.fill(); }
  }
  ctx.font = 'bold 11px sans-serif';
  for (const l of landmarks) {
    const x = view.px(l.x), y = view.py(l.y);
    ctx.fillStyle = l.moveable ? COLORS.moveable : COLORS.static;
    ctx.beginPath(); ctx.arc(x, y, l.moveable ? 6 : 5, 0, 2 * Math.PI); ctx.fill();
    ctx.fillText(String(l.id), x + 7, y - 5);
  }
}

function drawMonoslam() {
  const canvas = $('monoslam-canvas'), ctx = canvas.getContext('2d');
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const points = state.monoslam ? state.monoslam.points : [];
  const view = fitView(canvas, points, 25);
  drawAxes(ctx, view, 'x (m, right)', 'z (m, forward)');
  drawLine(ctx, view, points, COLORS.path, 2);
  if (points.length) {
    const [x, y] = points[points.length - 1];
    ctx.fillStyle = COLORS.static; ctx.beginPath(); ctx.arc(view.px(x), view.py(y), 5, 0, 2 * Math.PI); ctx.fill();
  } else {
    ctx.fillStyle = '#777777'; ctx.fillText('no MonoSLAM path yet (monoslam/path)', 30, 40);
  }
}

let shownImage = null; // {stamp, element} of the image on the canvas
function drawCamera() {
  const canvas = $('image-canvas'), ctx = canvas.getContext('2d');
  const image = state.image;
  const paint = () => {
    if (shownImage) {
      canvas.width = shownImage.element.width; canvas.height = shownImage.element.height;
      ctx.drawImage(shownImage.element, 0, 0);
    } else {
      ctx.fillStyle = '#f0f0f0'; ctx.fillRect(0, 0, canvas.width, canvas.height);
      ctx.fillStyle = '#777777'; ctx.fillText('no camera image yet (camera/image_raw or camera/image_raw/compressed)', 30, 40);
    }
    const features = state.features;
    if (!features) return;
    const scale = image ? image.scale : 1;
    for (const [, u, v, cls] of features.tracks) {
      ctx.strokeStyle = COLORS[cls] || COLORS.unknown; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(u * scale, v * scale, 5, 0, 2 * Math.PI); ctx.stroke();
    }
  };
  if (image && (!shownImage || shownImage.stamp !== image.stamp)) {
    const element = new Image();
    element.onload = () => { shownImage = { stamp: image.stamp, element }; paint(); };
    element.src = `data:image/jpeg;base64,${image.jpeg}`;
    return;
  }
  paint();
}

// --- tables and figures ---------------------------------------------------------------
function cell(row, text, className) {
  const td = row.insertCell(); td.textContent = text; if (className) td.className = className;
}

function renderDiagnostics() {
  const body = $('diagnostics').tBodies[0];
  const rows = state.diagnostics || [];
  body.replaceChildren();
  const counts = {};
  for (const d of rows) {
    counts[d.level] = (counts[d.level] || 0) + 1;
    const row = body.insertRow(); row.className = `level-${d.level}`;
    cell(row, d.level, 'level'); cell(row, d.name); cell(row, `${d.age.toFixed(1)} s`, 'age'); cell(row, d.message);
  }
  $('diagnostics-summary').textContent = rows.length
    ? Object.entries(counts).map(([k, v]) => `${v} ${k}`).join(', ')
    : 'nothing on /diagnostics yet';
}

function renderMapFigures() {
  const map = state.map;
  if (map) {
    $('landmark-count').textContent = map.count;
    $('static-count').textContent = map.static;
    $('moveable-count').textContent = map.moveable;
    $('map-frame').textContent = `frame ${map.frame}`;
  }
  const body = $('moveable-table').tBodies[0];
  body.replaceChildren();
  for (const m of state.moveable || []) {
    const row = body.insertRow();
    cell(row, m.id); cell(row, m.weight.toFixed(3)); cell(row, m.seen.length);
  }
}

function renderFeatures() {
  const f = state.features;
  if (!f) return;
  $('feature-count').textContent = f.tracks.length;
  const c = f.counts;
  $('feature-summary').textContent = `${c.static} static, ${c.dynamic} dynamic, ${c.pending} pending, ${c.unknown} no class yet`;
}

function render(changed) {
  const has = (name) => changed.includes(name);
  if (has('map') || has('path') || has('moveable')) { renderMapFigures(); drawMap(); }
  if (has('monoslam')) drawMonoslam();
  if (has('image') || has('features')) { renderFeatures(); drawCamera(); }
  if (has('diagnostics')) renderDiagnostics();
  if (has('monoslam') && state.monoslam) $('monoslam-frame').textContent = `frame ${state.monoslam.frame}`;
}

setInterval(() => {
  if (lastUpdate) $('updated').textContent = `${((new Date() - lastUpdate) / 1000).toFixed(1)} s ago`;
}, 500);
drawMap(); drawMonoslam(); drawCamera();
connect();
