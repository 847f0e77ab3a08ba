"""Synthetic route world: a closed street loop ray-cast through a pinhole camera.

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

import itertools
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from client.dataset import write_dataset_meta, write_round
from client.lab import textures as tx

PPM = 32.0  # wall texels per metre
GROUND_PPM = 10.0  # ground texels per metre
MIP_LEVELS = 6
ATLAS_WIDTH = 8192
ATLAS_MARGIN = 24
LAYERS = 4  # nearest wall hits kept per image column
MAX_RANGE_M = 120.0


@dataclass(frozen=True)
class Camera:
    width: int = 320
    height: int = 240
    hfov_deg: float = 65.0
    height_m: float = 1.2

    @property
    def focal_px(self) -> float:
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)


@dataclass(frozen=True)
class Condition:
    name: str
    sunny: bool
    sun_azimuth_deg: float  # direction towards the sun, counter-clockwise from east
    sun_elevation_deg: float
    ambient: float
    diffuse: float
    gamma: float
    contrast: float
    white_balance: float  # luminance gain per unit of a material's warm/cool tint
    noise: float = 2.2  # sensor noise std (grey levels of 255)
    gain: float = 1.0  # brightness of the final image (below 1: under-exposed)


CONDITIONS: dict[str, Condition] = {
    "sunny": Condition("sunny", True, 130.0, 38.0, 0.42, 0.85, 1.0, 1.15, -0.06),
    "cloudy": Condition("cloudy", False, 0.0, 90.0, 0.82, 0.0, 1.35, 0.7, 0.18),
    # late afternoon: the sun low in the west, shadows six times as long as their walls,
    # hard contrast and warm light (the hard lighting pair is lowsun map vs cloudy round)
    "lowsun": Condition("lowsun", True, 200.0, 9.0, 0.22, 1.1, 0.85, 1.35, -0.16, 2.5),
    # dusk: flat, dim and noisy, the camera's gain up
    "dusk": Condition("dusk", False, 0.0, 90.0, 0.5, 0.0, 1.7, 0.5, 0.28, 5.0, 0.55),
    # night: almost no light; what the camera sees is noise over faint structure
    "night": Condition("night", False, 0.0, 90.0, 0.08, 0.0, 2.2, 0.12, 0.0, 9.0, 0.3),
}


@dataclass
class Wall:
    """A vertical textured polyline standing on the ground."""

    points: np.ndarray  # (K, 2) metres
    height: float
    texture: tx.Texture
    tint: float = 0.0  # warm (+) / cool (-) material, for white balance
    casts_shadow: float = 1.0  # fraction of light blocked (trees and fences let some through)
    kind: str = ""


@dataclass(frozen=True)
class Pose:
    x: float
    y: float
    heading: float  # radians, counter-clockwise from east
    pitch: float = 0.0  # radians, positive looks up


class Route:
    """A closed rounded-rectangle street loop, parametrised by arc length s."""

    def __init__(self, length_m: float, aspect: float = 1.5, step_m: float = 0.05) -> None:
        r = min(16.0, length_m / 12.0)
        b = (length_m + 8 * r - 2 * math.pi * r) / (2 * (1 + aspect))
        a = aspect * b
        self.corner_radius = r
        pts = []
        # counter-clockwise: straight pieces and quarter arcs
        corners = [(a / 2 - r, -b / 2 + r, -90.0), (a / 2 - r, b / 2 - r, 0.0),
                   (-a / 2 + r, b / 2 - r, 90.0), (-a / 2 + r, -b / 2 + r, 180.0)]
        for cxx, cyy, start in corners:
            ang = np.radians(np.linspace(start, start + 90.0, 64))
            pts.append(np.column_stack([cxx + r * np.cos(ang), cyy + r * np.sin(ang)]))
        poly = np.vstack([*pts, pts[0][:1]])
        seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(cum[-1])
        s = np.arange(0.0, self.length, step_m)
        self._s = s
        self._xy = np.column_stack([np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])])
        d = np.roll(self._xy, -1, axis=0) - np.roll(self._xy, 1, axis=0)
        self._angle = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        self._step = step_m

    def _idx(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = (np.asarray(s, float) % self.length) / self._step
        i0 = np.floor(u).astype(int) % len(self._s)
        return i0, (i0 + 1) % len(self._s), u - np.floor(u)

    def point(self, s: np.ndarray | float) -> np.ndarray:
        i0, i1, w = self._idx(np.atleast_1d(s))
        return self._xy[i0] * (1 - w)[:, None] + self._xy[i1] * w[:, None]

    def heading(self, s: np.ndarray | float) -> np.ndarray:
        i0, _, _ = self._idx(np.atleast_1d(s))
        return self._angle[i0]

    def normal(self, s: np.ndarray | float) -> np.ndarray:
        """Unit left normal (towards the inside of the counter-clockwise loop)."""
        a = self.heading(s)
        return np.column_stack([-np.sin(a), np.cos(a)])

    def offset_polyline(self, s0: float, s1: float, offset: float, step: float = 1.0) -> np.ndarray:
        s = np.linspace(s0, s1, max(2, math.ceil((s1 - s0) / step) + 1))
        return self.point(s) + offset * self.normal(s)

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length and signed lateral offset (left positive) of points near the route."""
        from scipy.spatial import cKDTree

        tree = cKDTree(self._xy)
        _, idx = tree.query(xy)
        a = self._angle[idx]
        rel = xy - self._xy[idx]
        d = -rel[:, 0] * np.sin(a) + rel[:, 1] * np.cos(a)
        return self._s[idx], d

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return (float(self._xy[:, 0].min()), float(self._xy[:, 1].min()),
                float(self._xy[:, 0].max()), float(self._xy[:, 1].max()))


@dataclass
class Atlas:
    """All wall textures packed into shelves, with a mip pyramid for distance look-ups."""

    levels: list[np.ndarray]  # luminance uint8
    alpha: list[np.ndarray]  # alpha uint8
    offsets: list[tuple[int, int]]  # (x0, y0) of each texture in level 0


def pack_atlas(textures: list[tx.Texture]) -> Atlas:
    order = sorted(range(len(textures)), key=lambda i: -textures[i][0].shape[0])
    offsets: list[tuple[int, int]] = [(0, 0)] * len(textures)
    shelf_y, shelf_h, x = ATLAS_MARGIN, 0, ATLAS_MARGIN
    for i in order:
        h, w = textures[i][0].shape
        if w + 2 * ATLAS_MARGIN > ATLAS_WIDTH:
            raise ValueError(f"texture of {w} px does not fit the atlas width {ATLAS_WIDTH}")
        if x + w + ATLAS_MARGIN > ATLAS_WIDTH or shelf_h == 0:
            shelf_y += shelf_h + (ATLAS_MARGIN if shelf_h else 0)
            shelf_h, x = h, ATLAS_MARGIN
        offsets[i] = (x, shelf_y)
        x += w + ATLAS_MARGIN
    total_h = shelf_y + shelf_h + ATLAS_MARGIN
    total_h += (-total_h) % (1 << MIP_LEVELS)
    lum = np.zeros((total_h, ATLAS_WIDTH), np.uint8)
    alpha = np.zeros((total_h, ATLAS_WIDTH), np.uint8)
    for (img, a), (x0, y0) in zip(textures, offsets, strict=True):
        h, w = img.shape
        lum[y0 : y0 + h, x0 : x0 + w] = np.round(img * 255).astype(np.uint8)
        alpha[y0 : y0 + h, x0 : x0 + w] = a
    levels, alphas = [lum], [alpha]
    for _ in range(MIP_LEVELS - 1):
        levels.append(cv2.pyrDown(levels[-1]))
        alphas.append(cv2.pyrDown(alphas[-1]))
    return Atlas(levels, alphas, offsets)


@dataclass
class SegmentSet:
    """Wall polylines flattened into straight segments with their atlas coordinates."""

    p0: np.ndarray
    p1: np.ndarray
    height: np.ndarray
    u0: np.ndarray  # atlas column at p0 (level-0 texels)
    v_top: np.ndarray  # atlas row of the wall top
    length: np.ndarray
    tint: np.ndarray
    phase: np.ndarray  # per-wall phase of the sunny shadow bands

    @staticmethod
    def from_walls(walls: list[Wall], offsets: list[tuple[int, int]], seed: int) -> SegmentSet:
        rng = np.random.default_rng(seed)
        cols: dict[str, list] = {k: [] for k in
                                 ("p0", "p1", "height", "u0", "v_top", "length", "tint", "phase")}
        for wall, (x0, y0) in zip(walls, offsets, strict=True):
            pts = wall.points
            seg_len = np.linalg.norm(np.diff(pts, axis=0), axis=1)
            along = np.concatenate([[0.0], np.cumsum(seg_len)])[:-1]
            n = len(seg_len)
            cols["p0"].append(pts[:-1])
            cols["p1"].append(pts[1:])
            cols["height"].append(np.full(n, wall.height))
            cols["u0"].append(x0 + along * PPM)
            cols["v_top"].append(np.full(n, float(y0)))
            cols["length"].append(seg_len)
            cols["tint"].append(np.full(n, wall.tint))
            cols["phase"].append(np.full(n, rng.uniform(0, 2 * math.pi)))
        return SegmentSet(**{k: np.concatenate(v) for k, v in cols.items()})

    def concat(self, other: SegmentSet) -> SegmentSet:
        return SegmentSet(**{k: np.concatenate([getattr(self, k), getattr(other, k)])
                             for k in self.__dataclass_fields__})


@dataclass(frozen=True)
class Mover:
    """A pedestrian or a driving car that moves along the route during a round."""

    texture_index: int  # index into Scene.mover_textures
    s0: float
    speed: float  # m/s along the route (negative: against the driving direction)
    offset: float  # lateral, left positive
    is_car: bool


@dataclass
class Scene:
    """Everything needed to render one day of the world under one condition."""

    walls: SegmentSet
    atlas: Atlas
    mover_tex: list[tuple[int, int, float, float]]  # (x0, y0, width_m, height_m) per mover
    ground: list[np.ndarray]  # mip pyramid, float32 shaded for the condition
    ground_origin: tuple[float, float]  # world (x_min, y_max) of ground texel (0, 0)
    sky: np.ndarray
    condition: Condition


def _ground_texture(route: Route, rng: np.random.Generator, parking: list[tuple[float, float]],
                    ) -> tuple[np.ndarray, tuple[float, float]]:
    x0, y0, x1, y1 = route.bounds
    m = 45.0
    w, h = int((x1 - x0 + 2 * m) * GROUND_PPM), int((y1 - y0 + 2 * m) * GROUND_PPM)
    gx, gy = np.meshgrid((np.arange(w) + 0.5) / GROUND_PPM + x0 - m,
                         y1 + m - (np.arange(h) + 0.5) / GROUND_PPM)
    # route coordinates on a 4x coarser grid, interpolated (arc length via its angle on the loop)
    cs = 4
    s_c, d_c = route.project(np.column_stack([gx[::cs, ::cs].ravel(), gy[::cs, ::cs].ravel()]))
    shape_c = gx[::cs, ::cs].shape
    ang = 2 * np.pi * s_c.reshape(shape_c) / route.length

    def up(a: np.ndarray) -> np.ndarray:
        big = cv2.resize(a.astype(np.float32), (shape_c[1] * cs, shape_c[0] * cs),
                         interpolation=cv2.INTER_LINEAR)
        return big[:h, :w]

    d = up(d_c.reshape(shape_c))
    s = (np.arctan2(up(np.sin(ang)), up(np.cos(ang))) % (2 * np.pi)) * route.length / (2 * np.pi)
    asphalt = 0.33 + 0.05 * tx.value_noise(rng, (h, w), 30) + 0.04 * tx.value_noise(rng, (h, w), 3)
    grass = 0.3 + 0.09 * tx.value_noise(rng, (h, w), 12) + 0.06 * tx.value_noise(rng, (h, w), 2)
    tiles = 0.55 + 0.04 * tx.value_noise(rng, (h, w), 20)
    grid = ((gx % 0.5) < 0.04) | ((gy % 0.5) < 0.04)
    tiles = np.where(grid, tiles - 0.12, tiles)
    ad = np.abs(d)
    img = np.where(ad < 3.5, asphalt, np.where(ad < 6.0, tiles, grass))
    img = np.where((ad >= 3.5) & (ad < 3.7), 0.7, img)  # curb
    img = np.where((ad > 3.1) & (ad < 3.25), 0.8, img)  # edge line
    dash = (np.abs(d) < 0.08) & ((s % 6.0) < 3.0)
    img = np.where(dash, 0.85, img)
    for p0, p1 in parking:
        inside = (s > p0) & (s < p1) & (d < -6.0) & (d > -16.0)
        img = np.where(inside, asphalt + 0.02, img)
        img = np.where(inside & ((s % 2.6) < 0.1) & (d < -8.0), 0.8, img)
    for _ in range(int(route.length / 25)):  # manholes and patches
        at = rng.uniform(0, route.length)
        c = route.point(at)[0] + rng.uniform(-2.5, 2.5) * route.normal(at)[0]
        cx, cy = int((c[0] - x0 + m) * GROUND_PPM), int((y1 + m - c[1]) * GROUND_PPM)
        cv2.circle(img, (cx, cy), int(0.35 * GROUND_PPM), 0.18, -1)
        cv2.circle(img, (cx, cy), int(0.35 * GROUND_PPM), 0.45, 1)
    return np.clip(img, 0, 1).astype(np.float32), (x0 - m, y1 + m)


def _ground_shadows(walls: list[Wall], shape: tuple[int, int], origin: tuple[float, float],
                    cond: Condition) -> np.ndarray:
    """Light factor on the ground: every wall casts its shadow polygon away from the sun."""
    occlusion = np.zeros(shape, np.float32)
    if not cond.sunny:
        return 1.0 - occlusion
    az, el = math.radians(cond.sun_azimuth_deg), math.radians(cond.sun_elevation_deg)
    away = -np.array([math.cos(az), math.sin(az)]) / math.tan(el)
    ox, oy = origin
    # draw weak occluders first so that overlapping stronger shadows overwrite them
    for wall in sorted(walls, key=lambda w: w.casts_shadow):
        p = wall.points
        for a, b in itertools.pairwise(p):
            quad = np.array([a, b, b + wall.height * away, a + wall.height * away])
            pix = np.column_stack([(quad[:, 0] - ox) * GROUND_PPM, (oy - quad[:, 1]) * GROUND_PPM])
            cv2.fillConvexPoly(occlusion, np.round(pix).astype(np.int32),
                               0.6 * wall.casts_shadow)
    light = 1.0 - occlusion
    return cv2.GaussianBlur(light, (0, 0), 1.2)


class World:
    """A seeded street loop: route, static walls, parked cars per day, scenes, rendering."""

    def __init__(self, seed: int = 0, length_m: float = 260.0, spacing_m: float = 0.6,
                 camera: Camera | None = None) -> None:
        self.seed = seed
        self.camera = camera or Camera()
        self.spacing_m = spacing_m
        self.route = Route(length_m)
        rng = np.random.default_rng([seed, 1])
        self.parking: list[tuple[float, float]] = []
        self.static_walls = self._layout(rng)
        self._scenes: dict[tuple[str, str], Scene] = {}

    # ---- layout -------------------------------------------------------------------------
    def _layout(self, rng: np.random.Generator) -> list[Wall]:
        route, L = self.route, self.route.length
        inner_max = min(9.0, 0.75 * route.corner_radius)
        walls: list[Wall] = []

        def add(kind: Callable[..., tx.Texture], pts: np.ndarray, height: float,
                shadow: float = 1.0, **kw: object) -> None:
            length = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
            walls.append(Wall(pts, height, kind(rng, length, height, PPM, **kw),
                              rng.uniform(-1, 1), shadow, kind.__name__))

        for side in (+1, -1):
            s = rng.uniform(0, 5)
            end = s + L - 2.0
            if side == -1 and L > 120:
                p0 = rng.uniform(0.1, 0.5) * L
                self.parking.append((p0, p0 + min(45.0, 0.18 * L)))
            while s < end:
                seg = min(rng.uniform(10, 28), end - s)
                in_parking = any(p0 - 2 < s + seg / 2 < p1 + 2 for p0, p1 in self.parking)
                if side == -1 and in_parking:
                    p0, p1 = next(p for p in self.parking if p[0] - 2 < s + seg / 2 < p[1] + 2)
                    add(tx.fence, route.offset_polyline(p0, p1, -17.0), 1.8, 0.4)
                    add(tx.facade, route.offset_polyline(p0 - 4, p1 + 4, -24.0),
                        rng.uniform(9, 16))
                    s = p1 + 1.0
                    continue
                r = rng.random()
                if side == +1:
                    off = rng.uniform(0.7, 1.0) * inner_max
                else:
                    off = rng.uniform(7.0, 11.0)
                if r < 0.6:
                    add(tx.facade, route.offset_polyline(s, s + seg, side * off),
                        rng.uniform(6.5, 15.0))
                elif r < 0.8:
                    add(tx.hedge, route.offset_polyline(s, s + seg, side * 4.6),
                        rng.uniform(1.1, 1.9), 0.9)
                    add(tx.facade, route.offset_polyline(s - 2, s + seg + 2, side * (off + 2)),
                        rng.uniform(6.5, 12.0))
                else:
                    kind = tx.low_wall if rng.random() < 0.5 else tx.fence
                    add(kind, route.offset_polyline(s, s + seg, side * 4.8),
                        rng.uniform(0.8, 1.6), 0.7 if kind is tx.fence else 1.0)
                    add(tx.facade, route.offset_polyline(s - 2, s + seg + 2, side * (off + 3)),
                        rng.uniform(6.5, 12.0))
                s += seg + (rng.uniform(0.5, 4.0) if rng.random() < 0.6 else 0.0)
        for s in np.arange(rng.uniform(0, 10), L, 1.0):  # trees and sign posts
            if rng.random() < 0.045:
                side = rng.choice([-1, 1])
                c = route.point(s)[0] + side * 5.4 * route.normal(s)[0]
                a = rng.uniform(0, math.pi)
                w = rng.uniform(2.5, 4.5)
                d = 0.5 * w * np.array([math.cos(a), math.sin(a)])
                add(tx.tree, np.array([c - d, c + d]), rng.uniform(5.0, 8.0), 0.6)
                d2 = np.array([-d[1], d[0]])
                add(tx.tree, np.array([c - d2, c + d2]), rng.uniform(5.0, 8.0), 0.6)
            elif rng.random() < 0.03:
                side = rng.choice([-1, 1])
                c = route.point(s)[0] + side * 3.9 * route.normal(s)[0]
                t = np.array([math.cos(route.heading(s)[0]), math.sin(route.heading(s)[0])])
                n = np.array([-t[1], t[0]]) * rng.uniform(0.5, 0.9) * 0.5
                add(tx.signpost, np.array([c - n, c + n]), rng.uniform(2.4, 3.0), 0.2)
        return walls

    def _car_box(self, center: np.ndarray, heading: float, length: float, width: float
                 ) -> list[np.ndarray]:
        t = np.array([math.cos(heading), math.sin(heading)]) * length / 2
        n = np.array([-math.sin(heading), math.cos(heading)]) * width / 2
        c = [center - t - n, center + t - n, center + t + n, center - t + n]
        return [np.array([c[0], c[1]]), np.array([c[1], c[2]]),
                np.array([c[2], c[3]]), np.array([c[3], c[0]])]

    def _cars(self, rng: np.random.Generator, center: np.ndarray, heading: float) -> list[Wall]:
        length, width, height = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.6)
        side_tex = tx.car(rng, length, height, PPM, side=True)
        end_tex = tx.car(rng, width, height, PPM, side=False)
        tint = rng.uniform(-1, 1)
        return [Wall(pts, height, side_tex if k % 2 == 0 else end_tex, tint, 1.0)
                for k, pts in enumerate(self._car_box(center, heading, length, width))]

    def day_walls(self, day: str) -> list[Wall]:
        """Parked cars of one day: street parking and the parking lot differ between days."""
        rng = np.random.default_rng([self.seed, 2, *day.encode()])
        route, walls = self.route, []
        for p0, p1 in self.parking:
            for s in np.arange(p0 + 1.5, p1 - 1.5, 2.6):
                if rng.random() < 0.65:
                    c = route.point(s)[0] - 10.5 * route.normal(s)[0]
                    walls += self._cars(rng, c, float(route.heading(s)[0]) + math.pi / 2
                                        + rng.normal(0, 0.05))
        s = 0.0
        while s < route.length:
            if rng.random() < 0.12 and not any(p0 - 6 < s < p1 + 6 for p0, p1 in self.parking):
                c = route.point(s)[0] - 4.6 * route.normal(s)[0]
                walls += self._cars(rng, c, float(route.heading(s)[0]) + rng.normal(0, 0.03))
                s += rng.uniform(5.5, 7.0)
            else:
                s += rng.uniform(3, 12)
        return walls

    # ---- scenes -------------------------------------------------------------------------
    def scene(self, day: str, condition: str) -> Scene:
        key = (day, condition)
        if key not in self._scenes:
            self._scenes[key] = self._build_scene(day, CONDITIONS[condition])
        return self._scenes[key]

    @cached_property
    def _ground_base(self) -> tuple[np.ndarray, tuple[float, float]]:
        return _ground_texture(self.route, np.random.default_rng([self.seed, 3]), self.parking)

    def _seasonal(self, day: str) -> list[Wall]:
        """Vegetation grows and sheds between days: hedges and trees get new foliage."""
        rng = np.random.default_rng([self.seed, 6, *day.encode()])
        out = []
        for w in self.static_walls:
            if w.kind in ("hedge", "tree"):
                length = float(np.sum(np.linalg.norm(np.diff(w.points, axis=0), axis=1)))
                gen = tx.hedge if w.kind == "hedge" else tx.tree
                w = Wall(w.points, w.height, gen(rng, length, w.height, PPM), w.tint,
                         w.casts_shadow, w.kind)
            out.append(w)
        return out

    def _build_scene(self, day: str, cond: Condition) -> Scene:
        walls = self._seasonal(day) + self.day_walls(day)
        rng = np.random.default_rng([self.seed, 4])
        mover_textures = [tx.person(rng, 0.6, 1.75, PPM) for _ in range(6)]
        car_sizes = [(rng.uniform(3.8, 4.6), 1.5) for _ in range(3)]
        mover_textures += [tx.car(rng, ln, ht, PPM, side=True) for ln, ht in car_sizes]
        atlas = pack_atlas([w.texture for w in walls] + mover_textures)
        segs = SegmentSet.from_walls(walls, atlas.offsets[: len(walls)], self.seed)
        mover_tex = [(x0, y0, t[0].shape[1] / PPM, t[0].shape[0] / PPM)
                     for (x0, y0), t in zip(atlas.offsets[len(walls):], mover_textures,
                                            strict=True)]
        base, origin = self._ground_base
        ground = base * _ground_shadows(walls, base.shape, origin, cond)
        pyramid = [ground]
        for _ in range(MIP_LEVELS - 1):
            pyramid.append(cv2.pyrDown(pyramid[-1]))
        sky = tx.sky_panorama(np.random.default_rng([self.seed, 5, *day.encode()]), cond.sunny)
        return Scene(segs, atlas, mover_tex, pyramid, origin, sky, cond)

    # ---- rendering ----------------------------------------------------------------------
    def _mover_segments(self, scene: Scene, movers: Iterable[Mover], t: float) -> SegmentSet | None:
        cols: dict[str, list] = {k: [] for k in SegmentSet.__dataclass_fields__}
        for mv in movers:
            x0, y0, w_m, h_m = scene.mover_tex[mv.texture_index]
            s = mv.s0 + mv.speed * t
            c = self.route.point(s)[0] + mv.offset * self.route.normal(s)[0]
            a = float(self.route.heading(s)[0])
            if mv.is_car:
                box = self._car_box(c, a, w_m, 1.8)
                segs = [box[0], box[2][::-1]]  # both long sides show the side texture
            else:
                n = np.array([-math.sin(a), math.cos(a)]) * w_m / 2
                segs = [np.array([c - n, c + n])]
            for p in segs:
                cols["p0"].append(p[:1])
                cols["p1"].append(p[1:])
                cols["height"].append([h_m])
                cols["u0"].append([float(x0)])
                cols["v_top"].append([float(y0)])
                cols["length"].append([w_m])
                cols["tint"].append([0.0])
                cols["phase"].append([0.0])
        if not cols["p0"]:
            return None
        return SegmentSet(**{k: np.concatenate([np.asarray(v, float) for v in vals])
                             for k, vals in cols.items()})

    def render(self, pose: Pose, condition: str = "sunny", day: str | None = None,
               t: float = 0.0, movers: Iterable[Mover] = (), noise_seed: int | None = None,
               exposure: float = 1.0) -> np.ndarray:
        """Render one grayscale frame (uint8, camera.height x camera.width)."""
        scene = self.scene(day or condition, condition)
        cam, cond = self.camera, scene.condition
        W, H, f, hc = cam.width, cam.height, cam.focal_px, cam.height_m
        cx, cy = W / 2, H / 2 - f * math.tan(pose.pitch)
        xc = (np.arange(W) + 0.5 - cx) / f
        fwd = np.array([math.cos(pose.heading), math.sin(pose.heading)])
        right = np.array([math.sin(pose.heading), -math.cos(pose.heading)])
        D = fwd[None, :] + xc[:, None] * right[None, :]  # (W, 2); ray parameter = depth
        C = np.array([pose.x, pose.y])
        slope = (cy - (np.arange(H) + 0.5)) / f  # (H,) tan of elevation per row (over depth)

        out = self._sky(scene, pose, xc, slope)
        g_val, g_mask = self._ground(scene, C, D, slope)
        out[g_mask] = g_val[g_mask]

        segs = scene.walls
        moving = self._mover_segments(scene, movers, t)
        if moving is not None:
            segs = segs.concat(moving)
        mid = 0.5 * (segs.p0 + segs.p1) - C
        near = np.einsum("ij,ij->i", mid, mid) < (MAX_RANGE_M + 0.5 * segs.length) ** 2
        idx_s = np.flatnonzero(near)
        p0, p1 = segs.p0[idx_s], segs.p1[idx_s]
        E = p1 - p0
        rel = p0 - C
        denom = D[:, 0:1] * E[None, :, 1] - D[:, 1:2] * E[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            th = (rel[None, :, 0] * E[None, :, 1] - rel[None, :, 1] * E[None, :, 0]) / denom
            sh = (rel[None, :, 0] * D[:, 1:2] - rel[None, :, 1] * D[:, 0:1]) / denom
        ok = (np.abs(denom) > 1e-12) & (th > 0.3) & (sh >= 0) & (sh <= 1)
        th = np.where(ok, th, np.inf)
        nl = min(LAYERS, th.shape[1])
        if nl == 0:
            return self._finish(out, cond, pose, noise_seed, exposure)
        part = np.argpartition(th, nl - 1, axis=1)[:, :nl] if th.shape[1] > nl else \
            np.tile(np.arange(nl), (W, 1))
        tl = np.take_along_axis(th, part, axis=1)
        order = np.argsort(-tl, axis=1)  # far to near
        part = np.take_along_axis(part, order, axis=1)
        tl = np.take_along_axis(tl, order, axis=1)
        sl = np.take_along_axis(sh, part, axis=1)

        # per-segment shading: orientation to the sun, seen from the camera's side
        n = np.column_stack([-E[:, 1], E[:, 0]]) / np.maximum(
            np.linalg.norm(E, axis=1, keepdims=True), 1e-9)
        facing = np.sign(np.einsum("ij,ij->i", n, -rel))
        n = n * facing[:, None]
        if cond.sunny:
            az, el = math.radians(cond.sun_azimuth_deg), math.radians(cond.sun_elevation_deg)
            sun = np.array([math.cos(az), math.sin(az)]) * math.cos(el)
            shade = cond.ambient + cond.diffuse * np.clip(n @ sun, 0, None)
        else:
            shade = np.full(len(idx_s), cond.ambient)
        shade = shade * (1 + cond.white_balance * segs.tint[idx_s])

        for k in range(nl):
            depth = tl[:, k]
            valid_col = np.isfinite(depth)
            if not valid_col.any():
                continue
            local = part[:, k]
            gid = idx_s[local]
            depth_f = np.where(valid_col, depth, 1.0)
            z = hc + slope[:, None] * depth_f[None, :]  # (H, W) height on the wall
            hgt = segs.height[gid]
            au = segs.u0[gid] + sl[:, k] * segs.length[gid] * PPM
            av = segs.v_top[gid][None, :] + (hgt[None, :] - z) * PPM
            vis = valid_col[None, :] & (z >= 0) & (z <= hgt[None, :])
            lvl = np.clip(np.round(np.log2(np.maximum(depth_f * PPM / f, 1.0))), 0,
                          MIP_LEVELS - 1).astype(int)
            val = np.zeros((H, W), np.float32)
            alp = np.zeros((H, W), np.float32)
            for lv in np.unique(lvl[valid_col]):
                colm = (lvl == lv) & valid_col
                sc = 1.0 / (1 << lv)
                mx = np.broadcast_to(au[colm][None, :] * sc - 0.5, (H, int(colm.sum())))
                my = av[:, colm] * sc - 0.5
                mx, my = np.ascontiguousarray(mx, np.float32), np.ascontiguousarray(my, np.float32)
                val[:, colm] = cv2.remap(scene.atlas.levels[lv], mx, my, cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT)
                alp[:, colm] = cv2.remap(scene.atlas.alpha[lv], mx, my, cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT)
            vis &= alp > 127
            lit = val / 255.0 * shade[local][None, :]
            if cond.sunny:  # soft diagonal shadow bands (trees, poles, roofs across the street)
                ph = segs.phase[gid][None, :]
                band = np.sin(au[None, :] / PPM * 0.6 + av / PPM * 0.45 + ph)
                lit = lit * np.where((band > 0.8) & (np.sin(3 * ph) > 0.3), 0.6, 1.0)
                # shadow of the buildings across the street: a sloped line on the facade
                z_sh = hgt * (0.45 + 0.35 * np.sin(au / PPM * 0.08 + 2 * ph[0]))
                lit = lit * np.where((z < z_sh[None, :]) & (np.cos(5 * ph) > -0.2), 0.5, 1.0)
            haze = np.exp(-depth_f / 400.0)[None, :]
            lit = lit * haze + 0.8 * (1 - haze)
            out[vis] = lit[vis]
        return self._finish(out, cond, pose, noise_seed, exposure)

    def _sky(self, scene: Scene, pose: Pose, xc: np.ndarray, slope: np.ndarray) -> np.ndarray:
        sky = scene.sky
        ppd = sky.shape[1] / 360.0
        az = (math.degrees(pose.heading) - np.degrees(np.arctan(xc))) % 360.0
        el = np.degrees(np.arctan(slope[:, None] / np.sqrt(1 + xc[None, :] ** 2)))
        mx = np.broadcast_to(az[None, :] * ppd, el.shape).astype(np.float32)
        my = ((60.0 - np.clip(el, 0, 60)) * ppd).astype(np.float32)
        return cv2.remap(sky, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def _ground(self, scene: Scene, C: np.ndarray, D: np.ndarray, slope: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        H, W = len(slope), len(D)
        hc, f = self.camera.height_m, self.camera.focal_px
        rows = slope < -1e-6
        depth = np.where(rows, hc / np.where(rows, -slope, 1.0), np.inf)
        val = np.zeros((H, W), np.float32)
        mask = np.zeros((H, W), bool)
        ox, oy = scene.ground_origin
        footprint = depth / f * np.sqrt(np.maximum(depth / hc, 1.0)) * GROUND_PPM
        lvl = np.clip(np.round(np.log2(np.maximum(footprint, 1.0))), 0, MIP_LEVELS - 1)
        for lv in np.unique(lvl[rows]):
            r = rows & (lvl == lv)
            dep = depth[r][:, None]
            px = C[0] + dep * D[None, :, 0]
            py = C[1] + dep * D[None, :, 1]
            sc = 1.0 / (1 << int(lv))
            mx = ((px - ox) * GROUND_PPM * sc - 0.5).astype(np.float32)
            my = ((oy - py) * GROUND_PPM * sc - 0.5).astype(np.float32)
            g = cv2.remap(scene.ground[int(lv)], mx, my, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)
            haze = np.exp(-dep / 400.0)
            val[r] = g * haze + 0.8 * (1 - haze)
            mask[r] = True
        return val, mask

    def _finish(self, img: np.ndarray, cond: Condition, pose: Pose, noise_seed: int | None,
                exposure: float) -> np.ndarray:
        img = np.clip(img * exposure, 0, 1)
        mean = float(img.mean())
        img = np.clip(0.5 + (img - mean) * cond.contrast + 0.5 * (0.48 - mean), 0, 1) ** cond.gamma
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.55) * cond.gain
        if noise_seed is not None:
            rng = np.random.default_rng(noise_seed)
            img = img + rng.normal(0, cond.noise / 255, img.shape)
        return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)

    # ---- rounds -------------------------------------------------------------------------
    def round_trajectory(self, round_index: int, n_frames: int | None = None,
                         speed_mps: float = 0.6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact poses (x, y, heading, pitch) and times of one round, deterministic by index."""
        rng = np.random.default_rng([self.seed, 10, round_index])
        L = self.route.length
        n = n_frames or round(L / self.spacing_m)

        def smooth(amp: float, corr: float) -> np.ndarray:
            raw = rng.normal(0, 1, n + 64)
            k = np.exp(-0.5 * (np.arange(-32, 33) / corr) ** 2)
            sm = np.convolve(raw, k / np.sqrt(np.sum(k**2)), mode="same")[32 : 32 + n]
            return amp * sm

        step = self.spacing_m * (1 + smooth(0.06, 6.0))
        s = np.concatenate([[0.0], np.cumsum(step[:-1])]) + rng.uniform(0, 1.0)
        lateral = -1.3 + rng.uniform(-0.6, 0.6) + smooth(0.3, 15.0)
        pts = self.route.point(s) + lateral[:, None] * self.route.normal(s)
        dlat = np.gradient(lateral) / np.maximum(step, 1e-3)
        heading = self.route.heading(s) + np.arctan(dlat) + np.radians(
            smooth(3.0, 8.0) + rng.normal(0, 0.5, n))
        pitch = np.radians(smooth(0.8, 6.0))
        t = np.cumsum(step) / speed_mps - step[0] / speed_mps
        return np.column_stack([pts, heading, pitch]), t, s

    def movers(self, round_index: int, scene: Scene) -> list[Mover]:
        rng = np.random.default_rng([self.seed, 11, round_index])
        L = self.route.length
        n_people = rng.poisson(L / 25)
        n_cars = rng.poisson(L / 90)
        people = [Mover(int(rng.integers(0, 6)), rng.uniform(0, L), rng.choice([-1, 1])
                        * rng.uniform(0.8, 1.5), rng.choice([-1, 1]) * rng.uniform(4.0, 5.6), False)
                  for _ in range(n_people)]
        cars = [Mover(6 + int(rng.integers(0, 3)), rng.uniform(0, L), rng.uniform(-8, -3),
                      1.6, True) for _ in range(n_cars)]
        return people + cars

    def render_round(self, out_dir: str | Path, round_index: int, condition: str,
                     day: str | None = None, n_frames: int | None = None,
                     gps_noise_m: float = 0.3, progress: bool = False) -> Path:
        """Render a round into ``out_dir`` (images, poses.csv with GPS-like noise, truth.csv)."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        day = day or condition
        scene = self.scene(day, condition)
        poses, t, _ = self.round_trajectory(round_index, n_frames)
        movers = self.movers(round_index, scene)
        rng = np.random.default_rng([self.seed, 12, round_index])
        exposure = 1 + 0.04 * np.sin(np.arange(len(poses)) / 17.0 + rng.uniform(0, 6))
        names = [f"{k:05d}.png" for k in range(len(poses))]
        it = range(len(poses))
        if progress:
            from tqdm import tqdm

            it = tqdm(it, desc=f"round {round_index} ({condition})", unit="frame")
        for k in it:
            img = self.render(Pose(*poses[k]), condition, day, float(t[k]), movers,
                              noise_seed=int(rng.integers(2**31)), exposure=float(exposure[k]))
            cv2.imwrite(str(out_dir / names[k]), img)
        gps = poses[:, :2] + _correlated_noise(rng, len(poses), gps_noise_m)
        write_round(out_dir, names, gps, t, truth_xy=poses[:, :2])
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


def render_dataset(out_dir: str | Path, spec: DatasetSpec, progress: bool = False,
                   only: Iterable[str] | None = None) -> Path:
    out_dir = Path(out_dir)
    world = World(spec.seed, spec.length_m, spec.spacing_m)
    wanted = set(only) if only else None
    known = {r.name for r in spec.rounds + spec.extra_rounds}
    if wanted and wanted - known:
        raise ValueError(f"unknown round(s) {sorted(wanted - known)}; known: {sorted(known)}")
    for r in spec.rounds + spec.extra_rounds:
        if (r in spec.rounds and wanted is None) or (wanted is not None and r.name in wanted):
            world.render_round(out_dir / r.name, r.index, r.condition, r.day, progress=progress)
    write_dataset_meta(out_dir, {
        "name": f"swarmloc-world-{spec.seed}",
        "description": "Synthetic street loop rendered by swarmloc (client/world.py)",
        "generator": {"seed": spec.seed, "length_m": spec.length_m,
                      "spacing_m": spec.spacing_m, "route_length_m": world.route.length},
        "rounds": {r.name: {"condition": r.condition, "day": r.day, "index": r.index}
                   for r in spec.rounds + spec.extra_rounds
                   if (out_dir / r.name).is_dir()},
        "camera": world.camera.__dict__,
    })
    return out_dir


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
