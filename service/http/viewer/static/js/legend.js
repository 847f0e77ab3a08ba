// The legend of everything the scene draws (scene.js), with the same colours (colors.js).

import { LAYER_COLORS, STATUS_COLORS } from "./colors.js";

const C = LAYER_COLORS, GREEN = STATUS_COLORS.tracking;
const svg = (body) => `<svg width="22" height="14" viewBox="0 0 22 14" aria-hidden="true">${body}</svg>`;

// [data-item, glyph, label, tooltip]
const ITEMS = [
  ["robot", svg(`<path d="M19 7 L9 3 L9 11 Z" fill="${GREEN}"/><circle cx="9" cy="7" r="5" fill="${GREEN}" stroke="#fff" stroke-width="1.5"/>`),
    "robot", "estimate of a robot, coloured by status; the wedge points along its heading"],
  ["accuracy", svg(`<circle cx="11" cy="7" r="6" fill="${GREEN}" fill-opacity="0.13" stroke="${GREEN}" stroke-opacity="0.6"/>`),
    "accuracy_m", "68 % confidence disc of the estimate (accuracy_m)"],
  ["path", svg(`<path d="M1 11 C6 2 12 13 21 3" fill="none" stroke="${GREEN}" stroke-opacity="0.55" stroke-width="1.5"/>`),
    "path", "the robot's recent estimates"],
  ["hypotheses", svg(`<circle cx="7" cy="7" r="5.5" fill="none" stroke="${C.hypothesis}" stroke-width="1.5"/><circle cx="17" cy="7" r="3" fill="none" stroke="${C.hypothesis}" stroke-width="1.5"/>`),
    "hypotheses", "places the swarm holds; a bigger ring has more support (more than one: ambiguous)"],
  ["particles", svg(`<rect x="3" y="3" width="3" height="3" fill="${C.particle}"/><rect x="11" y="8" width="3" height="3" fill="${C.particle}"/><rect x="16" y="2" width="3" height="3" fill="${C.particle}"/>`),
    "particles", "the swarm's particles (when streamed: tick a robot or 'all particles')"],
  ["map-images", svg(`<path d="M1 7 H21" stroke="${C.route}" stroke-width="6" stroke-linecap="round"/><rect x="4" y="6" width="2" height="2" fill="${C.mapImage}"/><rect x="10" y="6" width="2" height="2" fill="${C.mapImage}"/><rect x="16" y="6" width="2" height="2" fill="${C.mapImage}"/>`),
    "map images", "the mapped route; a dot where each map image was taken"],
];

export function legendHtml() {
  const statuses = Object.entries(STATUS_COLORS).map(([s, c]) =>
    `<li data-status="${s}"><i style="background:${c}"></i>${s}</li>`).join("");
  const layers = ITEMS.map(([item, glyph, label, title]) =>
    `<li data-item="${item}" title="${title}">${glyph}${label}</li>`).join("");
  return `<ul class="statuses">${statuses}</ul><ul class="layers">${layers}</ul>`;
}
