from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pytest

from service.maps import route_map
from service.maps.route_map import MapError, list_maps, load_map, prune, save_map
from service.vision.features import Features, extract, match_batch, unit_descriptors


def test_pruning_keeps_features_seen_in_a_neighbour(sunny1) -> None:
    feats = [extract(sunny1.load_image(i)) for i in range(6)]
    pruned, stats = prune(feats)
    assert 0.2 < stats.removed_fraction < 0.9
    for i in range(1, 5):
        kept = pruned[i].descriptors
        nb = [feats[i - 1].descriptors, feats[i + 1].descriptors]
        # every kept feature has a symmetric match in a neighbour
        assert match_batch(kept, nb).matched.any(axis=0).all()
        assert 0 < len(kept) < len(feats[i])


def test_pruning_edge_images_use_one_neighbour() -> None:
    rng = np.random.default_rng(0)
    a = np.rint(255 * rng.random((20, 128)) ** 3).astype(np.uint8)
    kp = np.zeros((20, 2), np.float32)
    f = [Features(kp, a), Features(kp[:10], a[:10])]
    pruned, _ = prune(f)
    assert len(pruned[0]) == 10 and len(pruned[1]) == 10


def test_map_roundtrip_is_memory_mapped(small_map, sunny1) -> None:
    assert isinstance(small_map.codes, np.memmap) and small_map.codes.dtype == np.uint8
    assert small_map.n_images == len(sunny1) and small_map.n_layers == 1
    np.testing.assert_allclose(small_map.positions, sunny1.xy)
    assert small_map.image_names == list(sunny1.images)
    meta = small_map.meta
    assert meta["format_version"] == 6 and meta["delta"] == 0.6
    assert meta["keypoint_scale"] == 32  # 1/32 px: the finest fixed point up to 1/32 px
    assert meta["image_size"] == [320, 240] and meta["feature"]["type"] == "sift"
    assert meta["feature"]["clahe"] and meta["feature"]["root"]  # the default features
    assert not meta["pruning"]["enabled"]
    assert len(meta["checksum"]) == 64 and meta["pruning"]["features_after"] > 0


def test_loaded_map_matches_like_the_map_in_memory(small_map, sunny1, sunny2) -> None:
    from service.maps.route_map import build_map

    idx = list(range(0, 12))
    mem = build_map("m", [sunny1.load_image(i) for i in idx], sunny1.xy[idx],
                    [sunny1.images[i] for i in idx])
    f = extract(sunny2.load_image(5))
    ids = np.arange(12)
    np.testing.assert_array_equal(mem.similarity(f.codes, ids), small_map.similarity(f.codes, ids))
    # the exact uint8 matcher equals the float path on the same descriptors
    sets = [unit_descriptors(small_map.codes_of(int(i))) for i in ids]
    np.testing.assert_array_equal(small_map.similarity(f.codes, ids),
                                  match_batch(f.descriptors, sets).scores)


def test_multi_condition_map_compares_each_layer(tmp_path: Path, sunny1, cloudy1) -> None:
    from service.estimators.fitness import FrameFitness
    from service.maps.route_map import build_map

    idx = list(range(20, 30))
    imgs = [sunny1.load_image(i) for i in idx] + [cloudy1.load_image(i) for i in idx]
    xy = np.concatenate([sunny1.xy[idx], cloudy1.xy[idx]])
    m = build_map("two", imgs, xy, [f"s{i}" for i in idx] + [f"c{i}" for i in idx],
                  layers=np.repeat([0, 1], len(idx)))
    loaded = load_map(save_map(m, tmp_path / "two"))
    assert loaded.n_layers == 2 and loaded.layers.tolist() == [0] * 10 + [1] * 10
    ids, dist = loaded.nearest_per_layer(sunny1.xy[idx[:3]])
    assert dist.shape == (3, 2) and (dist[:, 0] < 1.0).all()
    assert ids.shape == (3, 2) and (ids[:, 0] < 10).all() and (ids[:, 1] >= 10).all()
    # a cloudy frame: both layers are compared, the cloudy image of its place wins
    f = extract(cloudy1.load_image(25))
    fit = FrameFitness(loaded, lambda i: loaded.similarity(f.codes, i), 2.0)
    _, m_best, best = fit(cloudy1.xy[[25]])
    assert fit.comparisons == 2 and best[0] >= 10
    assert m_best[0] == loaded.similarity(f.codes, [best[0]])[0]


def test_nearest_many_positions(small_map) -> None:
    q = small_map.positions[[0, 10, 20]] + 0.01
    ids, dist = small_map.nearest(q)
    assert ids.tolist() == [0, 10, 20]
    assert np.all(dist < 0.05)


def test_true_image_outscores_far_ones(small_map, sunny2, cloudy1) -> None:
    for rnd, min_frac in ((sunny2, 0.85), (cloudy1, 0.5)):
        wins = 0
        idx = range(0, len(rnd), 5)
        for i in idx:
            f = extract(rnd.load_image(i))
            ids, _ = small_map.nearest(rnd.truth_xy[i][None])
            d = np.linalg.norm(small_map.positions - rnd.truth_xy[i], axis=1)
            far = np.flatnonzero(d > 15)[::7]
            sc = small_map.similarity(f.codes, np.concatenate([ids, far]))
            wins += sc[0] > sc[1:].max()
        assert wins / len(idx) >= min_frac


def _copy(small_map, tmp_path: Path) -> Path:
    return save_map(small_map, tmp_path / "m")


def test_corrupted_maps_are_refused(small_map, tmp_path: Path) -> None:
    path = _copy(small_map, tmp_path)
    raw = bytearray(path.read_bytes())
    # a flipped byte deep in the descriptor codes
    flipped = tmp_path / "flipped.swmap"
    b = bytearray(raw)
    b[len(b) - 5000] ^= 0xFF
    flipped.write_bytes(bytes(b))
    with pytest.raises(MapError, match="checksum mismatch"):
        load_map(flipped)
    # truncated
    trunc = tmp_path / "trunc.swmap"
    trunc.write_bytes(bytes(raw[: len(raw) // 2]))
    with pytest.raises(MapError, match="truncated"):
        load_map(trunc)
    # wrong version, with a consistent header otherwise (same length: only the digit changes)
    needle = b'"format_version": 6'
    assert raw.count(needle) == 1
    wrong = tmp_path / "wrong.swmap"
    wrong.write_bytes(bytes(raw).replace(needle, b'"format_version": 9'))
    with pytest.raises(MapError, match="format version 9 is not supported"):
        load_map(wrong)
    # a keypoint scale that is no power of two (the keypoints would decode wrongly)
    needle = b'"keypoint_scale": 32'
    assert raw.count(needle) == 1
    odd = tmp_path / "odd.swmap"
    odd.write_bytes(bytes(raw).replace(needle, b'"keypoint_scale": 31'))
    with pytest.raises(MapError, match="fixed-point scale 31 is not a power of two"):
        load_map(odd)
    # not a map at all
    junk = tmp_path / "junk.swmap"
    junk.write_bytes(b"hello world")
    with pytest.raises(MapError, match="not a swarmloc map"):
        load_map(junk)


def test_atomic_write_replaces_whole_file(small_map, tmp_path: Path) -> None:
    path = _copy(small_map, tmp_path)
    save_map(small_map, path)  # overwrite in place
    assert [p.name for p in tmp_path.iterdir()] == ["m.swmap"]  # no temp files left
    assert load_map(path).n_images == small_map.n_images
    assert list_maps(tmp_path) == [path]


@pytest.mark.parametrize("verify", [True, "lazy"])
@pytest.mark.parametrize("change", ["moved", "grown"])
def test_a_new_version_renamed_in_while_loading_is_not_mixed_in(
        small_map, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, verify, change) -> None:
    """Another writer (a replica, the experience writer) renames its new version onto the
    path between the loader's header read and its arrays: the loader reads the file it
    opened, whole, and never the old header over the new arrays (a replica under load once
    refused its map's new version for 'bytes following the last array')."""
    path = _copy(small_map, tmp_path)
    old = load_map(path)
    if change == "moved":  # the same sizes, other positions
        new = dataclasses.replace(old, positions=np.asarray(old.positions) + 1.0)
    else:  # a larger file: longer image names
        new = dataclasses.replace(old, image_names=[f"{n}-renamed-{'x' * 40}"
                                                    for n in old.image_names])
    staged = save_map(new, tmp_path / "staged" / "m")
    assert staged.stat().st_size != path.stat().st_size or change == "moved"
    read_header = route_map._read_header

    def header_then_rename(p: Path, fh: BinaryIO | None = None) -> tuple[dict, int]:
        got = read_header(p, fh)
        if staged.exists():
            os.replace(staged, path)  # the writer's atomic rename, mid-load
        return got

    monkeypatch.setattr(route_map, "_read_header", header_then_rename)
    loaded = load_map(path, verify=verify)
    assert loaded.meta["checksum"] == old.meta["checksum"]  # the version it opened, whole
    assert np.array_equal(loaded.positions, old.positions)
    assert loaded.image_names == old.image_names
    assert not staged.exists()  # the rename did happen mid-load
    monkeypatch.setattr(route_map, "_read_header", read_header)
    again = load_map(path, verify=True)  # and the next load reads the new version
    assert again.image_names == new.image_names
    assert np.array_equal(again.positions, np.asarray(new.positions))


def test_saving_a_map_elsewhere_leaves_its_path_alone(small_map, tmp_path: Path) -> None:
    """``save_map`` writes a copy: the map still names the file it was loaded from, so
    changing the copy (here: junk appended) never reaches those who read ``map.path``."""
    before = small_map.path
    copy = save_map(small_map, tmp_path / "copy")
    copy.write_bytes(copy.read_bytes() + b"junk")
    assert small_map.path == before and before is not None and before != copy
    assert load_map(before).n_images == small_map.n_images


def test_map_from_geographic_round(tmp_path: Path, sunny1) -> None:
    from client.dataset import read_round
    from service.api.geo import LocalFrame
    from service.maps.route_map import build_map

    d = tmp_path / "geo"
    d.mkdir()
    frame = LocalFrame(48.52, 9.06)
    latlon = frame.to_geo(sunny1.xy[:8])
    rows = ["image,lat,lon"]
    for i in range(8):
        (d / sunny1.images[i]).write_bytes(sunny1.image_path(i).read_bytes())
        rows.append(f"{sunny1.images[i]},{latlon[i, 0]:.9f},{latlon[i, 1]:.9f}")
    (d / "poses.csv").write_text("\n".join(rows) + "\n")
    rnd = read_round(d)
    m = build_map("geo", [rnd.load_image(i) for i in range(len(rnd))], rnd.xy, list(rnd.images),
                  origin=rnd.origin)
    path = save_map(m, tmp_path / "geo")
    loaded = load_map(path)
    assert loaded.frame is not None
    back = loaded.frame.to_geo(loaded.positions)
    np.testing.assert_allclose(back, latlon, atol=1e-7)


def test_map_of_featureless_images_roundtrips(tmp_path: Path) -> None:
    from service.maps.route_map import build_map

    blank = [np.full((240, 320), 128, np.uint8)] * 3
    m = build_map("blank", blank, np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]),
                  ["a.png", "b.png", "c.png"])
    loaded = load_map(save_map(m, tmp_path / "blank"))
    assert loaded.n_images == 3 and loaded.offsets[-1] == 0
    assert loaded.similarity(np.ones((5, 128), np.uint8), [0, 1]).tolist() \
        == [0.0, 0.0]


def test_the_file_stores_keypoints_in_fixed_point_and_the_place_index_compactly(
        small_map, sunny1, sunny2, tmp_path: Path) -> None:
    """Format 6: uint16 keypoints at 1/32 px, an int8 place projection with a scale per column,
    float16 place descriptors. A built map holds the stored values already, so it matches,
    locates and recognises places exactly as its saved copy, and saving again is lossless."""
    from service.maps.route_map import _read_header, build_map

    assert small_map.path is not None
    layout = _read_header(small_map.path)[0]["arrays"]
    assert layout["keypoints"]["dtype"] == "<u2" and layout["place_projection"]["dtype"] == "|i1"
    assert layout["place_descriptors"]["dtype"] == "<f2"
    assert layout["place_projection_scale"]["shape"] == layout["place_projection"]["shape"][1:]
    per_feature = sum(layout[k]["nbytes"] for k in ("codes", "keypoints")) / len(small_map.codes)
    assert per_feature == 132  # 128-byte RootSIFT code + 2 x uint16
    info = small_map.summary()
    assert info["file_bytes"] == small_map.path.stat().st_size
    assert info["bytes_per_feature"] == round(info["file_bytes"] / len(small_map.codes), 1)

    idx = list(range(0, 30))
    mem = build_map("m", [sunny1.load_image(i) for i in idx], sunny1.xy[idx],
                    [sunny1.images[i] for i in idx])
    kps = mem.keypoints[0: len(mem.codes)]
    assert np.array_equal(kps * 32, np.rint(kps * 32))  # on the 1/32 px grid
    raw = extract(sunny1.load_image(3))  # the extractor's own keypoints, off the grid
    assert np.abs(mem.keypoints_of(3) - raw.keypoints).max() <= 1 / 64 + 1e-6
    assert not np.array_equal(mem.keypoints_of(3), raw.keypoints)
    saved = load_map(save_map(mem, tmp_path / "m"))
    assert np.array_equal(saved.keypoints[0: len(saved.codes)], kps)
    assert mem.place_index is not None and saved.place_index is not None
    np.testing.assert_array_equal(saved.place_index.projection, mem.place_index.projection)
    np.testing.assert_array_equal(saved.place_index.descriptors, mem.place_index.descriptors)
    f = extract(sunny2.load_image(7))
    assert [a.tolist() for a in saved.place_index.query(f.codes, 5)] == \
        [a.tolist() for a in mem.place_index.query(f.codes, 5)]
    ids = np.arange(30)
    np.testing.assert_array_equal(saved.similarity(f.codes, ids), mem.similarity(f.codes, ids))
    again = load_map(save_map(saved, tmp_path / "again"), verify="lazy")
    assert again.meta["checksum"] == saved.meta["checksum"]  # byte for byte the same arrays
    assert np.array_equal(again.keypoints_of(29), saved.keypoints_of(29))


def test_a_map_of_format_3_still_loads_and_is_written_again_as_6(small_map, sunny2,
                                                                  tmp_path: Path) -> None:
    from tests.legacy_maps import write_legacy

    old_path = write_legacy(small_map, tmp_path / "old.swmap", 3)
    assert old_path.stat().st_size > small_map.path.stat().st_size  # type: ignore[union-attr]
    for verify in (True, "lazy"):
        old = load_map(old_path, verify=verify)
        assert old.meta["format_version"] == 3 and old.keypoints.dtype == np.float32
        assert np.array_equal(old.keypoints_of(4), small_map.keypoints_of(4))
        f = extract(sunny2.load_image(9))
        ids = np.arange(small_map.n_images)
        np.testing.assert_array_equal(old.similarity(f.codes, ids),
                                      small_map.similarity(f.codes, ids))
        assert old.place_index is not None and small_map.place_index is not None
        assert [a.tolist() for a in old.place_index.query(f.codes, 5)] == \
            [a.tolist() for a in small_map.place_index.query(f.codes, 5)]
    new = load_map(save_map(old, tmp_path / "new"))
    assert new.meta["format_version"] == 6
    assert new.meta["checksum"] == small_map.meta["checksum"]  # the same file as the original
    # a damaged keypoint of the old format is still caught (its per-image digest)
    raw = bytearray(old_path.read_bytes())
    from service.maps.route_map import _read_header

    header, start = _read_header(old_path)
    raw[start + header["arrays"]["keypoints"]["offset"] + 8 * 40 + 1] ^= 0x10
    bad = tmp_path / "bad.swmap"
    bad.write_bytes(bytes(raw))
    with pytest.raises(MapError, match=r"checksum mismatch \(array 'keypoints'\)"):
        load_map(bad)
    lazy = load_map(bad, verify="lazy")
    with pytest.raises(MapError, match="does not match its digest"):
        for i in range(lazy.n_images):
            lazy.features_of(i)


def test_keypoints_the_fixed_point_cannot_hold_are_refused() -> None:
    from service.maps.compact import KeypointRangeError, encode_keypoints, keypoint_scale

    assert [keypoint_scale(w, h) for w, h in ((320, 240), (1226, 370), (2048, 64),
                                               (8191, 8191))] == [32, 32, 16, 8]
    assert encode_keypoints(np.array([[-0.4, 2047.9]]), 32).tolist() == [[0, 65533]]
    for bad, why in (([[np.nan, 1.0]], "not finite"), ([[-1.0, 1.0]], "outside"),
                     ([[1.0, 2048.5]], "outside")):
        with pytest.raises(KeypointRangeError, match=why):
            encode_keypoints(np.array(bad), 32)
