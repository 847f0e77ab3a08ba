// The side panel: one entry per robot. State is mirrored into data-* attributes
// (data-status, data-color, data-x/y, data-sx/sy) for scripts and tests.

import { statusColor } from "./colors.js";

const STALE_S = 5;

function fmt(v, digits, unit = "") {
  return v === null || v === undefined || !Number.isFinite(v) ? "–" : `${v.toFixed(digits)}${unit}`;
}

export class Panel {
  constructor(list, summary, { onSelect, onParticles }) {
    this.list = list;
    this.summary = summary;
    this.items = new Map();
    this.onSelect = onSelect;
    this.onParticles = onParticles;
  }

  #item(id) {
    let li = this.items.get(id);
    if (li) return li;
    li = document.createElement("li");
    li.className = "robot";
    li.dataset.robot = id;
    li.innerHTML = `<div class="top"><span class="name"></span><span class="status"></span>
      <label class="particles"><input type="checkbox"> particles</label></div>
      <dl><dt>speed</dt><dd class="speed"></dd><dt>score</dt><dd class="score"></dd>
      <dt>comp.</dt><dd class="comparisons"></dd><dt>rate</dt><dd class="fps"></dd>
      <dt>latency</dt><dd class="latency"></dd><dt>last</dt><dd class="age"></dd>
      <dt>layer</dt><dd class="experience"></dd>
      <dt>taught</dt><dd class="taught"></dd></dl>`;
    li.querySelector(".name").textContent = id;
    li.addEventListener("click", (e) => {
      if (!e.target.closest("label")) this.onSelect(id);
    });
    li.querySelector("input").addEventListener("change", (e) => {
      this.onParticles(id, e.target.checked);
    });
    this.items.set(id, li);
    return li;
  }

  update(fleet, selected, watched, learning = new Map()) {
    const ids = [...fleet.robots.keys()].sort();
    for (const [id, li] of this.items) {
      if (!fleet.robots.has(id)) { li.remove(); this.items.delete(id); }
    }
    const counts = {};
    let prev = null;
    for (const id of ids) {
      const r = fleet.robots.get(id), e = r.est;
      if (!e) continue;
      const li = this.#item(id);
      if (li.previousElementSibling !== prev || li.parentNode !== this.list) {
        if (prev) prev.after(li); else this.list.prepend(li);
      }
      prev = li;
      counts[e.status] = (counts[e.status] ?? 0) + 1;
      const color = statusColor(e.status);
      const age = fleet.ageSeconds(r);
      li.dataset.status = e.status;
      li.dataset.color = color;
      li.dataset.x = e.x; li.dataset.y = e.y;
      if (r.sx !== undefined) { li.dataset.sx = r.sx.toFixed(1); li.dataset.sy = r.sy.toFixed(1); }
      li.style.setProperty("--status-color", color);
      li.classList.toggle("selected", id === selected);
      li.classList.toggle("stale", age > STALE_S);
      const q = (c) => li.querySelector(c);
      q(".status").textContent = e.status;
      q(".speed").textContent = fmt(e.speed, 2, " m/s");
      q(".score").textContent = fmt(e.score, 3);
      q(".comparisons").textContent = `${e.comparisons}`;
      // the experience (learned layer) the frame was matched with; "map": the map's own images
      q(".experience").textContent = e.experience ?? "map";
      li.dataset.experience = e.experience ?? "";
      // a learning robot's frames taught (and bridged by the wheels) of those judged
      const lr = learning.get(id);
      q(".taught").textContent = lr
        ? `${lr.taught}${lr.bridged ? ` + ${lr.bridged}` : ""} of ${lr.frames}` : "–";
      li.dataset.taught = lr ? lr.taught + lr.bridged : "";
      q(".fps").textContent = fmt(r.fps, 1, "/s");
      q(".latency").textContent = fmt(e.latency_ms, 0, " ms");
      q(".age").textContent = age < 60 ? `${Math.max(0, age).toFixed(1)} s` : `${(age / 60).toFixed(0)} min`;
      const box = q("input");
      const on = watched.has(id) || watched.has("*");
      if (box.checked !== on) box.checked = on;
      box.disabled = watched.has("*");
    }
    const parts = Object.entries(counts).map(([s, n]) => `${n} ${s}`);
    this.summary.textContent = ids.length
      ? `${ids.length} robot${ids.length === 1 ? "" : "s"}: ${parts.join(", ")}`
      : "no robot on this map yet";
    this.summary.dataset.robots = ids.length;
  }
}
