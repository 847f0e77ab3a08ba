"""Counting the pair poses the two-view geometry builds (service/vision/map_geometry.py)."""

from __future__ import annotations

import pytest

import service.vision.map_geometry as mg


def count_pose_builds(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """From now on in the test, a 1 for every pair pose the geometry builds
    (``relative_pose``: its essential matrix): the list returned fills as they are built."""
    built: list[int] = []
    real = mg.relative_pose

    def counted(*args: object, **kwargs: object) -> object:
        built.append(1)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(mg, "relative_pose", counted)
    return built
