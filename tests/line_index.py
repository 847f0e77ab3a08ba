"""An estimator's view of a map for the estimators' own tests: images on a line."""

from __future__ import annotations

import numpy as np


class LineIndex:
    """``n`` images on a line ``spacing`` m apart (what an estimator needs of a map:
    service/estimators/fitness.py ``MapIndex``)."""

    def __init__(self, n: int, spacing: float) -> None:
        self.positions = np.column_stack([np.arange(n) * spacing, np.zeros(n)])

    def nearest(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pts = np.asarray(positions, float).reshape(-1, 2)
        d = np.linalg.norm(pts[:, None, :] - self.positions[None], axis=2)
        ids = d.argmin(axis=1)
        return ids.astype(np.int64), d[np.arange(len(pts)), ids]

    def nearest_per_layer(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ids, d = self.nearest(positions)
        return ids[:, None], d[:, None]
