// Boot: token, maps, stream; draws in requestAnimationFrame only when something changed.

import { Fleet } from "./fleet.js";
import { legendHtml } from "./legend.js";
import { Panel } from "./panel.js";
import { Scene } from "./scene.js";
import { openStream } from "./stream.js";

const PANEL_MS = 250; // side panel refresh (the time since the last frame keeps moving)
const LEARNING_MS = 3000; // the selected robot's learning progress (GET /sessions/{id})

const params = new URLSearchParams(location.search);
const token = params.get("token") ?? sessionStorage.getItem("swarmloc-token");
if (token) sessionStorage.setItem("swarmloc-token", token);

const $ = (id) => document.getElementById(id);
const fleet = new Fleet();
const scene = new Scene($("scene"));
const watched = new Set(); // robots whose particles are streamed, or "*"
let selected = null;
let learning = new Map(); // the selected robot -> its session's learning progress, if it learns
let mapName = null;
let stream = null;
const stats = { draws: 0, drawMs: 0, lastDrawMs: 0, drawTimes: [] }; // for benchmarks

function api(path) {
  return fetch(path, { headers: token ? { Authorization: `Bearer ${token}` } : {} })
    .then(async (res) => {
      if (!res.ok) throw new Error(`${path}: ${res.status} ${(await res.json()).error ?? ""}`);
      return res.json();
    });
}

function setConn(state, text) {
  $("conn").dataset.state = state;
  $("conn").textContent = text;
}

function connect() {
  stream?.close();
  const q = new URLSearchParams({ map: mapName });
  if (watched.size) q.set("particles", [...watched].join(","));
  stream = openStream({
    url: `events?${q}`, token,
    onBatch: (batch) => fleet.apply(batch),
    onState: setConn,
  });
}

async function selectMap(name) {
  mapName = name;
  params.set("map", name);
  history.replaceState(null, "", `?${params}`);
  const detail = await api(`maps/${encodeURIComponent(name)}`);
  scene.setRoute(detail.positions);
  fleet.clear();
  connect();
}

function toggleParticles(id, on) {
  if (on) watched.add(id); else watched.delete(id);
  if (!on) { const r = fleet.robots.get(id); if (r) r.particles = null; }
  if (id === "*" && !on) for (const r of fleet.robots.values()) r.particles = null;
  fleet.version += 1;
  connect();
}

function pollLearning() {
  const id = selected;
  if (id === null) { learning = new Map(); return; }
  api(`sessions/${encodeURIComponent(id)}`)
    .then((s) => { if (selected === id) learning = new Map(s.learning ? [[id, s.learning]] : []); })
    .catch(() => {}); // a session gone meanwhile: its entry goes with the stream
}

const panel = new Panel($("robots"), $("fleet-summary"), {
  onSelect: (id) => { selected = selected === id ? null : id; scene.selected = selected;
    scene.changed = true; pollLearning(); },
  onParticles: toggleParticles,
});

let drawn = -1;
function frame() {
  if (fleet.version !== drawn || scene.changed) {
    const t0 = performance.now();
    drawn = fleet.version;
    scene.draw(fleet);
    stats.lastDrawMs = performance.now() - t0;
    stats.drawMs = stats.draws ? 0.9 * stats.drawMs + 0.1 * stats.lastDrawMs : stats.lastDrawMs;
    stats.draws += 1;
    stats.drawTimes.push(stats.lastDrawMs);
    if (stats.drawTimes.length > 2000) stats.drawTimes.splice(0, 1000);
  }
  requestAnimationFrame(frame);
}

async function main() {
  $("legend").innerHTML = legendHtml();
  $("fit").addEventListener("click", () => scene.fit());
  $("all-particles").addEventListener("change", (e) => toggleParticles("*", e.target.checked));
  $("scene").addEventListener("pick", (e) => {
    const id = scene.pick(fleet, e.detail.x, e.detail.y);
    selected = id; scene.selected = id; scene.changed = true; pollLearning();
  });
  window.addEventListener("resize", () => { scene.changed = true; });
  setInterval(() => panel.update(fleet, selected, watched, learning), PANEL_MS);
  setInterval(pollLearning, LEARNING_MS); // one robot's session, not the fleet's: scales
  requestAnimationFrame(frame);
  try {
    const maps = await api("maps");
    const sel = $("map-select");
    for (const m of maps) sel.add(new Option(`${m.name} (${m.n_images} images)`, m.name));
    if (!maps.length) { setConn("error", "no maps loaded"); return; }
    const want = params.get("map");
    sel.value = maps.some((m) => m.name === want) ? want : maps[0].name;
    sel.addEventListener("change", () => selectMap(sel.value));
    await selectMap(sel.value);
  } catch (err) {
    setConn("error", String(err.message ?? err));
  }
}

window.swarmloc = { fleet, scene, stats, watched };
main();
