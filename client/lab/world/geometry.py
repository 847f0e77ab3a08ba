"""The world's primitives: camera, lighting conditions, walls, poses and the route loop."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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

