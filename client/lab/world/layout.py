"""The world's layout: static walls along the loop, parked cars per day, vegetation per day."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from client.lab import textures as tx
from client.lab.world.geometry import PPM, Route, Wall


def static_walls(route: Route, rng: np.random.Generator, parking: list[tuple[float, float]]
                 ) -> list[Wall]:
    """Facades, hedges, fences, low walls, trees and sign posts along both sides of the loop;
    the parking lots' spans are appended to ``parking``."""
    L = route.length
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
            parking.append((p0, p0 + min(45.0, 0.18 * L)))
        while s < end:
            seg = min(rng.uniform(10, 28), end - s)
            in_parking = any(p0 - 2 < s + seg / 2 < p1 + 2 for p0, p1 in parking)
            if side == -1 and in_parking:
                p0, p1 = next(p for p in parking if p[0] - 2 < s + seg / 2 < p[1] + 2)
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


def car_box(center: np.ndarray, heading: float, length: float, width: float
             ) -> list[np.ndarray]:
    t = np.array([math.cos(heading), math.sin(heading)]) * length / 2
    n = np.array([-math.sin(heading), math.cos(heading)]) * width / 2
    c = [center - t - n, center + t - n, center + t + n, center - t + n]
    return [np.array([c[0], c[1]]), np.array([c[1], c[2]]),
            np.array([c[2], c[3]]), np.array([c[3], c[0]])]


def cars(rng: np.random.Generator, center: np.ndarray, heading: float) -> list[Wall]:
    length, width, height = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.6)
    side_tex = tx.car(rng, length, height, PPM, side=True)
    end_tex = tx.car(rng, width, height, PPM, side=False)
    tint = rng.uniform(-1, 1)
    return [Wall(pts, height, side_tex if k % 2 == 0 else end_tex, tint, 1.0)
            for k, pts in enumerate(car_box(center, heading, length, width))]


def day_walls(seed: int, route: Route, parking: list[tuple[float, float]], day: str
              ) -> list[Wall]:
    """Parked cars of one day: street parking and the parking lot differ between days."""
    rng = np.random.default_rng([seed, 2, *day.encode()])
    walls: list[Wall] = []
    for p0, p1 in parking:
        for s in np.arange(p0 + 1.5, p1 - 1.5, 2.6):
            if rng.random() < 0.65:
                c = route.point(s)[0] - 10.5 * route.normal(s)[0]
                walls += cars(rng, c, float(route.heading(s)[0]) + math.pi / 2
                                    + rng.normal(0, 0.05))
    s = 0.0
    while s < route.length:
        if rng.random() < 0.12 and not any(p0 - 6 < s < p1 + 6 for p0, p1 in parking):
            c = route.point(s)[0] - 4.6 * route.normal(s)[0]
            walls += cars(rng, c, float(route.heading(s)[0]) + rng.normal(0, 0.03))
            s += rng.uniform(5.5, 7.0)
        else:
            s += rng.uniform(3, 12)
    return walls



def seasonal_walls(seed: int, walls: list[Wall], day: str) -> list[Wall]:
    """Vegetation grows and sheds between days: hedges and trees get new foliage."""
    rng = np.random.default_rng([seed, 6, *day.encode()])
    out = []
    for w in walls:
        if w.kind in ("hedge", "tree"):
            length = float(np.sum(np.linalg.norm(np.diff(w.points, axis=0), axis=1)))
            gen = tx.hedge if w.kind == "hedge" else tx.tree
            w = Wall(w.points, w.height, gen(rng, length, w.height, PPM), w.tint,
                     w.casts_shadow, w.kind)
        out.append(w)
    return out
