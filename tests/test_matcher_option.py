"""The ``words`` matcher as the service's option (``SWARMLOC_MATCHER``): a map loaded with it
compares frames through its inverted file, for the similarity and the geometry's kept pairs;
with every word probed it is the exact matcher; bad values are refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydantic import ValidationError

from service.engine.localization_service import LocalizationService
from service.engine.localizer import Localizer
from service.maps.route_map import RICH_FEATURES, RouteMap, load_map, save_map
from service.settings import Settings
from service.vision.features import Features
from service.vision.map_geometry import FramePairs
from service.vision.matcher import compiled_signatures, warm_up
from service.vision.vocabulary import words_for


def _kept(m: RouteMap, codes: np.ndarray, ids: list[int], delta: float = 0.9
          ) -> tuple[np.ndarray, FramePairs]:
    kept = FramePairs(delta)
    return m.similarity(codes, ids, kept), kept


def test_bad_matcher_values_are_refused_with_the_choices(camera_map: RouteMap) -> None:
    with pytest.raises(ValidationError, match="'auto', 'exact' or 'words'"):
        Settings(matcher="fast")
    assert camera_map.path is not None
    with pytest.raises(ValueError, match="unknown matcher 'fast': use one of auto, exact, words"):
        load_map(camera_map.path, matcher="fast")


def test_every_word_probed_gives_the_exact_scores_and_kept_pairs(camera_map: RouteMap,
                                                                 sunny2_features) -> None:
    words = camera_map.with_words(k=16, probes=16)
    ids = list(range(0, camera_map.n_images, 3))
    for f in sunny2_features[:3]:
        s_exact, k_exact = _kept(camera_map, f.codes, ids)
        s_words, k_words = _kept(words, f.codes, ids)
        assert np.array_equal(s_exact, s_words) and s_exact.max() > 0.1
        for i in ids:
            (re, ce), (rw, cw) = k_exact.get(i), k_words.get(i)  # type: ignore[misc]
            assert np.array_equal(re, rw) and np.array_equal(ce, cw)


def test_an_existing_map_loads_with_words_and_the_step_uses_them(camera_map: RouteMap,
                                                                 sunny2_features) -> None:
    assert camera_map.path is not None
    m = load_map(camera_map.path, verify="lazy", matcher="words")
    assert m.uses_words and not camera_map.uses_words
    ivf = m.inverted_file  # trained at load, k from the map's features per image
    assert ivf.vocabulary.k == words_for(float(np.median(np.diff(m.offsets))))
    warm_up()
    compiled = compiled_signatures()
    loc = Localizer(m, "dpso", {}, seed=0)
    for i, f in enumerate(sunny2_features[:4]):
        loc.step(f, float(i))
    assert compiled_signatures() == compiled  # warm_up covers the words path too
    indexed = ivf.indexed()
    assert len(indexed) >= 10  # the step compared frames through the inverted file ...
    # ... and never through the exact GEMM (no image prepared for it)
    assert not any(k[0] == "prepared" for k in m.image_cache.keys())
    # the geometry's kept pairs are the inverted file's, from the same pass
    f = sunny2_features[5]
    ids = indexed[:6]
    scores, kept = _kept(m, f.codes, ids)
    r, pairs = ivf.match_pairs(f.codes, ids, m.delta, 0.9)
    assert pairs is not None and np.array_equal(scores, r.scores)
    for i, (rows, cols) in zip(ids, pairs, strict=True):
        got = kept.get(i)
        assert got is not None and np.array_equal(got[0], rows) and np.array_equal(got[1], cols)
    # fewer candidate pairs than the exact matcher's every pair
    fw = ivf.frame_words(f.codes)
    for i in ids:
        idx = ivf.index(i)
        sizes = np.diff(idx.starts)
        assert sizes[fw.words].sum() < 0.2 * len(f.codes) * len(idx)


def test_the_service_loads_its_maps_with_the_setting(tmp_path, small_map: RouteMap) -> None:
    save_map(small_map, tmp_path / "small")
    svc = LocalizationService(Settings(maps_dir=tmp_path, session_store="memory",
                                       zenoh_enabled=False, matcher="words"))
    try:
        assert svc.maps["small"].uses_words
    finally:
        svc.close()


def test_a_learned_version_keeps_the_matcher(tmp_path, small_map: RouteMap,
                                             sunny2_features) -> None:
    """A new map version written by learning (an experience) is loaded with the same matcher
    (the service serves it in place of the old one)."""
    from service.maps.experiences import NewImage, add_experience

    assert small_map.path is not None
    m = load_map(save_map(small_map, tmp_path / "small"), matcher="words")
    f = sunny2_features[10]
    new, _ = add_experience(m, tmp_path / "small.swmap", "e1",
                            [NewImage(f.codes, f.keypoints, m.positions[10] + 0.1, "e1/1")],
                            condition=None, robot=None, now=0.0, budget_bytes=10**9)
    assert new.n_images == m.n_images + 1 and new.uses_words


def test_the_lab_keeps_the_words_similarities_apart_from_the_exact_ones(
        tmp_path, camera_map: RouteMap, sunny2) -> None:
    """`swarmloc experiment --matcher words` caches its similarity table beside the exact
    one, never in it: the same map checksum must not hand the exact scores to the words
    runs (or the reverse)."""
    from client.lab.experiment_cli import cached_table, save_table

    (tmp_path / ".maps").mkdir()
    exact = cached_table(tmp_path, camera_map, sunny2)
    exact.table[:] = 0.5  # a filled exact table, as a finished run leaves it
    save_table(exact)
    words = cached_table(tmp_path, camera_map.with_words(k=16), sunny2)
    assert words.cache_path != exact.cache_path
    assert np.isnan(words.table).all()  # nothing of the exact run's scores
    again = cached_table(tmp_path, camera_map, sunny2)
    assert np.all(again.table == 0.5)


def test_the_words_matchers_best_images_are_matched_again_exactly(camera_map: RouteMap,
                                                                 sunny2_features) -> None:
    """``exact_top``: the best images of a comparison (by their words score) get the exact
    scores and kept pairs, the others keep the inverted file's."""
    ids = list(range(0, camera_map.n_images, 2))
    coarse = camera_map.with_words(k=16, probes=1)
    again = camera_map.with_words(k=16, probes=1, exact_top=3)
    differs = 0
    for f in sunny2_features[:4]:
        s_exact, k_exact = _kept(camera_map, f.codes, ids)
        s_words, _ = _kept(coarse, f.codes, ids)
        s_again, k_again = _kept(again, f.codes, ids)
        top = np.argsort(-s_words, kind="stable")[:3]
        rest = np.setdiff1d(np.arange(len(ids)), top)
        assert np.array_equal(s_again[top], s_exact[top])
        assert np.array_equal(s_again[rest], s_words[rest])
        for j in top:
            (re, ce), (ra, ca) = k_exact.get(ids[j]), k_again.get(ids[j])  # type: ignore[misc]
            assert np.array_equal(re, ra) and np.array_equal(ce, ca)
        differs += int(not np.array_equal(s_words[top], s_exact[top]))
    assert differs > 0  # one probe misses matches: the exact pass changed something


def _with_features(m: RouteMap, per_image: int, **meta: object) -> RouteMap:
    """``m`` with ``per_image`` features in every image: each image's codes repeated and
    jittered (distinct features that still match the image's own), its keypoints likewise."""
    rng = np.random.default_rng(0)
    codes, kps = [], []
    for i in range(m.n_images):
        rows = np.arange(m.offsets[i], m.offsets[i + 1])
        take = rows[np.arange(per_image) % len(rows)]
        c = m.codes[take].astype(np.int16) + rng.integers(-2, 3, (per_image, m.codes.shape[1]))
        codes.append(np.clip(c, 0, 255).astype(np.uint8))
        kps.append(np.asarray(m.keypoints[take], np.float32) + rng.uniform(0, 0.5, (per_image, 2)))
    offsets = np.arange(m.n_images + 1, dtype=np.int64) * per_image
    return dataclasses.replace(m, name=f"{m.name}{per_image}", meta={**m.meta, **meta},
                               codes=np.concatenate(codes), offsets=offsets,
                               keypoints=np.concatenate(kps),
                               place_index=None, lazy_digests=None, path=None)


def test_auto_compares_maps_of_rich_images_through_their_words(tmp_path,
                                                               small_map: RouteMap) -> None:
    """The default ``auto``: a map whose images hold more RootSIFT features than a frame's
    default cap is loaded with its inverted file (trained at load) and reported as such; a
    map at the cap, and the same rich map with ``exact``, compare every pair."""
    assert small_map.matcher == "auto" and not small_map.uses_words  # ~300 per image
    rich = load_map(save_map(_with_features(small_map, RICH_FEATURES + 64), tmp_path / "rich"))
    at_cap = load_map(save_map(_with_features(small_map, RICH_FEATURES), tmp_path / "cap"))
    assert rich.rich_images and rich.uses_words and rich._words is not None  # trained at load
    assert rich.summary()["matcher"] == "words"
    assert not at_cap.rich_images and not at_cap.uses_words
    assert at_cap.summary()["matcher"] == "exact"
    exact = load_map(tmp_path / "rich.swmap", matcher="exact")
    assert not exact.uses_words and exact._words is None
    # the step goes through the words: no map image prepared for the exact GEMM
    loc = Localizer(rich, "dpso", {}, seed=0)
    rows = slice(int(rich.offsets[5]), int(rich.offsets[6]))
    frame = Features(np.asarray(rich.keypoints[rows]), np.asarray(rich.codes[rows]))
    for t in range(3):
        loc.step(frame, float(t))
    assert rich.inverted_file.indexed()
    assert not any(k[0] == "prepared" for k in rich.image_cache.keys())
    svc = LocalizationService(Settings(maps_dir=tmp_path, session_store="memory",
                                       zenoh_enabled=False))
    try:
        assert svc.settings.matcher == "auto"
        assert svc.maps[rich.name].uses_words and not svc.maps[at_cap.name].uses_words
        assert svc.map_summary(rich.name).meta["matcher"] == "words"
    finally:
        svc.close()


def test_auto_leaves_the_papers_sift_on_the_papers_similarity(small_map: RouteMap) -> None:
    from service.vision.features import SiftParams

    papers = {"type": "sift", **dataclasses.asdict(SiftParams.papers(320, 240))}
    plain = _with_features(small_map, RICH_FEATURES + 64, feature=papers)
    assert plain.rich_images and not plain.first_params.root
    assert not plain.uses_words and plain.with_matcher("words").uses_words


def test_map_build_caps_sifts_features_per_image_and_frame(tmp_path, sunny1) -> None:
    """``swarmloc map build --max-features N``: the map's images hold at most N RootSIFT
    features, its metadata keeps the cap, so frames extracted for it are capped alike; XFeat
    keeps its own cap and says so."""
    from typer.testing import CliRunner

    from client.cli import app
    from service.vision.features import SiftParams, extract

    rnd = tmp_path / "part"
    rnd.mkdir()
    part = sunny1.subset(range(4))
    lines = ["image,x,y"] + [f"{n},{x:.3f},{y:.3f}" for n, (x, y) in zip(
        part.images, part.xy, strict=True)]
    (rnd / "poses.csv").write_text("\n".join(lines) + "\n")
    for n in part.images:
        (rnd / n).write_bytes((sunny1.path / n).read_bytes())
    assert len(extract(sunny1.load_image(0), SiftParams()).codes) > 100
    out = CliRunner().invoke(app, ["map", "build", str(rnd), "--out", str(tmp_path / "m"),
                                   "--features", "clahe-rootsift", "--max-features", "60"])
    assert out.exit_code == 0, out.output
    m = load_map(tmp_path / "m.swmap")
    p = m.feature_params
    assert isinstance(p, SiftParams) and p.n_features == 60 and p.root
    # OpenCV keeps the N strongest and their ties (a keypoint's second orientation)
    assert np.all((np.diff(m.offsets) >= 60) & (np.diff(m.offsets) <= 64)) and not m.uses_words
    assert 60 <= len(extract(sunny1.load_image(1), p).codes) <= 64
    out = CliRunner().invoke(app, ["map", "build", str(rnd), "--out", str(tmp_path / "x"),
                                   "--features", "xfeat", "--max-features", "60"])
    assert out.exit_code != 0 and "XFeat keeps its own 1024" in out.output
