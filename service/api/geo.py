"""Local metric east/north frame around a stored WGS84 origin (pyproj azimuthal equidistant),
and angles in that frame."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pyproj import Transformer


def wrap_angle(a: float) -> float:
    """``a`` (rad) in [-pi, pi): one definition for headings in the map frame."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class LocalFrame:
    """East/north metres around (lat0, lon0); x = east, y = north."""

    lat0: float
    lon0: float
    _fwd: Transformer = field(init=False, repr=False, compare=False)
    _inv: Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (-90.0 <= self.lat0 <= 90.0 and -180.0 <= self.lon0 <= 180.0):
            raise ValueError(f"origin ({self.lat0}, {self.lon0}) is not a WGS84 lat/lon")
        try:
            from pyproj import Transformer
        except ImportError as exc:
            raise ImportError("geographic (lat/lon) positions need pyproj: "
                              "pip install 'swarmloc[geo]'") from exc
        proj = f"+proj=aeqd +lat_0={self.lat0!r} +lon_0={self.lon0!r} +datum=WGS84 +units=m"
        object.__setattr__(self, "_fwd", Transformer.from_crs("EPSG:4326", proj, always_xy=True))
        object.__setattr__(self, "_inv", Transformer.from_crs(proj, "EPSG:4326", always_xy=True))

    def to_local(self, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """WGS84 degrees -> (N, 2) metres east/north."""
        x, y = self._fwd.transform(np.asarray(lon, float), np.asarray(lat, float))
        return np.column_stack([np.atleast_1d(x), np.atleast_1d(y)])

    def to_geo(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) metres east/north -> (N, 2) lat, lon degrees."""
        xy = np.atleast_2d(np.asarray(xy, float))
        lon, lat = self._inv.transform(xy[:, 0], xy[:, 1])
        return np.column_stack([np.atleast_1d(lat), np.atleast_1d(lon)])
