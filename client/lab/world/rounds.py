"""Rounds: a traversal's trajectory and movers, rendered into the dataset format; datasets of
rounds; a contact sheet to look at them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from client.dataset import write_odometry, write_round
from client.lab.world.geometry import Camera, Pose, Route
from client.lab.world.renderer import Renderer
from client.lab.world.scene import MOVER_CARS, MOVER_PEOPLE, Mover, Scene


class World(Protocol):
    """What a round needs of the world it is rendered in (``client.lab.world.World``)."""

    seed: int
    spacing_m: float
    route: Route
    camera: Camera
    renderer: Renderer

    def scene(self, day: str, condition: str) -> Scene: ...

def round_trajectory(world: World, round_index: int, n_frames: int | None = None,
                     speed_mps: float = 0.6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact poses (x, y, heading, pitch) and times of one round, deterministic by index."""
    rng = np.random.default_rng([world.seed, 10, round_index])
    L = world.route.length
    n = n_frames or round(L / world.spacing_m)

    def smooth(amp: float, corr: float) -> np.ndarray:
        raw = rng.normal(0, 1, n + 64)
        k = np.exp(-0.5 * (np.arange(-32, 33) / corr) ** 2)
        sm = np.convolve(raw, k / np.sqrt(np.sum(k**2)), mode="same")[32 : 32 + n]
        return amp * sm

    step = world.spacing_m * (1 + smooth(0.06, 6.0))
    s = np.concatenate([[0.0], np.cumsum(step[:-1])]) + rng.uniform(0, 1.0)
    lateral = -1.3 + rng.uniform(-0.6, 0.6) + smooth(0.3, 15.0)
    pts = world.route.point(s) + lateral[:, None] * world.route.normal(s)
    dlat = np.gradient(lateral) / np.maximum(step, 1e-3)
    heading = world.route.heading(s) + np.arctan(dlat) + np.radians(
        smooth(3.0, 8.0) + rng.normal(0, 0.5, n))
    pitch = np.radians(smooth(0.8, 6.0))
    t = np.cumsum(step) / speed_mps - step[0] / speed_mps
    return np.column_stack([pts, heading, pitch]), t, s

def round_movers(world: World, round_index: int) -> list[Mover]:
    """The pedestrians and driving cars of one round, deterministic by index."""
    rng = np.random.default_rng([world.seed, 11, round_index])
    L = world.route.length
    n_people = rng.poisson(L / 25)
    n_cars = rng.poisson(L / 90)
    people = [Mover(MOVER_PEOPLE[int(rng.integers(0, len(MOVER_PEOPLE)))], rng.uniform(0, L),
                    rng.choice([-1, 1])
                    * rng.uniform(0.8, 1.5), rng.choice([-1, 1]) * rng.uniform(4.0, 5.6), False)
              for _ in range(n_people)]
    cars = [Mover(MOVER_CARS[int(rng.integers(0, len(MOVER_CARS)))], rng.uniform(0, L),
                  rng.uniform(-8, -3), 1.6, True) for _ in range(n_cars)]
    return people + cars

@dataclass(frozen=True)
class OdometryNoise:
    """How the simulated wheel odometry errs: a scale error of ``scale`` (the wheels'
    circumference: every step ``1 + scale`` too long or too short, sign drawn per round),
    a heading drift of ``drift_deg_per_m`` (sign drawn per round), and per-step noise."""

    scale: float = 0.03
    drift_deg_per_m: float = 0.1
    step_sigma: float = 0.01  # relative std of each step's length
    turn_sigma_deg: float = 0.1  # std of each step's turn


def simulate_odometry(poses: np.ndarray, rng: np.random.Generator,
                      noise: OdometryNoise = OdometryNoise()) -> np.ndarray:
    """(N, 3) odometry poses (x, y, yaw) of a trajectory ``poses`` (x, y, heading): each
    true step in the body frame, with ``noise``, integrated from (0, 0, 0)."""
    x, y, h = poses[:, 0], poses[:, 1], poses[:, 2]
    dx, dy = np.diff(x), np.diff(y)
    c, s = np.cos(h[:-1]), np.sin(h[:-1])
    fwd, left = c * dx + s * dy, -s * dx + c * dy
    turn = np.angle(np.exp(1j * np.diff(h)))
    n = len(fwd)
    sign_s, sign_d = rng.choice([-1.0, 1.0], 2)
    gain = (1 + sign_s * noise.scale) * (1 + rng.normal(0, noise.step_sigma, n))
    fwd, left = fwd * gain, left * gain
    turn = turn + np.radians(sign_d * noise.drift_deg_per_m * np.hypot(fwd, left)
                             + rng.normal(0, noise.turn_sigma_deg, n))
    out = np.zeros((n + 1, 3))
    for k in range(n):
        ox, oy, oyaw = out[k]
        co, so = math.cos(oyaw), math.sin(oyaw)
        out[k + 1] = (ox + co * fwd[k] - so * left[k], oy + so * fwd[k] + co * left[k],
                      oyaw + turn[k])
    return out


def write_round_odometry(world: World, out_dir: str | Path, round_index: int,
                         n_frames: int | None = None,
                         noise: OdometryNoise = OdometryNoise()) -> Path:
    """Write ``odometry.csv`` of a round (deterministic by world seed and round index)."""
    poses, _, _ = round_trajectory(world, round_index, n_frames)
    odom = simulate_odometry(poses, np.random.default_rng([world.seed, 13, round_index]),
                             noise)
    write_odometry(out_dir, [f"{k:05d}.png" for k in range(len(poses))], odom)
    return Path(out_dir)


def render_round(world: World, out_dir: str | Path, round_index: int, condition: str,
                 day: str | None = None, n_frames: int | None = None,
                 gps_noise_m: float = 0.3, progress: bool = False,
                 odometry: OdometryNoise = OdometryNoise()) -> Path:
    """Render a round into ``out_dir`` (images, poses.csv with GPS-like noise, truth.csv,
    odometry.csv with ``odometry``'s noise)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    day = day or condition
    scene = world.scene(day, condition)
    poses, t, _ = round_trajectory(world, round_index, n_frames)
    movers = round_movers(world, round_index)
    rng = np.random.default_rng([world.seed, 12, round_index])
    exposure = 1 + 0.04 * np.sin(np.arange(len(poses)) / 17.0 + rng.uniform(0, 6))
    names = [f"{k:05d}.png" for k in range(len(poses))]
    it = range(len(poses))
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=f"round {round_index} ({condition})", unit="frame")
    for k in it:
        img = world.renderer.render(scene, Pose(*poses[k]), float(t[k]), movers,
                                    noise_seed=int(rng.integers(2**31)),
                                    exposure=float(exposure[k]))
        cv2.imwrite(str(out_dir / names[k]), img)
    gps = poses[:, :2] + _correlated_noise(rng, len(poses), gps_noise_m)
    write_round(out_dir, names, gps, t, truth_xy=poses[:, :2])
    write_round_odometry(world, out_dir, round_index, n_frames, odometry)
    return out_dir



def _correlated_noise(rng: np.random.Generator, n: int, sigma: float, rho: float = 0.9
                      ) -> np.ndarray:
    e = rng.normal(0, sigma * math.sqrt(1 - rho**2), (n, 2))
    out = np.empty((n, 2))
    out[0] = rng.normal(0, sigma, 2)
    for k in range(1, n):
        out[k] = rho * out[k - 1] + e[k]
    return out


@dataclass
class RoundSpec:
    name: str
    condition: str
    day: str
    index: int


@dataclass
class DatasetSpec:
    """Which rounds to render; default like the papers: three sunny and three cloudy rounds."""

    seed: int = 0
    length_m: float = 260.0
    spacing_m: float = 0.6
    width: int = 320  # the camera's image size, pixels (the same field of view at any size)
    height: int = 240
    rounds: list[RoundSpec] = field(default_factory=lambda: [
        RoundSpec(f"{cond}{k}", cond, cond, i)
        for i, (cond, k) in enumerate([(c, k) for c in ("sunny", "cloudy") for k in (1, 2, 3)])
    ])
    # rendered only when named: the harder lighting (lowsun vs cloudy), dusk and night
    extra_rounds: list[RoundSpec] = field(default_factory=lambda: [
        RoundSpec(f"{cond}{k}", cond, cond, 6 + i)
        for i, (cond, k) in enumerate([(c, k) for c in ("lowsun", "dusk", "night")
                                       for k in (1, 2)])
    ])


def contact_sheet(images: list[np.ndarray], cols: int = 4, labels: list[str] | None = None
                  ) -> np.ndarray:
    """Tile frames into one image (for looking at what the world renders)."""
    h, w = images[0].shape[:2]
    rows = math.ceil(len(images) / cols)
    sheet = np.full((rows * (h + 4), cols * (w + 4)), 255, np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, cols)
        y, x = r * (h + 4), c * (w + 4)
        sheet[y : y + h, x : x + w] = img
        if labels:
            cv2.putText(sheet, labels[k], (x + 4, y + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 255, 1)
    return sheet
