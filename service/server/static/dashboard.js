// meniscope dashboard: draws what /ws sends (docs/service.md) on plain canvases, at most once per animation frame.
"use strict";

const MAX_WINDOWS = 200; // kept for the trends and the fitted curves
const state = { windows: [], trace: null, dirty: true };
// what the browser test reads: messages received and drawings made
window.meniscope = { windows: 0, traces: 0, draws: 0, axes: {} };

// A exp(-g t) cos(2 pi f t + phi) summed over the modes, plus offset and drift (REPORT.json's window fields).
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

// Ticks on [lo, hi] at a step of 1, 2 or 5 x 10^k: the coarsest step that still gives max(2, n - 1) of them.
function ticks(lo, hi, n) {
  const magnitude = 10 ** Math.floor(Math.log10((hi - lo) / n || Math.abs(hi) || 1));
  for (const m of [10, 5, 2, 1, 0.5]) {
    const step = m * magnitude, values = [];
    for (let k = Math.ceil(lo / step - 1e-9); k * step <= hi + step * 1e-9; k++) values.push(k * step);
    if (values.length >= Math.max(2, n - 1) || m === 0.5) return { values, step };
  }
}

// A tick label: as many decimals as the step needs, never an exponent, with its unit.
function tickLabel(v, step, unit) {
  const decimals = Math.max(0, -Math.floor(Math.log10(step) + 1e-9));
  const text = (Math.abs(v) < step / 1e6 ? 0 : v).toFixed(decimals);
  return unit ? `${text} ${unit}` : text;
}

const MARGIN = { left: 66, right: 8, top: 6, bottom: 30 };

// A plot area with its axes: x = {lo, hi, unit, title}, y = {lo, hi, unit}; ticks labelled with their units
// (what was drawn is kept in window.meniscope.axes[id] for the browser test). Returns mappers to pixels.
function axes(canvas, x, y) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height;
  const left = MARGIN.left, right = w - MARGIN.right, top = MARGIN.top, bottom = h - MARGIN.bottom;
  const px = (v) => left + ((v - x.lo) / (x.hi - x.lo || 1)) * (right - left);
  const py = (v) => bottom - ((v - y.lo) / (y.hi - y.lo || 1)) * (bottom - top);
  ctx.fillStyle = "#000";
  ctx.fillRect(0, 0, w, h);
  ctx.font = "11px sans-serif";
  ctx.lineWidth = 1;
  const yt = ticks(y.lo, y.hi, Math.max(2, Math.floor((bottom - top) / 36)));
  const xt = ticks(x.lo, x.hi, Math.max(2, Math.floor((right - left) / 90)));
  const drawn = { x: [], y: [], title: x.title };
  ctx.textAlign = "right";
  ctx.textBaseline = "middle";
  for (const v of yt.values) {
    ctx.strokeStyle = "#262626";
    ctx.beginPath(); ctx.moveTo(left, py(v)); ctx.lineTo(right, py(v)); ctx.stroke();
    const text = tickLabel(v, yt.step, y.unit);
    ctx.fillStyle = "#999";
    ctx.fillText(text, left - 4, py(v));
    drawn.y.push(text);
  }
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  for (const v of xt.values) {
    ctx.strokeStyle = "#262626";
    ctx.beginPath(); ctx.moveTo(px(v), top); ctx.lineTo(px(v), bottom + 3); ctx.stroke();
    const text = tickLabel(v, xt.step, "");
    ctx.fillStyle = "#999";
    ctx.fillText(text, px(v), bottom + 4);
    drawn.x.push(text);
  }
  ctx.textAlign = "right";
  ctx.fillStyle = "#bbb";
  ctx.fillText(`${x.title} (${x.unit})`, right, bottom + 17);
  ctx.strokeStyle = "#555";
  ctx.strokeRect(left, top, right - left, bottom - top);
  ctx.textAlign = "left";
  ctx.textBaseline = "alphabetic";
  window.meniscope.axes[canvas.id] = drawn;
  return { ctx, px, py, top, bottom };
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

// The fitted curve of window w over frames [from, to); fx maps a frame index to pixels.
function curve(w, from, to, fps, fx, py) {
  const pts = [];
  for (let f = Math.max(from, w.start_frame); f < Math.min(to, w.end_frame); f++) {
    pts.push([fx(f), py(fitted(w, (f - w.start_frame) / fps))]);
  }
  return pts;
}

function drawTrace() {
  const tr = state.trace;
  if (!tr) return;
  const canvas = document.getElementById("trace");
  const first = tr.first_index, last = first + tr.values.length;
  const ms = (f) => ((f - (last - 1)) / tr.fps) * 1e3; // 0 at the latest frame
  const [lo, hi] = range(tr.values);
  const { ctx, px, py, top, bottom } = axes(canvas, { lo: ms(first), hi: 0, unit: "ms", title: "time before the latest frame" },
    { lo, hi, unit: "mm" });
  const fx = (f) => px(ms(f));
  for (const e of tr.ejections) line(ctx, [[fx(e), top], [fx(e), bottom]], "#e55");
  line(ctx, tr.values.map((v, i) => [fx(first + i), v === null ? NaN : py(v)]), "#6cf");
  for (const { window: w } of state.windows) {
    if (w.end_frame > first && w.start_frame < last) line(ctx, curve(w, first, last, tr.fps, fx, py), "#fa3", 1.5);
  }
}

function drawWindow() {
  const latest = state.windows.findLast((m) => m.values);
  if (!latest) return;
  const w = latest.window, vals = latest.values;
  const [lo, hi] = range(vals);
  const ms = (f) => ((f - w.start_frame) / latest.fps) * 1e3; // 0 at the ejection that opened the window
  const { ctx, px, py } = axes(document.getElementById("window"),
    { lo: 0, hi: ms(w.end_frame), unit: "ms", title: "time since the ejection" }, { lo, hi, unit: "mm" });
  const fx = (f) => px(ms(f));
  ctx.fillStyle = "#6cf";
  vals.forEach((v, i) => { if (v !== null) ctx.fillRect(fx(w.start_frame + i) - 1, py(v) - 1, 2, 2); });
  line(ctx, curve(w, w.start_frame, w.end_frame, latest.fps, fx, py), "#fa3", 1.5);
  const f = w.modes.length ? `${w.modes[0].frequency_hz.toFixed(0)} Hz, ${w.modes[0].decay_rate_per_s.toFixed(0)} /s` : "";
  document.getElementById("window-caption").textContent =
    `#${latest.id}: ${w.status} ${f}` + (w.settled ? `, settled in ${(w.settling_time_s * 1e3).toFixed(2)} ms` : "");
}

// One value per window against the window's start on the camera's clock, in s before the latest window's.
function drawTrend(id, times, values, unit, flags) {
  const canvas = document.getElementById(id);
  const [lo, hi] = range(values);
  const span = Math.max(-Math.min(...times, 0), 1e-3);
  const { ctx, px, py } = axes(canvas, { lo: -span, hi: 0, unit: "s", title: "window start, before the latest" },
    { lo, hi, unit });
  line(ctx, values.map((v, i) => [px(times[i]), v === null ? NaN : py(v)]), "#555");
  values.forEach((v, i) => {
    if (v === null) return;
    ctx.fillStyle = flags && flags[i] ? "#e55" : "#6cf";
    ctx.fillRect(px(times[i]) - 2, py(v) - 2, 4, 4);
  });
}

function drawTrends() {
  // only the windows of the stream now running (a restart counts frames from 0 again)
  const latest = state.windows[state.windows.length - 1];
  if (!latest) return;
  const start = (m) => m.window.start_frame / m.fps;
  const shown = state.windows.filter((m) => m.source === latest.source && start(m) <= start(latest));
  const times = shown.map((m) => start(m) - start(latest));
  const ws = shown.map((m) => m.window);
  const dominant = (w) => (w.status === "ok" && w.modes.length ? w.modes[0] : null);
  drawTrend("trend-frequency", times, ws.map((w) => dominant(w)?.frequency_hz ?? null), "Hz");
  drawTrend("trend-decay", times, ws.map((w) => dominant(w)?.decay_rate_per_s ?? null), "1/s");
  // a window that did not settle is drawn at its length, in red: it lasted at least that long
  drawTrend("trend-settling", times, shown.map(({ window: w, fps }) =>
    (w.settled ? w.settling_time_s * 1e3 : w.modes.length ? ((w.end_frame - w.start_frame) / fps) * 1e3 : null)),
  "ms", ws.map((w) => !w.settled));
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

// a refined window (serve --refine) replaces the window of its id where it is still shown
function updateWindow(message) {
  const i = state.windows.findIndex((w) => w.id === message.id);
  if (i >= 0) { state.windows[i] = message; state.dirty = true; }
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onmessage = (event) => {
    const message = JSON.parse(event.data);
    if (message.type === "window") { window.meniscope.windows++; addWindow(message); }
    if (message.type === "window_update") { window.meniscope.refined = (window.meniscope.refined ?? 0) + 1; updateWindow(message); }
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
      // Eq. 1: d, a, b in mm; p multiplies a length to give one (dimensionless)
      document.getElementById("coefficients").textContent =
        `render of d ${c.d_mm.toFixed(4)} mm, p ${c.p.toFixed(4)} (dimensionless),\n` +
        `a ${c.a_mm.toFixed(4)} mm, b ${c.b_mm.toFixed(4)} mm`;
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
