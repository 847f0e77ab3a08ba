"""Long routes for the scale benchmarks: chained street loops, 400 to 40,000+ map images.

A long route is a chain of independent street loops (each a ``World`` of its own seed, so its
facades, signs, hedges, trees and parked cars differ), laid out on a grid of blocks. The map
traversal runs loop 0, then loop 1, ...; map image ``j`` is frame ``j % per_loop`` of loop
``j // per_loop``, so the map of the first N images of a route contains the map of the first
M < N: one rendering gives the 400, 4,000 and 40,000-image maps.

Rendering keeps one loop's world in memory at a time and writes only features: every loop
becomes one ``loopNNNNN.npz`` (descriptor codes, keypoints, counts per image, global
positions) in a spill directory, written atomically, so a long run can be resumed and loops
can be rendered by several processes. ``assemble_map`` streams the spill files into one map
file (service/maps/route_map.py) without holding the descriptors in memory.

Query legs are short traversals of another round (other lateral offset, heading jitter,
pedestrians, sensor noise) of one loop, written in the dataset format (images, poses.csv,
truth.csv) with global positions; a kidnapped robot is a replay that jumps from one leg to
another.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from client.lab.world.geometry import Camera, Pose, Route

if TYPE_CHECKING:
    from client.lab.world import World

MAP_ROUND = 0  # round index of the map traversal of every loop
QUERY_ROUND = 1  # round index of the query legs
CONDITION = "sunny"


@dataclass(frozen=True)
class Leg:
    """A query traversal: ``frames`` frames of the query round of ``loop`` from ``start``."""

    name: str
    loop: int
    start: int
    frames: int


@dataclass(frozen=True)
class LongRoute:
    """Geometry of a chain of loops; nothing is rendered until asked."""

    n_images: int
    seed: int = 0
    loop_length_m: float = 260.0
    spacing_m: float = 0.6
    camera: Camera = field(default_factory=lambda: Camera(width=256, height=192))
    gap_m: float = 60.0  # free space between neighbouring blocks (walls stand <= 25 m out)

    def __post_init__(self) -> None:
        if self.n_images < 1:
            raise ValueError("a long route needs at least one image")

    @property
    def route(self) -> Route:
        return Route(self.loop_length_m)

    @property
    def per_loop(self) -> int:
        """Map images per loop (the world's own frame count for its length and spacing)."""
        return round(self.route.length / self.spacing_m)

    @property
    def n_loops(self) -> int:
        return math.ceil(self.n_images / self.per_loop)

    @property
    def columns(self) -> int:
        return max(1, math.ceil(math.sqrt(self.n_loops)))

    def loop_seed(self, loop: int) -> int:
        return 1000 * (self.seed + 1) + loop

    def loop_origin(self, loop: int) -> np.ndarray:
        """Where loop ``loop``'s local frame lies in the route's frame (a grid of blocks)."""
        x0, y0, x1, y1 = self.route.bounds
        row, col = divmod(loop, self.columns)
        return np.array([col * (x1 - x0 + self.gap_m), row * (y1 - y0 + self.gap_m)])

    def loop_images(self, loop: int) -> int:
        """Map images of this loop that belong to the route (the last loop may be partial)."""
        return int(min(self.per_loop, self.n_images - loop * self.per_loop))

    def world(self, loop: int) -> World:
        from client.lab.world import World

        return World(self.loop_seed(loop), self.loop_length_m, self.spacing_m, self.camera)

    def plan_legs(self, count: int, frames: int, rng: np.random.Generator,
                  loops: int | None = None) -> list[Leg]:
        """``count`` legs of ``frames`` frames at random complete loops (of the first
        ``loops`` loops) and random starts: where a kidnapped robot wakes up."""
        full = [k for k in range(loops or self.n_loops) if self.loop_images(k) >= frames]
        if not full:
            raise ValueError(f"no loop has {frames} frames")
        chosen = rng.choice(full, count, replace=count > len(full))
        return [Leg(f"leg{j:03d}", int(k), int(rng.integers(0, self.loop_images(int(k))
                                                             - frames + 1)), frames)
                for j, k in enumerate(chosen)]


def render_loop(route: LongRoute, loop: int, spill_dir: Path, legs: list[Leg],
                query_dir: Path, params: object) -> Path:
    """Render one loop: its map features into ``spill_dir/loopNNNNN.npz`` and its query legs
    into ``query_dir/LEG`` (dataset rounds). Returns the spill file (kept when it exists)."""
    import cv2

    from client.dataset import write_round
    from client.lab.world.rounds import round_movers, round_trajectory
    from service.vision.features import SiftParams, extract

    assert isinstance(params, SiftParams)
    out = spill_dir / f"loop{loop:05d}.npz"
    todo_legs = [leg for leg in legs if leg.loop == loop
                 and not (query_dir / leg.name / "truth.csv").is_file()]
    if out.is_file() and not todo_legs:
        return out
    world = route.world(loop)
    origin = route.loop_origin(loop)
    scene = world.scene(CONDITION, CONDITION)
    if not out.is_file():
        poses, t, _ = round_trajectory(world, MAP_ROUND, route.per_loop)
        movers = round_movers(world, MAP_ROUND)
        rng = np.random.default_rng([world.seed, 12, MAP_ROUND])
        n = route.loop_images(loop)
        codes, kps, counts = [], [], []
        for k in range(n):
            img = world.renderer.render(scene, Pose(*poses[k]), float(t[k]), movers,
                                        noise_seed=int(rng.integers(2**31)))
            f = extract(img, params)
            codes.append(f.codes)
            kps.append(f.keypoints)
            counts.append(len(f))
        tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}.npz")
        np.savez(tmp, codes=np.concatenate(codes).astype(np.uint8),
                 keypoints=np.concatenate(kps).astype(np.float32),
                 counts=np.asarray(counts, np.int64), xy=poses[:n, :2] + origin)
        os.replace(tmp, out)
    for leg in todo_legs:
        poses, t, _ = round_trajectory(world, QUERY_ROUND, route.per_loop)
        movers = round_movers(world, QUERY_ROUND)
        rng = np.random.default_rng([world.seed, 12, QUERY_ROUND])
        seeds = rng.integers(2**31, size=len(poses))
        d = query_dir / leg.name
        d.mkdir(parents=True, exist_ok=True)
        idx = range(leg.start, leg.start + leg.frames)
        names = [f"{k:05d}.png" for k in idx]
        for k, name in zip(idx, names, strict=True):
            img = world.renderer.render(scene, Pose(*poses[k]), float(t[k]), movers,
                                        noise_seed=int(seeds[k]))
            cv2.imwrite(str(d / name), img)
        xy = poses[leg.start: leg.start + leg.frames, :2] + origin
        tt = t[leg.start: leg.start + leg.frames] - t[leg.start]
        write_round(d, names, xy, tt, truth_xy=xy)
    return out


def _render_one(args: tuple[LongRoute, int, str, list[Leg], str, object]) -> int:
    route, loop, spill, legs, qdir, params = args
    render_loop(route, loop, Path(spill), legs, Path(qdir), params)
    return loop


def render_long_route(route: LongRoute, out_dir: str | Path, legs: list[Leg],
                      params: object, workers: int = 1,
                      progress: Callable[[int], None] | None = None) -> Path:
    """Render every loop's map features and the legs (resumable); ``workers`` processes."""
    out_dir = Path(out_dir)
    spill, qdir = out_dir / "spill", out_dir / "queries"
    spill.mkdir(parents=True, exist_ok=True)
    qdir.mkdir(parents=True, exist_ok=True)
    (out_dir / "route.json").write_text(json.dumps(describe(route, legs), indent=1))
    jobs = [(route, k, str(spill), legs, str(qdir), params) for k in range(route.n_loops)]
    if workers <= 1:
        for job in jobs:
            if progress:
                progress(_render_one(job))
            else:
                _render_one(job)
        return out_dir
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers) as pool:
        for k in pool.map(_render_one, jobs):
            if progress:
                progress(k)
    return out_dir


def describe(route: LongRoute, legs: list[Leg]) -> dict:
    return {"n_images": route.n_images, "seed": route.seed,
            "loop_length_m": route.loop_length_m, "spacing_m": route.spacing_m,
            "camera": route.camera.__dict__, "per_loop": route.per_loop,
            "n_loops": route.n_loops, "condition": CONDITION,
            "legs": [leg.__dict__ for leg in legs]}


def read_legs(out_dir: str | Path) -> list[Leg]:
    meta = json.loads((Path(out_dir) / "route.json").read_text())
    return [Leg(**d) for d in meta["legs"]]


def spill_images(spill_dir: Path, n_images: int
                 ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(codes, keypoints, counts, xy) of the loops in order, cut after ``n_images`` images."""
    left = n_images
    for path in sorted(spill_dir.glob("loop*.npz")):
        if left <= 0:
            return
        with np.load(path) as z:
            counts = z["counts"][:left]
            end = int(counts.sum())
            yield z["codes"][:end], z["keypoints"][:end], counts, z["xy"][:left]
        left -= len(counts)
    if left > 0:
        raise ValueError(f"{spill_dir}: {n_images - left} of {n_images} images rendered; "
                         "render the route first")


class SpillCodes:
    """The spill's descriptor codes per image (one loop's file kept at a time), what the
    place index is built from without assembling a map first."""

    def __init__(self, spill_dir: Path, n_images: int) -> None:
        self.files = sorted(spill_dir.glob("loop*.npz"))
        starts, total = [], 0
        for path in self.files:
            starts.append(total)
            with np.load(path) as z:
                total += len(z["counts"])
        if total < n_images:
            raise ValueError(f"{spill_dir}: {total} of {n_images} images rendered")
        self.starts = np.asarray(starts, np.int64)
        self._n = n_images
        self._loaded: tuple[int, np.ndarray, np.ndarray] | None = None

    @property
    def n_images(self) -> int:
        return self._n

    def codes_of(self, image_id: int) -> np.ndarray:
        k = int(np.searchsorted(self.starts, image_id, side="right") - 1)
        if self._loaded is None or self._loaded[0] != k:
            with np.load(self.files[k]) as z:
                off = np.concatenate([[0], np.cumsum(z["counts"])])
                self._loaded = (k, z["codes"], off)
        _, codes, off = self._loaded
        j = image_id - int(self.starts[k])
        return codes[off[j]: off[j + 1]]


def assemble_maps(out_dir: str | Path, sizes: list[int]) -> list[Path]:
    """Write ``out_dir/maps/route-N.swmap`` (the first N images of the route, with their
    place index) for every size N, streamed from the spill; existing maps are kept."""
    import datetime as dt

    from service.api.round_format import camera_from_hfov
    from service.maps.route_map import SUFFIX, write_map
    from service.vision.features import DEFAULT_DELTA, SiftParams
    from service.vision.place_index import build_place_index

    out_dir = Path(out_dir)
    meta_in = json.loads((out_dir / "route.json").read_text())
    cam = meta_in["camera"]
    params = SiftParams(width=cam["width"], height=cam["height"])
    spill = out_dir / "spill"
    written = []
    for n in sizes:
        path = out_dir / "maps" / f"route-{n}{SUFFIX}"
        if path.is_file():
            written.append(path)
            continue
        xy, counts = [], []
        for _, _, cnt, pos in spill_images(spill, n):
            xy.append(pos)
            counts.append(cnt)
        cnt_all = np.concatenate(counts)
        index = build_place_index(SpillCodes(spill, n), np.random.default_rng(0))
        total = int(cnt_all.sum())
        meta = {"feature": params.as_dict(), "delta": DEFAULT_DELTA,
                "image_size": [params.width, params.height], "origin": None,
                "build_date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                "pruning": {"enabled": False, "features_before": total,
                            "features_after": total, "removed_fraction": 0.0},
                "source": {"long_route": {k: v for k, v in meta_in.items() if k != "legs"},
                           "images": n},
                "camera": camera_from_hfov(cam["hfov_deg"], cam["width"], cam["height"])}
        names = [f"loop{j // meta_in['per_loop']:05d}/{j % meta_in['per_loop']:05d}"
                 for j in range(n)]
        chunks = ((c, k, cnt) for c, k, cnt, _ in spill_images(spill, n))
        written.append(write_map(path, f"route-{n}", meta, np.concatenate(xy), names,
                                 np.zeros(n, np.int64), cnt_all, chunks, index))
    return written
