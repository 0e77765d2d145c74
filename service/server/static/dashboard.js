// meniscope dashboard: draws what /ws sends (docs/service.md) on plain canvases, at most once per animation frame.
"use strict";

const MAX_WINDOWS = 200; // kept for the trends and the fitted curves
const state = { windows: [], trace: null, dirty: true };
// what the browser test reads: messages received and drawings made
window.meniscope = { windows: 0, traces: 0, draws: 0 };

// A exp(-g t) cos(2 pi f t + phi) summed over the modes, plus offset and drift (shared/spec/cli.md, REPORT.json).
function fitted(w, t) {
  let y = (w.offset_mm ?? NaN) + (w.drift_mm_per_s ?? 0) * t;
  for (const m of w.modes) {
    y += m.amplitude_mm * Math.exp(-m.decay_rate_per_s * t) * Math.cos(2 * Math.PI * m.frequency_hz * t + m.phase_rad);
  }
  return y;
}

function range(values) {
  let lo = Infinity, hi = -Infinity;
  for (const v of values) if (v !== null && Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (!Number.isFinite(lo)) return [-1, 1];
  const pad = (hi - lo) * 0.08 || 1e-3;
  return [lo - pad, hi + pad];
}

// A plot area over [x0, x1] x [y0, y1]; returns a mapper from data to pixels.
function axes(canvas, x0, x1, y0, y1) {
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#000";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.fillStyle = "#777";
  ctx.font = "11px sans-serif";
  ctx.fillText(y1.toPrecision(3), 2, 11);
  ctx.fillText(y0.toPrecision(3), 2, canvas.height - 3);
  const px = (x) => 40 + ((x - x0) / (x1 - x0 || 1)) * (canvas.width - 44);
  const py = (y) => canvas.height - 4 - ((y - y0) / (y1 - y0 || 1)) * (canvas.height - 8);
  return { ctx, px, py };
}

function line(ctx, points, colour, width = 1) {
  ctx.strokeStyle = colour;
  ctx.lineWidth = width;
  ctx.beginPath();
  let pen = false;
  for (const [x, y] of points) {
    if (!Number.isFinite(y)) { pen = false; continue; }
    if (pen) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    pen = true;
  }
  ctx.stroke();
}

function curve(w, from, to, fps, px, py) {
  const pts = [];
  for (let f = Math.max(from, w.start_frame); f < Math.min(to, w.end_frame); f++) {
    pts.push([px(f), py(fitted(w, (f - w.start_frame) / fps))]);
  }
  return pts;
}

function drawTrace() {
  const tr = state.trace;
  if (!tr) return;
  const canvas = document.getElementById("trace");
  const first = tr.first_index, last = first + tr.values.length;
  const [lo, hi] = range(tr.values);
  const { ctx, px, py } = axes(canvas, first, last, lo, hi);
  for (const e of tr.ejections) line(ctx, [[px(e), 0], [px(e), canvas.height]], "#e55");
  line(ctx, tr.values.map((v, i) => [px(first + i), v === null ? NaN : py(v)]), "#6cf");
  for (const { window: w } of state.windows) {
    if (w.end_frame > first && w.start_frame < last) line(ctx, curve(w, first, last, tr.fps, px, py), "#fa3", 1.5);
  }
}

function drawWindow() {
  const latest = state.windows.findLast((m) => m.values);
  if (!latest) return;
  const w = latest.window, vals = latest.values;
  const [lo, hi] = range(vals);
  const { ctx, px, py } = axes(document.getElementById("window"), w.start_frame, w.end_frame, lo, hi);
  ctx.fillStyle = "#6cf";
  vals.forEach((v, i) => { if (v !== null) ctx.fillRect(px(w.start_frame + i) - 1, py(v) - 1, 2, 2); });
  line(ctx, curve(w, w.start_frame, w.end_frame, latest.fps, px, py), "#fa3", 1.5);
  const f = w.modes.length ? `${w.modes[0].frequency_hz.toFixed(0)} Hz, ${w.modes[0].decay_rate_per_s.toFixed(0)} /s` : "";
  document.getElementById("window-caption").textContent =
    `#${latest.id}: ${w.status} ${f}` + (w.settled ? `, settled in ${(w.settling_time_s * 1e3).toFixed(2)} ms` : "");
}

function drawTrend(id, values, flags) {
  const canvas = document.getElementById(id);
  const [lo, hi] = range(values);
  const { ctx, px, py } = axes(canvas, 0, Math.max(values.length - 1, 1), lo, hi);
  line(ctx, values.map((v, i) => [px(i), v === null ? NaN : py(v)]), "#555");
  values.forEach((v, i) => {
    if (v === null) return;
    ctx.fillStyle = flags && flags[i] ? "#e55" : "#6cf";
    ctx.fillRect(px(i) - 2, py(v) - 2, 4, 4);
  });
}

function drawTrends() {
  const ws = state.windows.map((m) => m.window);
  const dominant = (w) => (w.status === "ok" && w.modes.length ? w.modes[0] : null);
  drawTrend("trend-frequency", ws.map((w) => dominant(w)?.frequency_hz ?? null));
  drawTrend("trend-decay", ws.map((w) => dominant(w)?.decay_rate_per_s ?? null));
  // a window that did not settle is drawn at its length, in red: it lasted at least that long
  drawTrend("trend-settling", state.windows.map(({ window: w, fps }) =>
    (w.settled ? w.settling_time_s * 1e3 : w.modes.length ? ((w.end_frame - w.start_frame) / fps) * 1e3 : null)),
  ws.map((w) => !w.settled));
}

function draw() {
  if (state.dirty) {
    state.dirty = false;
    drawTrace();
    drawWindow();
    drawTrends();
    window.meniscope.draws++;
  }
  requestAnimationFrame(draw);
}

function addWindow(message) {
  state.windows.push(message);
  if (state.windows.length > MAX_WINDOWS) state.windows.shift();
  state.dirty = true;
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onmessage = (event) => {
    const message = JSON.parse(event.data);
    if (message.type === "window") { window.meniscope.windows++; addWindow(message); }
    if (message.type === "trace") { window.meniscope.traces++; state.trace = message; state.dirty = true; }
  };
  ws.onclose = () => setTimeout(connect, 1000);
}

async function poll() {
  try {
    const s = await (await fetch("/api/v1/status")).json();
    const el = document.getElementById("state");
    el.textContent = s.ready ? "ready" : `${s.state}: ${s.reason ?? ""}`;
    el.className = s.ready ? "state ready" : "state";
    document.getElementById("status").textContent =
      `${s.source.uri ?? "demo"} | in ${s.fps_in.toFixed(0)} fps, inferred ${s.fps_out.toFixed(0)} fps | ` +
      `dropped ${s.frames.dropped} frames, ${s.frames.gaps} gaps | windows ${s.windows.closed} (${s.windows.skipped} unfitted)`;
    if (s.ready) {
      const t = Date.now();
      document.getElementById("frame").src = `/api/v1/frames/latest.png?t=${t}`;
      document.getElementById("render").src = `/api/v1/frames/latest/render.png?t=${t}`;
      const c = await (await fetch("/api/v1/frames/latest")).json();
      document.getElementById("coefficients").textContent =
        `render: d ${c.d_mm.toFixed(4)} p ${c.p.toFixed(3)} a ${c.a_mm.toFixed(4)} b ${c.b_mm.toFixed(4)}`;
    }
  } catch (err) {
    document.getElementById("state").textContent = `no answer: ${err}`;
  }
}

async function start() {
  try {
    const history = await (await fetch("/api/v1/windows?limit=100")).json();
    for (const stored of history.windows) addWindow(stored);
  } catch (err) { /* the live feed fills in */ }
  connect();
  poll();
  setInterval(poll, 1000);
  requestAnimationFrame(draw);
}

start();
