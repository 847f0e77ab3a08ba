"""A loaded map's geometry structures are built in the background, the same as a frame would
build them, and the worker stops with the service (service/engine/geometry_warmer.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from service.engine.localization_service import LocalizationService
from service.maps.route_map import RouteMap, load_map
from service.settings import Settings
from service.vision.map_geometry import GeometryParams
from tests.pose_builds import count_pose_builds


def _service(tmp_path: Path, camera_map: RouteMap, warm: bool) -> LocalizationService:
    assert camera_map.path is not None
    shutil.copy(camera_map.path, tmp_path / "cam.swmap")
    return LocalizationService(Settings(maps_dir=tmp_path, session_store="memory",
                                        warm_geometry=warm))


def test_a_loaded_map_has_every_structure_built_ahead_of_the_robots(
        tmp_path: Path, camera_map: RouteMap) -> None:
    service = _service(tmp_path, camera_map, warm=True)
    try:
        assert service.warmer.wait(120)
        g = service.maps["cam"].geometry
        assert g is not None and g.cached() == list(range(camera_map.n_images))
        fresh = load_map(camera_map.path).geometry  # built here, on this thread, on demand
        assert fresh is not None
        p = GeometryParams()
        for i in range(0, camera_map.n_images, 9):
            a, b = g.structure(i, p), fresh.structure(i, p)
            assert (a is None) == (b is None)
            if a is not None and b is not None:
                assert np.array_equal(a.points, b.points)
                assert np.array_equal(a.feature_ids, b.feature_ids)
        assert not service.warmer.running  # done: the thread ended with the queue
    finally:
        service.close()


def test_without_warming_structures_wait_for_a_frame(tmp_path: Path,
                                                     camera_map: RouteMap) -> None:
    service = _service(tmp_path, camera_map, warm=False)
    try:
        assert service.warmer.wait(0.1) and not service.warmer.running  # nothing queued
        g = service.maps["cam"].geometry
        assert g is not None and g.cached() == []
    finally:
        service.close()


def test_closing_the_service_stops_the_warming(tmp_path: Path, camera_map: RouteMap) -> None:
    service = _service(tmp_path, camera_map, warm=True)
    assert service.warmer.running  # started by the map's load
    service.close()  # at the next image, well within the join's 5 s
    assert not service.warmer.running
    g = service.maps["cam"].geometry
    assert g is not None and len(g.cached()) < camera_map.n_images  # stopped part way


def test_a_map_no_longer_served_is_left_unwarmed(camera_map: RouteMap) -> None:
    """A version replaced before its turn (a learned experience, an upload) is skipped."""
    from service.engine.geometry_warmer import GeometryWarmer

    assert camera_map.path is not None
    served, replaced = load_map(camera_map.path), load_map(camera_map.path)
    warmer = GeometryWarmer(duty=1.0, current=lambda m: m is served)
    try:
        warmer.submit(replaced)
        warmer.submit(served)
        assert warmer.wait(120)
        assert replaced.geometry is not None and replaced.geometry.cached() == []
        assert served.geometry is not None
        assert served.geometry.cached() == list(range(served.n_images))
    finally:
        warmer.close()


def test_a_warmed_map_locates_without_building_a_pair_s_pose_again(
        camera_map: RouteMap, monkeypatch: pytest.MonkeyPatch) -> None:
    """Warming builds each image's camera heading with its structure: a map with more pairs
    than the poses kept (``POSES_KEPT``, made small here) needs no pair's pose built again
    when frames are located at its images (before, the heading was left for the first frame
    and rebuilt the evicted poses on the frame path: on a learned map of 622 images the
    step's p50 was 23.3 ms, 13.7 ms with the headings warmed)."""
    import service.vision.map_geometry as mg
    from service.engine.geometry_warmer import GeometryWarmer

    assert camera_map.path is not None
    monkeypatch.setattr(mg, "POSES_KEPT", 4)
    m = load_map(camera_map.path)
    warmer = GeometryWarmer(duty=1.0)
    try:
        warmer.submit(m)
        assert warmer.wait(120)
    finally:
        warmer.close()
    g = m.geometry
    assert g is not None
    p = GeometryParams()
    built = count_pose_builds(monkeypatch)
    located = [i for i in range(m.n_images) if g.structure(i, p) is not None]
    headings = [g.camera_heading(i, p) for i in located]
    assert len(located) > 0.8 * m.n_images and built == []
    fresh = load_map(camera_map.path).geometry  # the same headings, built on demand
    assert fresh is not None
    assert headings == [fresh.camera_heading(i, p) for i in located]
    assert built  # which does build poses: the counter counts
