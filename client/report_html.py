"""``report.html``: a self-contained page that plays a replay back (inline CSS, JS and data).

Route (map image positions), truth and estimate with the accuracy circle and heading, status
and error over time, and a time slider (with play). No network access, no external file: the
page opens from disk or as a CI artefact.
"""

from __future__ import annotations

import html
import json
from typing import Any

import numpy as np

from client.runs import Run

STATUSES = ("initializing", "tracking", "recovering", "lost")


def _r(a: Any, nd: int = 2) -> list:
    return np.round(np.asarray(a, float), nd).tolist()


def run_data(run: Run) -> dict[str, Any]:
    """One run as columns (compact: one list per quantity, positions in cm)."""
    return {
        "start": run.start, "seed": run.seed, "kidnap": run.kidnap, "dt": run.dt,
        "image": np.asarray(run.frames).astype(int).tolist(),
        "x": _r(run.est_xy[:, 0]), "y": _r(run.est_xy[:, 1]),
        "tx": _r(run.true_xy[:, 0]), "ty": _r(run.true_xy[:, 1]),
        "error": _r(run.errors), "accuracy": _r(run.accuracy_m),
        "heading": _r(run.heading, 3), "speed": _r(run.speed, 3),
        "status": [STATUSES.index(s) if s in STATUSES else 0 for s in run.status],
        "score": _r(run.scores, 4), "comparisons": [int(c) for c in run.comparisons],
        "latency_ms": _r(run.latency_ms, 1),
    }


def render_html(report: dict, runs: list[Run], route_xy: np.ndarray) -> str:
    data = {"statuses": STATUSES, "route": _r(route_xy), "runs": [run_data(r) for r in runs],
            "summary": report["summary"], "round": report["round"], "via": report["via"],
            "config": report["config"], "created": report["created"]}
    blob = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    cfg = report["config"]
    title = (f"swarmloc replay: {report['round']['name']} on "
             f"{cfg['map_name'] or 'default map'}")
    return (_TEMPLATE.replace("{{TITLE}}", html.escape(title))
            .replace("{{DATA}}", blob))


_TEMPLATE = r"""<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{{TITLE}}</title>
<style>
:root { --ink: #1d232b; --muted: #6b7480; --line: #dde1e6; }
body { margin: 0; font: 13px/1.4 system-ui, sans-serif; color: var(--ink); background: #f6f7f9; }
header { padding: 10px 16px; background: #fff; border-bottom: 1px solid var(--line); }
h1 { font-size: 16px; margin: 0 0 4px; }
#summary { color: var(--muted); }
main { display: grid; grid-template-columns: minmax(0, 1fr) 300px; gap: 12px; padding: 12px; }
.card { background: #fff; border: 1px solid var(--line); border-radius: 6px; padding: 8px; }
svg { display: block; width: 100%; }
#route-svg { height: 62vh; min-height: 320px; }
#time-svg { height: 170px; }
#controls { display: flex; gap: 10px; align-items: center; grid-column: 1 / -1; }
#slider { flex: 1; }
dl { display: grid; grid-template-columns: auto 1fr; gap: 3px 10px; margin: 0; }
dt { color: var(--muted); } dd { margin: 0; font-variant-numeric: tabular-nums; }
.legend span { margin-right: 12px; white-space: nowrap; }
.legend i { display: inline-block; width: 10px; height: 10px; border-radius: 50%;
  margin-right: 4px; vertical-align: -1px; }
.axis { font-size: 10px; fill: var(--muted); }
</style>
</head>
<body>
<header><h1>{{TITLE}}</h1><div id="summary"></div></header>
<main>
  <div id="controls" class="card">
    <button id="play" type="button">play</button>
    <input id="slider" type="range" min="0" value="0" step="1" aria-label="frame">
    <label>speed <select id="rate"><option>1</option><option selected>4</option>
      <option>16</option></select>x</label>
    <label>run <select id="run"></select></label>
  </div>
  <div class="card">
    <svg id="route-svg" aria-label="route with truth and estimate"></svg>
    <div class="legend" id="legend"></div>
  </div>
  <div class="card"><dl id="readout"></dl></div>
  <div class="card" style="grid-column: 1 / -1">
    <svg id="time-svg" aria-label="error and status over time"></svg>
  </div>
</main>
<script id="data" type="application/json">{{DATA}}</script>
<script>
"use strict";
const D = JSON.parse(document.getElementById("data").textContent);
const COLORS = { initializing: "#8c8c8c", tracking: "#2e9d4f", recovering: "#f08c00",
  lost: "#d62728" };
const TRUTH = "#1f6fd1";
const NS = "http://www.w3.org/2000/svg";
const $ = (id) => document.getElementById(id);
function el(tag, attrs, parent) {
  const e = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}
const fmt = (v, d) => (v === null || v === undefined) ? "n/a" : Number(v).toFixed(d);

let run = D.runs[0], frame = 0, playing = null;
const routeSvg = $("route-svg"), timeSvg = $("time-svg"), slider = $("slider");
let toS = null; // world -> SVG user units
let marks = {};

function niceStep(raw) {
  const p = 10 ** Math.floor(Math.log10(raw));
  for (const n of [1, 2, 5]) if (n * p >= raw) return n * p;
  return 10 * p;
}

function drawRoute() {
  routeSvg.replaceChildren();
  const W = 1000, H = 620, pad = 30;
  routeSvg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  const xs = [...D.route.map((p) => p[0]), ...run.tx];
  const ys = [...D.route.map((p) => p[1]), ...run.ty];
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const s = Math.min((W - 2 * pad) / Math.max(x1 - x0, 1), (H - 2 * pad) / Math.max(y1 - y0, 1));
  const ox = (W - s * (x1 - x0)) / 2, oy = (H - s * (y1 - y0)) / 2;
  toS = (x, y) => [ox + (x - x0) * s, oy + (y1 - y) * s];
  toS.scale = s;
  const path = (X, Y) => X.map((x, i) => toS(x, Y[i]).map((v) => v.toFixed(1)).join(",")).join(" ");
  el("polyline", { points: path(D.route.map((p) => p[0]), D.route.map((p) => p[1])),
    fill: "none", stroke: "#d3d7dd", "stroke-width": 8, "stroke-linejoin": "round",
    "stroke-linecap": "round", id: "route-line" }, routeSvg);
  el("polyline", { points: path(run.tx, run.ty), fill: "none", stroke: TRUTH,
    "stroke-width": 1.5, id: "truth-line" }, routeSvg);
  const dots = el("g", { id: "estimate-dots" }, routeSvg);
  run.x.forEach((x, i) => {
    const [sx, sy] = toS(x, run.y[i]);
    el("circle", { cx: sx.toFixed(1), cy: sy.toFixed(1), r: 1.6, fill: "#c0392b",
      "fill-opacity": 0.45 }, dots);
  });
  // scale bar
  const m = niceStep(120 / s);
  el("path", { d: `M20 ${H - 20} v-6 M20 ${H - 20} h${m * s} v-6`, stroke: "#1d232b",
    "stroke-width": 2, fill: "none" }, routeSvg);
  el("text", { x: 26 + m * s, y: H - 18, class: "axis" }, routeSvg).textContent = `${m} m`;
  marks = {
    err: el("line", { stroke: "#c0392b", "stroke-dasharray": "3 3", id: "error-line" }, routeSvg),
    acc: el("circle", { "fill-opacity": 0.14, "stroke-opacity": 0.6, id: "accuracy-circle" },
      routeSvg),
    truth: el("circle", { r: 6, fill: "#fff", stroke: TRUTH, "stroke-width": 3,
      id: "truth-marker" }, routeSvg),
    head: el("path", { id: "heading" }, routeSvg),
    est: el("circle", { r: 7, stroke: "#fff", "stroke-width": 2, id: "est-marker" }, routeSvg),
  };
}

function drawTimeline() {
  timeSvg.replaceChildren();
  const W = 1000, H = 170, L = 40, B = 20, n = run.error.length;
  timeSvg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  const sorted = [...run.error].sort((a, b) => a - b);
  const top = Math.max(10, 1.1 * sorted[Math.floor(0.99 * (n - 1))]);
  const X = (i) => L + (W - L - 10) * (n > 1 ? i / (n - 1) : 0);
  const Y = (e) => (H - B) - (H - B - 8) * Math.min(e, top) / top;
  let start = 0; // status bands
  for (let i = 1; i <= n; i++) {
    if (i === n || run.status[i] !== run.status[start]) {
      const st = D.statuses[run.status[start]];
      el("rect", { x: X(start - 0.5), width: Math.max(1, X(i - 0.5) - X(start - 0.5)),
        y: 8, height: H - B - 8, fill: COLORS[st],
        "fill-opacity": st === "tracking" ? 0.08 : 0.25, "data-status": st }, timeSvg);
      start = i;
    }
  }
  for (const v of [0, top / 2, top]) {
    el("text", { x: 4, y: Y(v) + 3, class: "axis" }, timeSvg).textContent = `${v.toFixed(0)} m`;
  }
  el("text", { x: W - 60, y: H - 4, class: "axis" }, timeSvg).textContent = `frame ${n - 1}`;
  el("text", { x: L, y: H - 4, class: "axis" }, timeSvg).textContent = "error (m) over frames";
  el("polyline", { points: run.error.map((e, i) => `${X(i).toFixed(1)},${Y(e).toFixed(1)}`)
    .join(" "), fill: "none", stroke: "#1d232b", "stroke-width": 1.2, id: "error-curve" },
    timeSvg);
  marks.cursor = el("line", { y1: 4, y2: H - B, stroke: "#3a5fcd", "stroke-width": 2,
    id: "cursor" }, timeSvg);
  marks.X = X;
}

function show(k) {
  frame = Math.max(0, Math.min(run.x.length - 1, k));
  slider.value = frame;
  const st = D.statuses[run.status[frame]], c = COLORS[st];
  const [ex, ey] = toS(run.x[frame], run.y[frame]);
  const [tx, ty] = toS(run.tx[frame], run.ty[frame]);
  const set = (e, a) => { for (const [k2, v] of Object.entries(a)) e.setAttribute(k2, v); };
  set(marks.est, { cx: ex.toFixed(2), cy: ey.toFixed(2), fill: c, "data-x": run.x[frame],
    "data-y": run.y[frame], "data-status": st, "data-frame": frame });
  set(marks.truth, { cx: tx.toFixed(2), cy: ty.toFixed(2) });
  set(marks.acc, { cx: ex.toFixed(2), cy: ey.toFixed(2), r: (run.accuracy[frame] * toS.scale)
    .toFixed(2), fill: c, stroke: c });
  set(marks.err, { x1: ex, y1: ey, x2: tx, y2: ty });
  const h = run.heading[frame], hx = Math.cos(h), hy = -Math.sin(h);
  set(marks.head, { d: `M${ex + 18 * hx},${ey + 18 * hy} L${ex - 6 * hy},${ey + 6 * hx} ` +
    `L${ex + 6 * hy},${ey - 6 * hx} Z`, fill: c });
  set(marks.cursor, { x1: marks.X(frame), x2: marks.X(frame) });
  const rows = [["frame", `${frame} / ${run.x.length - 1} (image ${run.image[frame]})`],
    ["time", `${fmt(frame * run.dt, 1)} s`], ["status", st],
    ["error", `${fmt(run.error[frame], 2)} m`], ["accuracy", `${fmt(run.accuracy[frame], 2)} m`],
    ["speed", `${fmt(run.speed[frame], 2)} m/s`], ["score", fmt(run.score[frame], 3)],
    ["comparisons", run.comparisons[frame]], ["latency", `${fmt(run.latency_ms[frame], 1)} ms`],
    ["estimate", `${fmt(run.x[frame], 2)}, ${fmt(run.y[frame], 2)} m`],
    ["truth", `${fmt(run.tx[frame], 2)}, ${fmt(run.ty[frame], 2)} m`]];
  $("readout").replaceChildren(...rows.flatMap(([k2, v]) => {
    const dt = document.createElement("dt"), dd = document.createElement("dd");
    dt.textContent = k2; dd.textContent = v; dd.dataset.field = k2;
    if (k2 === "status") dd.style.color = c;
    return [dt, dd];
  }));
}

function selectRun(i) {
  run = D.runs[i];
  slider.max = run.x.length - 1;
  drawRoute();
  drawTimeline();
  show(0);
}

function play() {
  if (playing) { cancelAnimationFrame(playing); playing = null; $("play").textContent = "play";
    return; }
  $("play").textContent = "pause";
  let last = performance.now(), acc = 0;
  const tick = (now) => {
    acc += (now - last) / 1000 * Number($("rate").value) / Math.max(run.dt, 1e-3);
    last = now;
    if (acc >= 1) { show(frame + Math.floor(acc)); acc %= 1; }
    if (frame >= run.x.length - 1) { playing = null; $("play").textContent = "play"; return; }
    playing = requestAnimationFrame(tick);
  };
  playing = requestAnimationFrame(tick);
}

const S = D.summary;
$("summary").textContent = `${D.round.name} (${D.round.images} images) via ${D.via}, ` +
  `${D.config.estimator}, ${S.runs} run(s): mean error ${fmt(S.error_mean_m, 2)} m, ` +
  `median ${fmt(S.error_median_m, 2)} m, within 5 m ${fmt(100 * S.within_5m, 1)} %, ` +
  `${fmt(S.comparisons_per_frame, 1)} comparisons/frame, latency p50 ` +
  `${fmt(S.latency_p50_ms, 1)} ms (${D.created})`;
$("legend").innerHTML = `<span><i style="background:${TRUTH}"></i>truth</span>` +
  '<span><i style="background:#c0392b"></i>estimates</span>' +
  Object.entries(COLORS).map(([s, c]) =>
    `<span><i style="background:${c}"></i>${s}</span>`).join("");
D.runs.forEach((r, i) => $("run").add(new Option(`${i + 1}: start ${r.start}, seed ${r.seed}`, i)));
$("run").addEventListener("change", (e) => selectRun(Number(e.target.value)));
slider.addEventListener("input", () => show(Number(slider.value)));
$("play").addEventListener("click", play);
document.addEventListener("keydown", (e) => {
  if (e.target === slider) return; // the slider steps itself
  if (e.key === "ArrowRight") show(frame + 1);
  if (e.key === "ArrowLeft") show(frame - 1);
});
selectRun(0);
</script>
</body>
</html>
"""
