"""Synthetic route world: a closed street loop ray-cast through a pinhole camera.

Parts: ``geometry`` (camera, conditions, walls, poses, the route), ``layout`` (where the walls
stand, parked cars and vegetation per day), ``scene`` (one day under one condition, ready to
render), ``renderer`` (frames), ``rounds`` (trajectories, movers, rounds and datasets on disk).
``World`` ties them together for one seed.

The world is a 2-D layout of textured vertical walls (facades, hedges, fences, low walls, trees,
sign posts, parked cars) around a closed route, plus a textured ground plane and a sky
panorama. A frame is rendered by casting one ray per image column against every wall segment,
keeping the nearest few hits per column (so a hedge in front of a facade, or a tree crown, shows
what is behind it), and painting far to near with mip-mapped texture look-ups.

Lighting conditions: ``sunny`` (hard orientation-dependent shading, ground shadows of every
wall, shadow bands on facades), ``cloudy`` (flat light, other gamma and white balance),
``lowsun`` (a low western sun: long shadows, hard warm light), ``dusk`` (dim, flat, noisy) and
``night`` (almost dark: noise over faint structure, the case no map can match).
Parked cars belong to a *day*: rounds of one day share them, other days have other cars.
Every round has its own lateral offset, heading and pitch jitter, moving pedestrians and cars,
and sensor noise. Everything is deterministic by seed; nothing is read from disk or network.
"""

from __future__ import annotations

from collections.abc import Iterable
from functools import cached_property
from pathlib import Path

import numpy as np

from client.dataset import write_dataset_meta
from client.lab.world.geometry import CONDITIONS, Camera, Condition, Pose, Route, Wall
from client.lab.world.layout import day_walls, seasonal_walls, static_walls
from client.lab.world.renderer import Renderer
from client.lab.world.rounds import (
    DatasetSpec,
    RoundSpec,
    contact_sheet,
    render_round,
    round_movers,
    round_trajectory,
)
from client.lab.world.scene import (
    MOVER_CARS,
    MOVER_PEOPLE,
    Mover,
    Scene,
    build_scene,
    ground_texture,
)

__all__ = [
    "CONDITIONS", "MOVER_CARS", "MOVER_PEOPLE", "Camera", "Condition", "DatasetSpec", "Mover",
    "Pose", "RoundSpec", "Route", "Scene", "Wall", "World", "contact_sheet", "render_dataset",
]


class World:
    """A seeded street loop: route, static walls, parked cars per day, scenes, rendering."""

    def __init__(self, seed: int = 0, length_m: float = 260.0, spacing_m: float = 0.6,
                 camera: Camera | None = None) -> None:
        self.seed = seed
        self.camera = camera or Camera()
        self.spacing_m = spacing_m
        self.route = Route(length_m)
        self.parking: list[tuple[float, float]] = []
        self.static_walls = static_walls(self.route, np.random.default_rng([seed, 1]),
                                         self.parking)
        self.renderer = Renderer(self.camera, self.route)
        self._scenes: dict[tuple[str, str], Scene] = {}

    def day_walls(self, day: str) -> list[Wall]:
        """Parked cars of one day: street parking and the parking lot differ between days."""
        return day_walls(self.seed, self.route, self.parking, day)

    def scene(self, day: str, condition: str) -> Scene:
        key = (day, condition)
        if key not in self._scenes:
            walls = seasonal_walls(self.seed, self.static_walls, day) + self.day_walls(day)
            self._scenes[key] = build_scene(self.seed, walls, self._ground_base, day,
                                            CONDITIONS[condition])
        return self._scenes[key]

    @cached_property
    def _ground_base(self) -> tuple[np.ndarray, tuple[float, float]]:
        return ground_texture(self.route, np.random.default_rng([self.seed, 3]), self.parking)

    def render(self, pose: Pose, condition: str = "sunny", day: str | None = None,
               t: float = 0.0, movers: Iterable[Mover] = (), noise_seed: int | None = None,
               exposure: float = 1.0) -> np.ndarray:
        """Render one grayscale frame (uint8, camera.height x camera.width)."""
        return self.renderer.render(self.scene(day or condition, condition), pose, t, movers,
                                    noise_seed, exposure)

    def round_trajectory(self, round_index: int, n_frames: int | None = None,
                         speed_mps: float = 0.6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact poses (x, y, heading, pitch) and times of one round, deterministic by index."""
        return round_trajectory(self, round_index, n_frames, speed_mps)

    def movers(self, round_index: int) -> list[Mover]:
        return round_movers(self, round_index)

    def render_round(self, out_dir: str | Path, round_index: int, condition: str,
                     day: str | None = None, n_frames: int | None = None,
                     gps_noise_m: float = 0.3, progress: bool = False) -> Path:
        """Render a round into ``out_dir`` (images, poses.csv with GPS-like noise, truth.csv)."""
        return render_round(self, out_dir, round_index, condition, day, n_frames, gps_noise_m,
                            progress)


def render_dataset(out_dir: str | Path, spec: DatasetSpec, progress: bool = False,
                   only: Iterable[str] | None = None) -> Path:
    out_dir = Path(out_dir)
    world = World(spec.seed, spec.length_m, spec.spacing_m,
                  Camera(width=spec.width, height=spec.height))
    wanted = set(only) if only else None
    known = {r.name for r in spec.rounds + spec.extra_rounds}
    if wanted and wanted - known:
        raise ValueError(f"unknown round(s) {sorted(wanted - known)}; known: {sorted(known)}")
    for r in spec.rounds + spec.extra_rounds:
        if (r in spec.rounds and wanted is None) or (wanted is not None and r.name in wanted):
            render_round(world, out_dir / r.name, r.index, r.condition, r.day, progress=progress)
    write_dataset_meta(out_dir, {
        "name": f"swarmloc-world-{spec.seed}",
        "description": "Synthetic street loop rendered by swarmloc (client/lab/world)",
        "generator": {"seed": spec.seed, "length_m": spec.length_m,
                      "spacing_m": spec.spacing_m, "route_length_m": world.route.length},
        "rounds": {r.name: {"condition": r.condition, "day": r.day, "index": r.index}
                   for r in spec.rounds + spec.extra_rounds
                   if (out_dir / r.name).is_dir()},
        "camera": world.camera.__dict__,
    })
    return out_dir
