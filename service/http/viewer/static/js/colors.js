// One colour per estimator status (README "Viewer"); the page's legend is drawn from it.
export const STATUS_COLORS = Object.freeze({
  initializing: "#8c8c8c",
  tracking: "#2e9d4f",
  recovering: "#f08c00",
  lost: "#d62728",
});

export function statusColor(status) {
  return STATUS_COLORS[status] ?? "#5a5a5a";
}
