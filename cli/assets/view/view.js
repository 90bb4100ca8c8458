// twinstack view: live telemetry from `twinstack view` over Server-Sent Events, drawn on
// <canvas>. No library, nothing fetched from elsewhere.
"use strict";

const COLORS = {
  setpoint: "#222222", sensor: "#1f77b4", estimate: "#2ca02c", error: "#d62728",
  left: "#ff7f0e", right: "#9467bd",
};
const GROUPS = [
  { canvas: "plot-position", names: ["setpoint", "sensor", "estimate"], unit: "um" },
  { canvas: "plot-error", names: ["error"], unit: "um" },
  { canvas: "plot-stacks", names: ["left", "right"], unit: "V" },
];

// What the page received, for the eye and for tests: `samples` is the page's own count of
// telemetry samples in this run from sample `start` on (the first it saw: a page opened
// during a run sees it from then), `counts` the server's (what the board sent).
const view = {
  run: -1, samples: 0, start: null, expected: 0, gaps: 0, missedMessages: 0, batches: 0,
  counts: null, status: null, hello: null, draws: 0, rateHz: 0, signals: [],
  tune: null, calibration: null, connected: false,
};
window.twinstackView = view;

let buffers = {};   // name -> {data: Float64Array, head, filled}
let capacity = 4000;

function resetBuffers() {
  const seconds = Math.max(0.1, parseFloat(document.getElementById("window-s").value) || 1);
  capacity = Math.max(16, Math.round(seconds * (view.rateHz || 1000)));
  buffers = {};
  for (const name of view.signals) {
    buffers[name] = { data: new Float64Array(capacity), head: 0, filled: 0 };
  }
}

function startRun(run) {
  view.run = run;
  view.samples = 0;
  view.start = null;
  view.expected = 0;
  view.gaps = 0;
  resetBuffers();
}

function push(name, values) {
  const b = buffers[name];
  if (!b) return;
  for (let i = 0; i < values.length; i++) {
    b.data[b.head] = values[i];
    b.head = (b.head + 1) % capacity;
  }
  b.filled = Math.min(capacity, b.filled + values.length);
}

const events = new EventSource("/events");
events.onopen = () => { view.connected = true; setLink("live", "#8f8"); };
events.onerror = () => { view.connected = false; setLink("disconnected", "#f88"); };
events.addEventListener("hello", (e) => {
  const h = JSON.parse(e.data);
  view.hello = h;
  view.rateHz = h.rate_hz;
  view.signals = h.signals;
  document.getElementById("port").textContent = h.port;
  document.getElementById("rate").textContent =
    `${h.signals.join(", ")} at ${h.rate_hz} samples/s`;
  if (h.run !== view.run) startRun(h.run);
});
events.addEventListener("samples", (e) => {
  const b = JSON.parse(e.data);
  if (b.run !== view.run) startRun(b.run);
  if (view.start === null) { view.start = b.first; view.expected = b.first; }
  if (b.first > view.expected) view.gaps += b.first - view.expected;
  view.samples += b.n;
  view.expected = b.first + b.n;
  view.batches += 1;
  view.counts = b.counts;
  for (const name in b.signals) push(name, b.signals[name]);
});
events.addEventListener("status", (e) => {
  view.status = JSON.parse(e.data);
  if (view.status.telemetry) view.counts = view.status.telemetry;
  showStatus();
});
events.addEventListener("missed", (e) => {
  view.missedMessages += JSON.parse(e.data).messages;
});
events.addEventListener("closed", () => { setLink("the server has stopped", "#fc8"); events.close(); });

function setLink(text, color) {
  const el = document.getElementById("link");
  el.textContent = text;
  el.style.color = color;
}

function rows(table, pairs) {
  table.innerHTML = pairs
    .map(([k, v, id]) => `<tr><td>${k}</td><td${id ? ` id="${id}"` : ""}>${v}</td></tr>`)
    .join("");
}

function showStatus() {
  const s = view.status;
  if (!s) return;
  rows(document.getElementById("status"), [
    ["image", s.image], ["mode", s.mode, "status-mode"], ["flags", (s.flags || []).join(" ") || "–"],
    ["ticks", s.ticks], ["tick rate", `${s.tick_rate_hz} Hz`],
    ["queue", `${s.queue_fill} (credits ${s.credits})`], ["underruns", s.underruns],
    ["host: bytes in", s.host_link ? s.host_link.bytes_received : "–"],
    ["host: corrupt frames", s.host_link ? s.host_link.corrupt_frames : "–"],
  ]);
  for (const b of document.querySelectorAll("button[data-mode]")) {
    b.classList.toggle("on", b.dataset.mode === s.mode);
  }
  showCounters();
}

function showCounters() {
  const c = view.counts || {};
  rows(document.getElementById("counters"), [
    ["run", view.run],
    ["page: samples received", view.samples, "page-samples"],
    ["board: samples sent", c.expected === undefined ? "–" : c.expected - (view.start || 0), "board-samples"],
    ["missing (board's count)", c.missing ?? "–", "missing"],
    ["dropped on the board", c.lost_on_board ?? "–"],
    ["frames lost on the line", c.frames_missing ?? "–"],
    ["page: gaps, missed messages", `${view.gaps}, ${view.missedMessages}`],
    ["running", c.running === false ? "no" : "yes"],
  ]);
}

// ---------------------------------------------------------------------------------------
// Drawing

function fit(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const w = canvas.clientWidth, h = canvas.clientHeight || 150;
  if (canvas.width !== Math.round(w * ratio)) {
    canvas.width = Math.round(w * ratio);
    canvas.height = Math.round(h * ratio);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  return { ctx, w, h };
}

function niceTicks(lo, hi, n) {
  const span = hi - lo || 1;
  const step0 = span / n;
  const mag = Math.pow(10, Math.floor(Math.log10(step0)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0) || mag * 10;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * span; v += step) out.push(v);
  return out;
}

// A tick's text: 4 significant digits, and 0 for a tick that is 0 up to rounding.
function tickText(v, lo, hi) {
  return Math.abs(v) < 1e-9 * (Math.abs(lo) + Math.abs(hi)) ? "0" : String(+v.toPrecision(4));
}

function axes(ctx, box, xlo, xhi, ylo, yhi, xlabel, ylabel, xfmt) {
  ctx.strokeStyle = "#ddd"; ctx.fillStyle = "#555"; ctx.lineWidth = 1;
  ctx.font = "11px sans-serif";
  ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (const v of niceTicks(ylo, yhi, 4)) {
    const y = box.y + box.h - ((v - ylo) / (yhi - ylo)) * box.h;
    ctx.beginPath(); ctx.moveTo(box.x, y); ctx.lineTo(box.x + box.w, y); ctx.stroke();
    ctx.fillText(tickText(v, ylo, yhi), box.x - 4, y);
  }
  ctx.textAlign = "center"; ctx.textBaseline = "top";
  for (const v of niceTicks(xlo, xhi, 6)) {
    const x = box.x + ((v - xlo) / (xhi - xlo)) * box.w;
    ctx.beginPath(); ctx.moveTo(x, box.y); ctx.lineTo(x, box.y + box.h); ctx.stroke();
    ctx.fillText(xfmt ? xfmt(v) : tickText(v, xlo, xhi), x, box.y + box.h + 3);
  }
  ctx.strokeStyle = "#888";
  ctx.strokeRect(box.x, box.y, box.w, box.h);
  ctx.textAlign = "left"; ctx.textBaseline = "top";
  ctx.fillText(ylabel, box.x + 4, box.y + 2);
  ctx.textAlign = "right";
  ctx.fillText(xlabel, box.x + box.w, box.y + box.h + 16);
}

// One live plot: the last `capacity` samples of each signal of the group, min/max per pixel
// column so that every sample shows however many there are.
function drawGroup(group) {
  const canvas = document.getElementById(group.canvas);
  const { ctx, w, h } = fit(canvas);
  ctx.clearRect(0, 0, w, h);
  const names = group.names.filter((n) => buffers[n]);
  if (!names.length) {
    ctx.fillStyle = "#999"; ctx.font = "12px sans-serif";
    ctx.fillText(`${group.names.join(", ")}: not in this telemetry (--signals)`, 10, 20);
    return;
  }
  const box = { x: 52, y: 6, w: w - 64, h: h - 34 };
  let lo = Infinity, hi = -Infinity;
  for (const n of names) {
    const b = buffers[n];
    for (let i = 0; i < b.filled; i++) {
      const v = b.data[(b.head - b.filled + i + capacity) % capacity];
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
  }
  if (!isFinite(lo)) { lo = -1; hi = 1; }
  if (hi - lo < 1e-9) { lo -= 0.5; hi += 0.5; }
  const pad = (hi - lo) * 0.05; lo -= pad; hi += pad;
  const seconds = capacity / (view.rateHz || 1);
  axes(ctx, box, -seconds, 0, lo, hi, "t − now [s]", `[${group.unit}]`);
  names.forEach((n, k) => {
    const b = buffers[n];
    ctx.strokeStyle = COLORS[n] || "#000"; ctx.lineWidth = 1.2;
    ctx.beginPath();
    const cols = Math.max(1, Math.floor(box.w));
    const start = capacity - b.filled;
    let col = -1, cmin = 0, cmax = 0, first = true;
    const flush = () => {
      if (col < 0) return;
      const x = box.x + col;
      const y1 = box.y + box.h - ((cmin - lo) / (hi - lo)) * box.h;
      const y2 = box.y + box.h - ((cmax - lo) / (hi - lo)) * box.h;
      if (first) { ctx.moveTo(x, y1); first = false; } else ctx.lineTo(x, y1);
      ctx.lineTo(x, y2);
    };
    for (let i = 0; i < b.filled; i++) {
      const v = b.data[(b.head - b.filled + i + capacity) % capacity];
      const c = Math.floor(((start + i) / capacity) * cols);
      if (c !== col) { flush(); col = c; cmin = v; cmax = v; }
      else { if (v < cmin) cmin = v; if (v > cmax) cmax = v; }
    }
    flush();
    ctx.stroke();
    ctx.fillStyle = COLORS[n] || "#000"; ctx.font = "11px sans-serif";
    ctx.textAlign = "left"; ctx.textBaseline = "top";
    ctx.fillText(n, box.x + 60 + 70 * k, box.y + 2);
  });
}

function frame() {
  for (const g of GROUPS) drawGroup(g);
  view.draws += 1;
  showCounters();
  requestAnimationFrame(frame);
}
requestAnimationFrame(frame);

// The last tune's measured response (magnitude and phase against log frequency).
function drawBode() {
  const canvas = document.getElementById("bode");
  const { ctx, w, h } = fit(canvas);
  ctx.clearRect(0, 0, w, h);
  const t = view.tune;
  ctx.font = "12px sans-serif"; ctx.fillStyle = "#999";
  if (!t) { ctx.fillText("no tune: start the view with --tune tune.json (twinstack tune --json)", 10, 20); return; }
  const pts = t.points;
  const lf = pts.map((p) => Math.log10(p.frequency_hz));
  const xlo = Math.min(...lf), xhi = Math.max(...lf);
  const half = (h - 40) / 2;
  const panels = [
    { key: "magnitude_db", label: "[dB]", box: { x: 52, y: 6, w: w - 64, h: half - 10 } },
    { key: "phase_deg", label: "[°]", box: { x: 52, y: half + 16, w: w - 64, h: half - 10 } },
  ];
  const fmt = (v) => { const f = Math.pow(10, v); return f >= 1000 ? `${+(f / 1000).toPrecision(3)}k` : `${+f.toPrecision(3)}`; };
  for (const p of panels) {
    const ys = pts.map((q) => q[p.key]);
    let lo = Math.min(...ys), hi = Math.max(...ys);
    const pad = (hi - lo) * 0.08 || 1; lo -= pad; hi += pad;
    axes(ctx, p.box, xlo, xhi, lo, hi, p.key === "phase_deg" ? "frequency [Hz]" : "", p.label, fmt);
    ctx.strokeStyle = "#1f77b4"; ctx.lineWidth = 1.5; ctx.beginPath();
    pts.forEach((q, i) => {
      const x = p.box.x + ((lf[i] - xlo) / (xhi - xlo || 1)) * p.box.w;
      const y = p.box.y + p.box.h - ((q[p.key] - lo) / (hi - lo)) * p.box.h;
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.stroke();
    if (t.fit && t.fit.resonance_hz) {
      const x = p.box.x + ((Math.log10(t.fit.resonance_hz) - xlo) / (xhi - xlo || 1)) * p.box.w;
      ctx.strokeStyle = "#d62728"; ctx.setLineDash([4, 3]);
      ctx.beginPath(); ctx.moveTo(x, p.box.y); ctx.lineTo(x, p.box.y + p.box.h); ctx.stroke();
      ctx.setLineDash([]);
    }
  }
  if (t.fit) {
    ctx.fillStyle = "#d62728"; ctx.textAlign = "right"; ctx.textBaseline = "top";
    ctx.fillText(`resonance ${t.fit.resonance_hz.toFixed(0)} Hz, ζ ${t.fit.zeta.toFixed(3)}`, w - 14, 10);
  }
}

// The calibration's ranking: one horizontal bar per candidate, its validation max error, the
// label left of the bar and the figure at its end (nothing drawn over the bars).
function drawRanking() {
  const canvas = document.getElementById("ranking");
  const { ctx, w, h } = fit(canvas);
  ctx.clearRect(0, 0, w, h);
  const c = view.calibration;
  ctx.font = "12px sans-serif"; ctx.fillStyle = "#999";
  if (!c) { ctx.fillText("no calibration: start the view with --calibration cal.json (twinstack calibrate --json)", 10, 20); return; }
  const rows = c.ranking;
  const box = { x: 12, y: 8, w: w - 24, h: h - 36 };
  const top = Math.max(...rows.map((r) => r.max_pct || 0), 1e-9) * 1.25;
  axes(ctx, box, 0, top, 0, 1, "validation max error [% of span]", "", null);
  ctx.clearRect(0, box.y + 1, box.x - 1, box.h);  // no y ticks: rows are categories
  const rowH = box.h / rows.length;
  rows.forEach((r, i) => {
    // Each row: the label on top, the bar under it, the figure at the bar's end.
    const y0 = box.y + i * rowH;
    const picked = r.model === c.model;
    ctx.textAlign = "left"; ctx.textBaseline = "middle";
    ctx.fillStyle = "#222";
    ctx.font = picked ? "bold 11px sans-serif" : "11px sans-serif";
    ctx.fillText(`${i + 1}. ${r.model}`, box.x + 3, y0 + rowH * 0.27);
    const y = y0 + rowH * 0.48, bh = rowH * 0.4;
    ctx.font = "11px sans-serif";
    if (r.max_pct === undefined) {
      ctx.fillStyle = "#999";
      ctx.fillText(`not fitted: ${r.error || ""}`.slice(0, 80), box.x + 3, y + bh / 2);
      return;
    }
    const bw = (r.max_pct / top) * box.w;
    ctx.fillStyle = r.not_admitted ? "#bbb" : (picked ? "#1f77b4" : "#9ecae1");
    ctx.fillRect(box.x, y, bw, bh);
    ctx.fillStyle = "#222";
    ctx.fillText(`${r.max_pct.toFixed(2)} %${picked ? " kept" : ""}${r.not_admitted ? " (not admitted)" : ""}`, box.x + bw + 4, y + bh / 2);
  });
}

async function load(path, key, draw) {
  try {
    const r = await fetch(path);
    view[key] = r.ok ? await r.json() : null;
  } catch (e) {
    view[key] = null;
  }
  draw();
}
load("/api/tune", "tune", drawBode);
load("/api/calibration", "calibration", drawRanking);
window.addEventListener("resize", () => { drawBode(); drawRanking(); });

// ---------------------------------------------------------------------------------------
// Commands

async function post(path, body) {
  const el = document.getElementById("message");
  try {
    const r = await fetch(path, {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body || {}),
    });
    const v = await r.json();
    el.textContent = v.ok || v.error;
    el.className = r.ok ? "" : "error";
    return v;
  } catch (e) {
    el.textContent = `${path}: ${e}`;
    el.className = "error";
    return { error: String(e) };
  }
}
window.twinstackPost = post;

for (const b of document.querySelectorAll("button[data-mode]")) {
  b.addEventListener("click", () => post("/api/mode", { mode: b.dataset.mode }));
}
const num = (id) => parseFloat(document.getElementById(id).value);
document.getElementById("wf-start").addEventListener("click", () => post("/api/waveform", {
  amplitude: num("wf-amplitude"), frequency: num("wf-frequency"),
  shape: document.getElementById("wf-shape").value,
}));
document.getElementById("stop").addEventListener("click", () => post("/api/stop"));
document.getElementById("scan-start").addEventListener("click", () => post("/api/scan", {
  pattern: document.getElementById("scan-pattern").value,
  ticks_per_pixel: Math.round(num("scan-tpp")),
}));
document.getElementById("scan-stop").addEventListener("click", () => post("/api/stop"));
document.getElementById("tel-run").addEventListener("click", () => post("/api/telemetry", { run: true }));
document.getElementById("tel-pause").addEventListener("click", () => post("/api/telemetry", { run: false }));
document.getElementById("window-s").addEventListener("change", resetBuffers);
