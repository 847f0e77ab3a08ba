// The robots as the page knows them: last estimate, trail, frame rate, particles.

const TRAIL = 80; // estimates kept per robot
const FPS_ALPHA = 0.3;

export class Fleet {
  constructor() {
    this.robots = new Map();
    this.clockOffset = 0; // client time - server time, s
    this.messages = 0;
    this.version = 0; // bumped on every change: the scene redraws when it moves
  }

  apply(batch) {
    this.clockOffset = Date.now() / 1000 - batch.now;
    for (const m of batch.m) {
      this.messages += 1;
      if (m.k === "e") this.#estimate(m);
      else if (m.k === "p") this.#particles(m);
      else if (m.k === "x") this.robots.delete(m.robot);
    }
    this.version += 1;
  }

  #estimate(m) {
    let r = this.robots.get(m.robot);
    if (!r) {
      r = { id: m.robot, trail: [], fps: null, particles: null, est: null };
      this.robots.set(m.robot, r);
    }
    const prev = r.est;
    if (prev && m.seq < prev.seq) { r.trail = []; r.fps = null; } // session replaced
    if (prev && m.seq > prev.seq && m.wall > prev.wall) {
      const inst = (m.seq - prev.seq) / (m.wall - prev.wall);
      r.fps = r.fps === null ? inst : (1 - FPS_ALPHA) * r.fps + FPS_ALPHA * inst;
    }
    if (prev && m.seq === prev.seq && m.latency_ms === null) {
      m.latency_ms = prev.latency_ms; // a reconnect's snapshot does not know the latency
    }
    if (!prev || m.seq !== prev.seq) {
      r.trail.push(m.x, m.y);
      if (r.trail.length > 2 * TRAIL) r.trail.splice(0, r.trail.length - 2 * TRAIL);
    }
    r.est = m;
  }

  #particles(m) {
    const r = this.robots.get(m.robot);
    if (r) r.particles = m.xy;
  }

  ageSeconds(r) {
    return Date.now() / 1000 - this.clockOffset - r.est.wall;
  }

  clear() {
    this.robots.clear();
    this.version += 1;
  }
}
