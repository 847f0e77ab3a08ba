"""The place-recognition index (service/vision/place_index.py), map format 3 (index stored,
per-image digests, lazy verification, version 2 still readable) and the long-route generator."""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from service.engine.localizer import Localizer
from service.maps.route_map import MAGIC, MapError, _canonical, _pad, load_map, save_map
from service.vision.features import extract


def _hit(m, ids: np.ndarray, xy: np.ndarray, radius: float = 5.0) -> bool:
    return bool((np.linalg.norm(m.positions[ids] - xy, axis=1) <= radius).any())


def test_index_recall_on_a_small_map(small_map, sunny2) -> None:
    idx = small_map.place_index
    assert idx is not None and idx.n_images == small_map.n_images
    assert small_map.meta["place_index"]["type"] == "vlad"
    frames = range(0, len(sunny2), 4)
    top1 = top10 = 0
    for i in frames:
        f = extract(sunny2.load_image(i), small_map.feature_params)
        ids, scores = idx.query(f.codes, 10)
        assert len(ids) == 10 and np.all(np.diff(scores) <= 1e-6)  # best first
        assert sunny2.truth_xy is not None
        top1 += _hit(small_map, ids[:1], sunny2.truth_xy[i])
        top10 += _hit(small_map, ids, sunny2.truth_xy[i])
    assert top10 / len(frames) >= 0.9
    assert top1 / len(frames) >= 0.6


def test_index_is_stored_and_reloaded_identically(small_map, tmp_path: Path) -> None:
    again = load_map(save_map(small_map, tmp_path / "again"))
    a, b = small_map.place_index, again.place_index
    assert a is not None and b is not None
    for k, arr in a.arrays().items():
        np.testing.assert_array_equal(np.asarray(arr), np.asarray(b.arrays()[k]), err_msg=k)
    codes = np.asarray(small_map.codes_of(7))
    assert a.query(codes, 5)[0].tolist() == b.query(codes, 5)[0].tolist()
    assert a.query(codes, 1)[0][0] == 7  # an image finds itself first


def test_seeded_global_start_places_particles_at_candidates(small_map, sunny2) -> None:
    f = extract(sunny2.load_image(40), small_map.feature_params)
    loc = Localizer(small_map, "dpso", {"place_candidates": 3}, seed=1)
    assert loc.seeder is not None and loc.estimator.wants_places()
    loc.step(f, 0.0)
    cand = small_map.positions[loc.seeder.last_ids]
    assert len(cand) == 3 and loc.seeder.queries == 1
    # every placement of the start was drawn around one of the three candidate places
    x = loc.estimator.particles()
    assert x is not None
    # (the step moved them once after placing: within a few metres plus one move)
    d = np.linalg.norm(x[:, None, :] - cand[None, :, :], axis=2).min(axis=1)
    assert np.median(d) < 15.0
    # without the index: placements around random map images spread over the whole loop
    rnd = Localizer(small_map, "dpso", {"place_candidates": 0}, seed=1)
    assert rnd.seeder is None
    rnd.step(f, 0.0)
    xr = rnd.estimator.particles()
    assert xr is not None
    dr = np.linalg.norm(xr[:, None, :] - cand[None, :, :], axis=2).min(axis=1)
    assert np.median(dr) > np.median(d)


def _error_after(loc: Localizer, feats: list, truth: np.ndarray, t0: int = 0) -> np.ndarray:
    out = []
    for k, f in enumerate(feats):
        e = loc.step(f, float(t0 + k))
        out.append(np.hypot(e.x - truth[k, 0], e.y - truth[k, 1]))
    return np.asarray(out)


def test_seeded_start_and_kidnap_recover(small_map, sunny2) -> None:
    assert sunny2.truth_xy is not None
    feats = [extract(sunny2.load_image(i), small_map.feature_params) for i in range(len(sunny2))]
    truth = sunny2.truth_xy
    for seed in (0, 1):
        # a fresh start in the middle of the round: back within 5 m in a few frames
        loc = Localizer(small_map, "dpso", None, seed)
        err = _error_after(loc, feats[60:90], truth[60:90])
        assert (err[8:] <= 5.0).all(), err
        # tracking, not searching: only the periodic checks ask the index, and they agree
        assert loc.seeder is not None
        before = loc.seeder.queries
        _error_after(loc, feats[90:96], truth[90:96], 30)
        assert loc.seeder.queries - before == 2  # every third frame
        assert loc.estimator.place_candidates is None and loc.estimator.place_disagree == 0
        # kidnapped to the other side of the loop: the index brings it back
        err = _error_after(loc, feats[5:45], truth[5:45], 35)
        assert (err[25:] <= 5.0).all(), err


def _write_v2(m, path: Path) -> Path:
    """A map file in format version 2 (one checksum over the header and every array)."""
    arrays = {"positions": np.ascontiguousarray(m.positions, "<f8"),
              "offsets": np.ascontiguousarray(m.offsets, "<i8"),
              "codes": np.ascontiguousarray(m.codes, np.uint8),
              "keypoints": np.ascontiguousarray(m.keypoints[0: len(m.codes)], "<f4"),
              "image_names": np.frombuffer(json.dumps(m.image_names).encode(), np.uint8),
              "layers": np.ascontiguousarray(m.layers, "<i8")}
    layout, off = {}, 0
    for k, a in arrays.items():
        layout[k] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": off,
                     "nbytes": a.nbytes}
        off += a.nbytes + _pad(a.nbytes)
    meta = {k: v for k, v in m.meta.items() if k not in ("arrays", "checksum", "place_index")}
    header = {**meta, "name": m.name, "format_version": 2, "arrays": layout}
    digest = hashlib.sha256(_canonical(header))
    for a in arrays.values():
        digest.update(a.tobytes())
    header["checksum"] = digest.hexdigest()
    head = json.dumps(header).encode()
    prefix = MAGIC + struct.pack("<Q", len(head)) + head
    blob = b"".join(a.tobytes() + b"\x00" * _pad(a.nbytes) for a in arrays.values())
    path.write_bytes(prefix + b"\x00" * _pad(len(prefix)) + blob)
    return path


def test_version_2_map_loads_without_index(small_map, sunny2, tmp_path: Path) -> None:
    old = load_map(_write_v2(small_map, tmp_path / "old.swmap"))
    assert old.meta["format_version"] == 2 and old.place_index is None
    loc = Localizer(old, "dpso", None, 0)
    assert loc.seeder is None  # random map images, as before the index
    e = loc.step(extract(sunny2.load_image(3), old.feature_params), 0.0)
    assert e.comparisons > 0
    # saving it again writes the current version (index absent until the map is rebuilt)
    again = load_map(save_map(old, tmp_path / "new"))
    assert again.meta["format_version"] == 6 and again.place_index is None
    assert again.meta["checksum"] != old.meta["checksum"]


def test_lazy_verification_catches_a_corrupted_image_on_use(small_map, tmp_path: Path) -> None:
    path = save_map(small_map, tmp_path / "m")
    raw = bytearray(path.read_bytes())
    header = json.loads(raw[16: 16 + struct.unpack("<Q", raw[8:16])[0]])
    start = 16 + struct.unpack("<Q", raw[8:16])[0]
    data = start + _pad(start)
    image = 20
    at = data + header["arrays"]["codes"]["offset"] + int(small_map.offsets[image]) * 128 + 5
    raw[at] ^= 0xFF
    bad = tmp_path / "bad.swmap"
    bad.write_bytes(bytes(raw))
    with pytest.raises(MapError, match="checksum mismatch \\(array 'codes'\\)"):
        load_map(bad)
    lazy = load_map(bad, verify="lazy")  # opens: only the header and small arrays checked
    codes = np.asarray(small_map.codes_of(3))
    assert lazy.similarity(codes, [3, 19, 21]).shape == (3,)  # intact images match
    with pytest.raises(MapError, match=f"image {image} .* does not match its digest"):
        lazy.similarity(codes, [image])
    # the geometry reads keypoints through the same check
    assert lazy.keypoints_of(3).shape == (int(np.diff(small_map.offsets)[3]), 2)
    with pytest.raises(MapError, match=f"image {image} .* does not match its digest"):
        lazy.keypoints_of(image)


def test_long_route_shape() -> None:
    from client.lab.world.long_route import LongRoute

    r = LongRoute(40_000)
    assert r.per_loop * r.n_loops >= 40_000 > r.per_loop * (r.n_loops - 1)
    assert sum(r.loop_images(k) for k in range(r.n_loops)) == 40_000
    origins = np.array([r.loop_origin(k) for k in range(r.n_loops)])
    x0, y0, x1, y1 = r.route.bounds
    # blocks on a grid: neighbours are a loop plus a gap apart, none overlaps another
    d = np.abs(origins[:, None, :] - origins[None, :, :])
    apart = (d[..., 0] >= x1 - x0 + r.gap_m - 1e-6) | (d[..., 1] >= y1 - y0 + r.gap_m - 1e-6)
    assert apart[~np.eye(len(origins), dtype=bool)].all()
    legs = r.plan_legs(12, 50, np.random.default_rng(0))
    assert len({leg.name for leg in legs}) == 12
    assert all(0 <= leg.start and leg.start + leg.frames <= r.loop_images(leg.loop)
               for leg in legs)
    assert len({r.loop_seed(k) for k in range(r.n_loops)}) == r.n_loops


def test_tiny_long_route_renders_into_maps(tmp_path: Path) -> None:
    from client.dataset import read_round
    from client.lab.world.long_route import Leg, LongRoute, assemble_maps, render_long_route
    from service.vision.features import SiftParams

    route = LongRoute(60, loop_length_m=24.0)
    assert route.n_loops == 2 and route.per_loop < 60
    legs = [Leg("leg000", 1, 2, 6)]
    params = SiftParams(width=route.camera.width, height=route.camera.height)
    render_long_route(route, tmp_path, legs, params)
    small, full = assemble_maps(tmp_path, [route.per_loop, 60])
    a, b = load_map(small), load_map(full)
    assert (a.n_images, b.n_images) == (route.per_loop, 60)
    np.testing.assert_array_equal(a.positions, b.positions[: a.n_images])  # a prefix
    assert np.array_equal(np.asarray(a.codes), np.asarray(b.codes[: len(a.codes)]))
    # the second loop lies in its own block
    assert b.positions[route.per_loop:, 0].min() > a.positions[:, 0].max()
    assert b.place_index is not None and b.image_names[route.per_loop] == "loop00001/00000"
    q = read_round(tmp_path / "queries" / "leg000")
    assert len(q) == 6 and q.truth_xy is not None
    d = np.linalg.norm(b.positions[:, None] - q.truth_xy[None], axis=2).min(axis=0)
    assert (d < 3.0).all()  # the leg runs along the map's second loop
