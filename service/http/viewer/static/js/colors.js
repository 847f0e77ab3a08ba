// One colour per estimator status (README "Viewer"), and one per layer the scene draws; the
// page's legend (legend.js) is drawn from both.
export const STATUS_COLORS = Object.freeze({
  initializing: "#8c8c8c",
  tracking: "#2e9d4f",
  recovering: "#f08c00",
  lost: "#d62728",
});

export function statusColor(status) {
  return STATUS_COLORS[status] ?? "#5a5a5a";
}

export const LAYER_COLORS = Object.freeze({
  route: "#d3d7dd", // the mapped route
  mapImage: "#a9b0b9", // one dot per map image
  particle: "#3a5fcd",
  hypothesis: "#7b3fc4",
  ink: "#1d232b", // labels, selection ring, scale bar
});
