// Canvas drawing of one map: metric grid and axes, route, scale bar, robots.
// World coordinates are metres east (x) and north (y) of the map frame.

import { LAYER_COLORS, statusColor } from "./colors.js";

const NICE = [1, 2, 5];

export function niceStep(raw) {
  const p = 10 ** Math.floor(Math.log10(raw));
  for (const n of NICE) if (n * p >= raw) return n * p;
  return 10 * p;
}

export class Scene {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.view = { cx: 0, cy: 0, scale: 4 }; // scale: CSS pixels per metre
    this.width = 1;
    this.height = 1;
    this.route = null; // Float64Array x0, y0, x1, y1, ...
    this.bounds = null;
    this.selected = null;
    this.changed = true;
    this.#interact();
  }

  setRoute(positions) {
    this.route = Float64Array.from(positions.flat());
    const xs = positions.map((p) => p[0]);
    const ys = positions.map((p) => p[1]);
    this.bounds = xs.length
      ? [Math.min(...xs), Math.min(...ys), Math.max(...xs), Math.max(...ys)] : [-10, -10, 10, 10];
    this.fit();
  }

  fit() {
    this.resize();
    const [x0, y0, x1, y1] = this.bounds ?? [-10, -10, 10, 10];
    const w = Math.max(x1 - x0, 10), h = Math.max(y1 - y0, 10);
    this.view = { cx: (x0 + x1) / 2, cy: (y0 + y1) / 2,
      scale: 0.88 * Math.min(this.width / w, this.height / h) };
    this.changed = true;
  }

  resize() {
    const r = this.canvas.getBoundingClientRect();
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(r.width)), h = Math.max(1, Math.round(r.height));
    if (w !== this.width || h !== this.height || this.canvas.width !== Math.round(w * dpr)) {
      this.width = w; this.height = h;
      this.canvas.width = Math.round(w * dpr);
      this.canvas.height = Math.round(h * dpr);
      this.ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
      this.changed = true;
    }
  }

  toScreen(x, y) {
    const v = this.view;
    return [this.width / 2 + (x - v.cx) * v.scale, this.height / 2 - (y - v.cy) * v.scale];
  }

  toWorld(sx, sy) {
    const v = this.view;
    return [v.cx + (sx - this.width / 2) / v.scale, v.cy - (sy - this.height / 2) / v.scale];
  }

  #interact() {
    const c = this.canvas;
    let drag = null;
    c.addEventListener("pointerdown", (e) => {
      drag = { x: e.offsetX, y: e.offsetY, moved: 0 };
      c.setPointerCapture(e.pointerId);
    });
    c.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.offsetX - drag.x, dy = e.offsetY - drag.y;
      drag.moved += Math.abs(dx) + Math.abs(dy);
      this.view.cx -= dx / this.view.scale;
      this.view.cy += dy / this.view.scale;
      drag.x = e.offsetX; drag.y = e.offsetY;
      this.changed = true;
    });
    c.addEventListener("pointerup", (e) => {
      if (drag && drag.moved < 4) c.dispatchEvent(new CustomEvent("pick",
        { detail: { x: e.offsetX, y: e.offsetY } }));
      drag = null;
    });
    c.addEventListener("wheel", (e) => {
      e.preventDefault();
      const [wx, wy] = this.toWorld(e.offsetX, e.offsetY);
      this.view.scale *= Math.exp(-e.deltaY * 0.0015);
      const [nx, ny] = this.toWorld(e.offsetX, e.offsetY);
      this.view.cx += wx - nx; this.view.cy += wy - ny;
      this.changed = true;
    }, { passive: false });
  }

  // The robot whose marker is nearest to a screen point (within 14 px), or null.
  pick(fleet, sx, sy) {
    let best = null, bestD = 14;
    for (const r of fleet.robots.values()) {
      const d = Math.hypot(r.sx - sx, r.sy - sy);
      if (d < bestD) { best = r.id; bestD = d; }
    }
    return best;
  }

  draw(fleet) {
    this.resize();
    const ctx = this.ctx;
    ctx.clearRect(0, 0, this.width, this.height);
    this.#grid();
    this.#route();
    const robots = [...fleet.robots.values()].filter((r) => r.est);
    for (const r of robots) this.#under(r);
    for (const r of robots) this.#marker(r);
    this.#scaleBar();
    this.changed = false;
  }

  #grid() {
    const ctx = this.ctx, v = this.view;
    const step = niceStep(90 / v.scale);
    const [x0, y1] = this.toWorld(0, 0), [x1, y0] = this.toWorld(this.width, this.height);
    ctx.lineWidth = 1;
    ctx.strokeStyle = "#eceef1";
    ctx.fillStyle = "#9aa1aa";
    ctx.font = "10px system-ui, sans-serif";
    ctx.beginPath();
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
      const [sx] = this.toScreen(x, 0);
      ctx.moveTo(Math.round(sx) + 0.5, 0); ctx.lineTo(Math.round(sx) + 0.5, this.height);
    }
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
      const [, sy] = this.toScreen(0, y);
      ctx.moveTo(0, Math.round(sy) + 0.5); ctx.lineTo(this.width, Math.round(sy) + 0.5);
    }
    ctx.stroke();
    ctx.textBaseline = "top";
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
      ctx.fillText(`${+x.toFixed(6)}`, this.toScreen(x, 0)[0] + 2, 2);
    }
    ctx.textBaseline = "bottom";
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
      ctx.fillText(`${+y.toFixed(6)}`, 2, this.toScreen(0, y)[1] - 1);
    }
    // the metric frame: origin with east (x) and north (y) axes
    const [ox, oy] = this.toScreen(0, 0);
    ctx.strokeStyle = "#7d8590"; ctx.fillStyle = "#7d8590"; ctx.lineWidth = 1.5;
    ctx.beginPath();
    ctx.moveTo(ox, oy); ctx.lineTo(ox + 36, oy); ctx.moveTo(ox, oy); ctx.lineTo(ox, oy - 36);
    ctx.stroke();
    ctx.beginPath();
    ctx.moveTo(ox + 40, oy); ctx.lineTo(ox + 33, oy - 3.5); ctx.lineTo(ox + 33, oy + 3.5);
    ctx.moveTo(ox, oy - 40); ctx.lineTo(ox - 3.5, oy - 33); ctx.lineTo(ox + 3.5, oy - 33);
    ctx.fill();
    ctx.textBaseline = "middle";
    ctx.fillText("x east", ox + 43, oy);
    ctx.textBaseline = "bottom";
    ctx.fillText("y north", ox - 8, oy - 42);
  }

  #route() {
    const p = this.route;
    if (!p || p.length < 2) return;
    const ctx = this.ctx;
    ctx.lineJoin = "round"; ctx.lineCap = "round";
    ctx.strokeStyle = LAYER_COLORS.route; ctx.lineWidth = Math.max(4, Math.min(14, 2 * this.view.scale));
    ctx.beginPath();
    for (let i = 0; i < p.length; i += 2) {
      const [sx, sy] = this.toScreen(p[i], p[i + 1]);
      if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
    }
    ctx.stroke();
    ctx.fillStyle = LAYER_COLORS.mapImage;
    const every = Math.max(1, Math.ceil(3 / this.view.scale)); // dots at least ~3 px apart
    for (let i = 0; i < p.length; i += 2 * every) {
      const [sx, sy] = this.toScreen(p[i], p[i + 1]);
      ctx.fillRect(sx - 1, sy - 1, 2, 2);
    }
  }

  // trail, particles, hypotheses and accuracy circle: everything under the markers
  #under(r) {
    const ctx = this.ctx, e = r.est, color = statusColor(e.status);
    const t = r.trail;
    if (t.length >= 4) {
      ctx.strokeStyle = color; ctx.globalAlpha = 0.55; ctx.lineWidth = 1.5;
      ctx.beginPath();
      for (let i = 0; i < t.length; i += 2) {
        const [sx, sy] = this.toScreen(t[i], t[i + 1]);
        if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      }
      ctx.stroke();
      ctx.globalAlpha = 1;
    }
    if (r.particles) {
      ctx.fillStyle = LAYER_COLORS.particle; ctx.globalAlpha = 0.7;
      const p = r.particles;
      for (let i = 0; i < p.length; i += 2) {
        const [sx, sy] = this.toScreen(p[i], p[i + 1]);
        ctx.fillRect(sx - 1.5, sy - 1.5, 3, 3);
      }
      ctx.globalAlpha = 1;
    }
    for (const [hx, hy, w] of e.hypotheses ?? []) {
      const [sx, sy] = this.toScreen(hx, hy);
      ctx.strokeStyle = LAYER_COLORS.hypothesis; ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.arc(sx, sy, 5 + 15 * Math.sqrt(Math.max(0, w)), 0, 2 * Math.PI);
      ctx.stroke();
    }
    const [sx, sy] = this.toScreen(e.x, e.y);
    const rad = Math.max(0, (e.accuracy_m ?? 0) * this.view.scale);
    if (rad > 0) {
      ctx.beginPath(); ctx.arc(sx, sy, rad, 0, 2 * Math.PI);
      ctx.fillStyle = color; ctx.globalAlpha = 0.13; ctx.fill();
      ctx.globalAlpha = 0.6; ctx.strokeStyle = color; ctx.lineWidth = 1; ctx.stroke();
      ctx.globalAlpha = 1;
    }
  }

  #marker(r) {
    const ctx = this.ctx, e = r.est, color = statusColor(e.status);
    const [sx, sy] = this.toScreen(e.x, e.y);
    r.sx = sx; r.sy = sy; r.color = color;
    const h = e.heading ?? 0;
    // heading: a wedge from the marker along the direction of motion (screen y is down)
    const hx = Math.cos(h), hy = -Math.sin(h);
    ctx.fillStyle = color;
    ctx.beginPath();
    ctx.moveTo(sx + 17 * hx, sy + 17 * hy);
    ctx.lineTo(sx - 6 * hy, sy + 6 * hx);
    ctx.lineTo(sx + 6 * hy, sy - 6 * hx);
    ctx.closePath(); ctx.fill();
    ctx.beginPath(); ctx.arc(sx, sy, 7, 0, 2 * Math.PI);
    ctx.fill();
    ctx.lineWidth = 2; ctx.strokeStyle = "#ffffff"; ctx.stroke();
    if (r.id === this.selected) {
      ctx.beginPath(); ctx.arc(sx, sy, 11, 0, 2 * Math.PI);
      ctx.lineWidth = 2; ctx.strokeStyle = "#1d232b"; ctx.stroke();
    }
    ctx.fillStyle = "#1d232b"; ctx.font = "11px system-ui, sans-serif";
    ctx.textBaseline = "middle";
    ctx.fillText(r.id, sx + 12, sy - 10);
  }

  #scaleBar() {
    const ctx = this.ctx;
    const metres = niceStep(120 / this.view.scale);
    const px = metres * this.view.scale;
    const x = 14, y = this.height - 18;
    ctx.fillStyle = "rgba(255,255,255,0.8)";
    ctx.fillRect(x - 6, y - 18, px + 60, 26);
    ctx.strokeStyle = "#1d232b"; ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x, y - 5); ctx.lineTo(x, y); ctx.lineTo(x + px, y); ctx.lineTo(x + px, y - 5);
    ctx.stroke();
    ctx.fillStyle = "#1d232b"; ctx.font = "11px system-ui, sans-serif";
    ctx.textBaseline = "bottom";
    ctx.fillText(metres >= 1000 ? `${metres / 1000} km` : `${metres} m`, x + px + 6, y + 4);
    this.scaleBar = { metres, px };
  }
}
