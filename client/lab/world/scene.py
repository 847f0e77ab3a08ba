"""A scene: one day of the world under one lighting condition, ready to render (texture atlas,
wall segments, shaded ground pyramid, sky panorama, the movers' textures by name)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from client.lab import textures as tx
from client.lab.world.geometry import (
    ATLAS_MARGIN,
    ATLAS_WIDTH,
    GROUND_PPM,
    MIP_LEVELS,
    PPM,
    Condition,
    Route,
    Wall,
)
from client.lab.world.layout import car_box


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


#: the movers' textures, by name: six pedestrians and three cars (the sides of driving cars)
MOVER_PEOPLE = tuple(f"person{i}" for i in range(6))
MOVER_CARS = tuple(f"car{i}" for i in range(3))


@dataclass(frozen=True)
class MoverTexture:
    """Where a mover's texture lies in the atlas, and its size in the world."""

    x0: int
    y0: int
    width_m: float
    height_m: float


@dataclass(frozen=True)
class Mover:
    """A pedestrian or a driving car that moves along the route during a round."""

    texture: str  # a name of MOVER_PEOPLE or MOVER_CARS
    s0: float
    speed: float  # m/s along the route (negative: against the driving direction)
    offset: float  # lateral, left positive
    is_car: bool


@dataclass
class Scene:
    """Everything needed to render one day of the world under one condition."""

    walls: SegmentSet
    atlas: Atlas
    mover_tex: dict[str, MoverTexture]  # by name (MOVER_PEOPLE, MOVER_CARS)
    ground: list[np.ndarray]  # mip pyramid, float32 shaded for the condition
    ground_origin: tuple[float, float]  # world (x_min, y_max) of ground texel (0, 0)
    sky: np.ndarray
    condition: Condition


def ground_texture(route: Route, rng: np.random.Generator, parking: list[tuple[float, float]],
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


def ground_shadows(walls: list[Wall], shape: tuple[int, int], origin: tuple[float, float],
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



def build_scene(seed: int, walls: list[Wall], ground_base: tuple[np.ndarray, tuple[float, float]],
                day: str, cond: Condition) -> Scene:
    """Pack the day's walls and the movers' textures into an atlas; shade ground and sky."""
    rng = np.random.default_rng([seed, 4])
    mover_textures = [tx.person(rng, 0.6, 1.75, PPM) for _ in MOVER_PEOPLE]
    car_sizes = [(rng.uniform(3.8, 4.6), 1.5) for _ in MOVER_CARS]
    mover_textures += [tx.car(rng, ln, ht, PPM, side=True) for ln, ht in car_sizes]
    atlas = pack_atlas([w.texture for w in walls] + mover_textures)
    segs = SegmentSet.from_walls(walls, atlas.offsets[: len(walls)], seed)
    mover_tex = {name: MoverTexture(x0, y0, t[0].shape[1] / PPM, t[0].shape[0] / PPM)
                 for name, (x0, y0), t in zip(MOVER_PEOPLE + MOVER_CARS,
                                              atlas.offsets[len(walls):], mover_textures,
                                              strict=True)}
    base, origin = ground_base
    ground = base * ground_shadows(walls, base.shape, origin, cond)
    pyramid = [ground]
    for _ in range(MIP_LEVELS - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    sky = tx.sky_panorama(np.random.default_rng([seed, 5, *day.encode()]), cond.sunny)
    return Scene(segs, atlas, mover_tex, pyramid, origin, sky, cond)


def mover_segments(route: Route, scene: Scene, movers: Iterable[Mover], t: float
                   ) -> SegmentSet | None:
    """The movers' billboards (a pedestrian) or long sides (a car) at time ``t``."""
    cols: dict[str, list] = {k: [] for k in SegmentSet.__dataclass_fields__}
    for mv in movers:
        tex = scene.mover_tex[mv.texture]
        x0, y0, w_m, h_m = tex.x0, tex.y0, tex.width_m, tex.height_m
        s = mv.s0 + mv.speed * t
        c = route.point(s)[0] + mv.offset * route.normal(s)[0]
        a = float(route.heading(s)[0])
        if mv.is_car:
            box = car_box(c, a, w_m, 1.8)
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
