"""Maps of two feature types (``clahe-rootsift+xfeat``, format 5): both sets per image saved,
loaded and verified, the fused similarity, the refusals of a damaged or incomplete file, and
the name accepted by the CLI and the HTTP API."""

from __future__ import annotations

import json
import os
import re
import struct
from dataclasses import replace
from pathlib import Path

import httpx
import numpy as np
import pytest
from typer.testing import CliRunner

from client.cli import app
from client.dataset import Round
from client.lab.world import World
from service.api.models import SessionConfig
from service.api.params import DPSOParams
from service.api.round_format import camera_from_hfov
from service.engine.experience_writer import Batch
from service.engine.learning import Learner, LearnGates
from service.engine.localization_service import LocalizationService
from service.engine.localizer import Localizer
from service.estimators.lost_detection import DistinctnessMonitor
from service.maps.experiences import NewImage, add_experience, remove_experience
from service.maps.route_map import (
    MAGIC,
    MapError,
    RouteMap,
    build_map_from_rounds,
    load_map,
    save_map,
)
from service.settings import Settings
from service.vision.features import DualParams, SiftParams, extract, named_params
from service.vision.fusion import Fusion
from service.vision.map_geometry import GeometryParams
from service.vision.xfeat import XFeatParams
from tests.test_experiences import feed_a_wrong_place

DUAL = "clahe-rootsift+xfeat"


@pytest.fixture(scope="module")
def dual_map(tmp_path_factory: pytest.TempPathFactory, small_world: World, sunny1: Round
             ) -> RouteMap:
    """Every second image of the small world's sunny round as a map of both types with the
    camera, saved and reloaded (fully verified)."""
    cam = small_world.camera
    rnd = replace(sunny1.subset(range(0, len(sunny1), 2)),
                  camera=camera_from_hfov(cam.hfov_deg, cam.width, cam.height))
    m = build_map_from_rounds([rnd], name="dual", params=named_params(DUAL))
    return load_map(save_map(m, tmp_path_factory.mktemp("dmaps") / "dual"))


def _header(path: Path) -> tuple[dict, int, int]:
    """(header, its length, where the arrays start) of a map file."""
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[len(MAGIC): len(MAGIC) + 8])
    start = len(MAGIC) + 8 + n
    return json.loads(raw[len(MAGIC) + 8: start]), n, start + (-start) % 64


def _rewrite_header(path: Path, header: dict, length: int) -> None:
    """The same file with ``header`` (padded with spaces to the old length)."""
    raw = bytearray(path.read_bytes())
    head = json.dumps(header).encode()
    assert len(head) <= length
    raw[len(MAGIC) + 8: len(MAGIC) + 8 + length] = head + b" " * (length - len(head))
    path.write_bytes(bytes(raw))


def test_a_dual_map_round_trips_both_sets(dual_map: RouteMap,
                                                      small_map: RouteMap) -> None:
    p = dual_map.feature_params
    assert isinstance(p, DualParams) and p == named_params(DUAL)
    assert dual_map.meta["format_version"] == 6 and small_map.meta["format_version"] == 6
    assert dual_map.codes.dtype == np.uint8 and dual_map.codes.shape[1] == 128
    s = dual_map.second
    assert s is not None and s.codes.dtype == np.int8 and s.codes.shape[1] == 64
    assert len(s.offsets) == dual_map.n_images + 1 and s.offsets[-1] == len(s.codes)
    fusion = dual_map.fusion
    assert fusion is not None and fusion.as_dict() == dual_map.meta["fusion"]
    assert 0 <= fusion.first_chance < fusion.second_chance < 0.1  # XFeat shares more by chance
    assert 0.1 < fusion.first_typical < fusion.second_typical < 1  # ... and at one place
    assert dual_map.place_index is not None and dual_map.geometry is not None
    assert dual_map.path is not None
    header, _, _ = _header(dual_map.path)
    for key in ("codes2", "keypoints2", "offsets2", "image_digests2"):
        assert re.fullmatch(r"[0-9a-f]{64}", header["arrays"][key]["sha256"]), key
    lazy = load_map(dual_map.path, verify="lazy")
    assert lazy.second is not None and lazy.second.lazy_digests is not None
    img, again = dual_map.image_features(7), lazy.image_features(7)
    assert img.second is not None and again.second is not None
    assert np.array_equal(img.second.codes, again.second.codes)
    ids = range(dual_map.n_images)
    np.testing.assert_array_equal(dual_map.similarity(img, ids), lazy.similarity(img, ids))
    first, second = dual_map.type_similarities(img, ids)
    assert int(np.argmax(first)) == int(np.argmax(second)) == 7
    np.testing.assert_allclose(dual_map.similarity(img, ids), (
        first + second * fusion.first_typical / fusion.second_typical) / 2)
    with pytest.raises(ValueError, match=r"two feature types.*Features"):
        dual_map.similarity(img.codes, ids)  # codes alone cannot be fused


def test_a_dual_map_of_format_5_still_loads(dual_map: RouteMap, tmp_path: Path) -> None:
    """Maps written before format 6 (float32 keypoints and place index) load, fully or
    lazily verified, and give the same features, scores and located cameras."""
    from tests.legacy_maps import write_legacy

    old_path = write_legacy(dual_map, tmp_path / "old5.swmap", 5)
    img = dual_map.image_features(11)
    ids = range(dual_map.n_images)
    for verify in (True, "lazy"):
        old = load_map(old_path, verify=verify)
        assert old.meta["format_version"] == 5 and old.second is not None
        again = old.image_features(11)
        assert again.second is not None and img.second is not None
        assert np.array_equal(again.keypoints, img.keypoints)
        assert np.array_equal(again.second.keypoints, img.second.keypoints)
        np.testing.assert_array_equal(old.similarity(img, ids), dual_map.similarity(img, ids))
    assert load_map(save_map(old, tmp_path / "new")).meta["checksum"] == \
        dual_map.meta["checksum"]


def test_a_frame_is_extracted_once_with_both_types(sunny2: Round) -> None:
    img = sunny2.load_image(12)
    f = extract(img, named_params(DUAL))
    one, other = extract(img, SiftParams()), extract(img, XFeatParams())
    assert f.second is not None and other.second is None
    assert np.array_equal(f.codes, one.codes) and np.array_equal(f.keypoints, one.keypoints)
    assert np.array_equal(f.second.codes, other.codes)


def test_a_dark_frame_is_placed_by_xfeat_where_rootsift_finds_nothing(dual_map: RouteMap,
                                                                       sunny2: Round) -> None:
    rng = np.random.default_rng(0)
    placed = by_rootsift = 0
    frames = range(20, len(sunny2) - 20, 15)
    ids = range(dual_map.n_images)
    for i in frames:
        img = sunny2.load_image(i).astype(float) * 0.05 + rng.normal(0, 1.5, (240, 320))
        f = extract(np.clip(img, 0, 255).astype(np.uint8), dual_map.feature_params)
        truth = np.asarray(sunny2.xy[i])
        first, _ = dual_map.type_similarities(f, ids)
        by_rootsift += bool(first.max() > 0 and np.linalg.norm(
            dual_map.positions[int(np.argmax(first))] - truth) <= 3.0)
        best = dual_map.positions[int(np.argmax(dual_map.similarity(f, ids)))]
        placed += bool(np.linalg.norm(best - truth) <= 3.0)
    assert by_rootsift <= len(frames) // 2  # RootSIFT sees (almost) nothing in the dark
    assert placed >= len(frames) - 1


def test_dpso_localizes_on_a_dual_map_with_the_geometry(dual_map: RouteMap, sunny2: Round
                                                        ) -> None:
    loc = Localizer(dual_map, "dpso", {}, seed=1)
    errors, located = [], 0
    for k, i in enumerate(range(0, 60)):
        est = loc.localize(sunny2.load_image(i), t=float(k))
        if k >= 20:
            errors.append(np.hypot(est.x - sunny2.xy[i][0], est.y - sunny2.xy[i][1]))
            located += est.heading_source == "camera"
    assert np.median(errors) < 1.5
    assert located > 0  # the two-view geometry works on the RootSIFT matches


def test_a_dark_frame_is_located_by_xfeats_geometry_where_rootsifts_fails(
        dual_map: RouteMap, sunny2: Round) -> None:
    """Frames darkened to a tenth (dusk-like): RootSIFT's two-view geometry locates few of
    them against the map image nearest the truth; the localizer's, which tries XFeat's
    matches where RootSIFT's fail, locates them, each at the distance from that image the
    truth lies (within 1.5 m). With ``metric_second`` off it locates what RootSIFT's does."""
    geo, p = dual_map.geometry, GeometryParams()
    assert geo is not None
    loc = Localizer(dual_map, "dpso", {}, seed=0)
    off_loc = Localizer(dual_map, "dpso", {"metric_second": False}, seed=0)
    rng = np.random.default_rng(0)
    frames = range(20, len(sunny2) - 20, 5)
    by_rootsift = by_both = by_without = 0
    for i in frames:
        img = sunny2.load_image(i).astype(float) * 0.1 + rng.normal(0, 1.5, (240, 320))
        f = extract(np.clip(img, 0, 255).astype(np.uint8), dual_map.feature_params)
        truth = np.asarray(sunny2.xy[i])
        near = int(np.argmin(np.linalg.norm(dual_map.positions - truth, axis=1)))
        by_rootsift += geo.locate(f, near, p) is not None
        without = off_loc.locator(f)
        assert without is not None
        by_without += without(near) is not None
        locate = loc.locator(f)
        assert locate is not None
        off = locate(near)
        if off is not None:
            by_both += 1
            reach = float(np.hypot(off.right_m, off.ahead_m))
            assert abs(reach - np.linalg.norm(truth - dual_map.positions[near])) <= 1.5
    assert by_rootsift <= len(frames) // 3 and by_without == by_rootsift
    assert by_both >= len(frames) - 2


def _flip(path: Path, key: str, at: int = 0) -> None:
    header, _, data = _header(path)
    raw = bytearray(path.read_bytes())
    raw[data + int(header["arrays"][key]["offset"]) + at] ^= 0x01
    path.write_bytes(bytes(raw))


def test_a_damaged_xfeat_array_is_refused_naming_the_file_and_the_fix(
        dual_map: RouteMap, tmp_path: Path) -> None:
    assert dual_map.path is not None and dual_map.second is not None
    path = tmp_path / "broken.swmap"
    path.write_bytes(dual_map.path.read_bytes())
    image = 3
    _flip(path, "codes2", int(dual_map.second.offsets[image]) * 64 + 5)
    fix = re.escape("swarmloc map build --features clahe-rootsift+xfeat")
    with pytest.raises(MapError, match=rf"broken\.swmap: checksum mismatch \(array 'codes2'\)"
                                       rf".*{fix}"):
        load_map(path)
    lazy = load_map(path, verify="lazy")  # opens; the image is refused when first used
    frame = dual_map.image_features(image)
    lazy.similarity(frame, [image + 1])
    with pytest.raises(MapError, match=rf"broken\.swmap: image {image} .* XFeat features .*"
                                       rf"{fix}"):
        lazy.similarity(frame, [image])


@pytest.mark.parametrize("damage", ["missing", "short", "no fusion"])
def test_an_incomplete_dual_map_is_refused_naming_the_file_and_the_fix(
        dual_map: RouteMap, tmp_path: Path, damage: str) -> None:
    assert dual_map.path is not None
    path = tmp_path / "incomplete.swmap"
    path.write_bytes(dual_map.path.read_bytes())
    header, length, _ = _header(path)
    if damage == "missing":
        del header["arrays"]["codes2"]
        want = r"lacks its XFeat arrays \(codes2\)"
    elif damage == "short":  # offsets that promise more features than the codes hold
        header["arrays"]["offsets2"]["shape"] = [dual_map.n_images]
        header["arrays"]["offsets2"]["nbytes"] -= 8
        want = r"XFeat arrays do not fit together"
    else:
        del header["fusion"]
        want = r"lacks its fusion levels"
    _rewrite_header(path, header, length)
    with pytest.raises(MapError, match=rf"incomplete\.swmap: .*{want}.*"
                                       r"--features clahe-rootsift\+xfeat"):
        load_map(path, verify=False)


def test_an_older_service_is_told_to_rebuild(dual_map: RouteMap, tmp_path: Path) -> None:
    """A format this swarmloc does not read names the versions it reads and the fix."""
    assert dual_map.path is not None
    path = tmp_path / "future.swmap"
    path.write_bytes(dual_map.path.read_bytes())
    header, length, _ = _header(path)
    header["format_version"] = 7
    _rewrite_header(path, header, length)
    with pytest.raises(MapError, match=r"future\.swmap: map format version 7 is not supported "
                                       r"\(this swarmloc reads versions 2, 3, 4, 5, 6\); rebuild"):
        load_map(path)


def test_a_learning_session_on_a_dual_map_learns_both_sets(dual_map: RouteMap, cloudy1: Round,
                                                           tmp_path: Path) -> None:
    """A learning robot on a map of two feature types: each learned image keeps the frame's
    RootSIFT and XFeat features (the file verified on load), the batch handed over through
    Redis carries both, and removing the experience gives back the map's own images."""
    assert dual_map.path is not None
    (tmp_path / "dual.swmap").write_bytes(dual_map.path.read_bytes())
    svc = LocalizationService(Settings(maps_dir=tmp_path, zenoh_enabled=False,
                                       session_store="memory", learn_commit_images=5,
                                       learn_accuracy_m=2.0))
    try:
        svc.put_session("learner", SessionConfig(map="dual", learn=True, condition="cloudy"))
        for i in range(30):
            svc.process_frame("learner", cloudy1.image_path(i).read_bytes(), t=float(i))
        svc.delete_session("learner")
        assert svc.writer.wait(120)
        (e,) = svc.map_summary("dual").experiences
        path = svc.get_map("dual").path
    finally:
        svc.close()
    assert path is not None
    m = load_map(path, verify=True)
    assert m.second is not None and e.images > 0
    learned = np.flatnonzero(m.layers == e.layer)
    assert len(learned) == e.images and m.n_images == dual_map.n_images + e.images
    params = named_params(DUAL)
    for i in learned[:2]:  # the image is frame seq - 1's features, both sets
        frame = extract(cloudy1.load_image(int(m.image_names[i].rsplit("/", 1)[1]) - 1), params)
        got = m.image_features(int(i))
        assert got.second is not None and frame.second is not None
        assert np.array_equal(got.codes, frame.codes)
        assert np.array_equal(got.second.codes, frame.second.codes)
    own = m.image_features(0)  # the map's own images keep their sets
    assert own.second is not None and dual_map.second is not None
    assert np.array_equal(own.second.codes, dual_map.second.codes[dual_map.second.rows(0)])
    images = [NewImage(frame.codes, frame.keypoints, np.zeros(2), "n", frame.second.codes,
                       frame.second.keypoints)]
    (back,) = Batch.decode(Batch("dual", "e", images, None, "r").encode()).images
    assert back.codes2 is not None and np.array_equal(back.codes2, frame.second.codes)
    gone = remove_experience(m, path, e.id)
    assert gone.n_images == dual_map.n_images and gone.second is not None
    assert np.array_equal(gone.second.offsets, dual_map.second.offsets)
    with pytest.raises(MapError, match="lack the second set"):
        add_experience(gone, path, "x", [NewImage(frame.codes, frame.keypoints,
                                                  gone.positions[3], "y")],
                       condition=None, robot=None, now=0.0, budget_bytes=10**9)


def test_the_cli_builds_a_dual_map(tmp_path: Path, sunny1: Round) -> None:
    part = sunny1.subset(range(8))
    rnd = tmp_path / "part"
    rnd.mkdir()
    lines = ["image,x,y"] + [f"{n},{x:.3f},{y:.3f}" for n, (x, y) in zip(
        part.images, part.xy, strict=True)]
    (rnd / "poses.csv").write_text("\n".join(lines) + "\n")
    for n in part.images:
        (rnd / n).write_bytes((sunny1.path / n).read_bytes())
    out = CliRunner().invoke(app, ["map", "build", str(rnd), "--out", str(tmp_path / "m"),
                                   "--features", DUAL])
    assert out.exit_code == 0, out.output
    m = load_map(next(tmp_path.glob("m*.swmap")))
    assert isinstance(m.feature_params, DualParams) and m.second is not None


def test_the_http_api_accepts_the_name(server) -> None:
    """The build route's features parameter takes the new name (an empty body is refused for
    the archive, not for the name)."""
    r = httpx.post(f"{server['url']}/maps/dualbuilt/build", content=b"",
                   params={"features": DUAL}, headers={"content-type": "application/zip"})
    assert r.status_code == 400 and "features" not in r.text, r.text  # the archive's fault
    r = httpx.post(f"{server['url']}/maps/dualbuilt/build", content=b"",
                   params={"features": "surf"}, headers={"content-type": "application/zip"})
    assert r.status_code == 422 and DUAL in r.text


def test_a_wrong_place_does_not_stand_out_on_the_fused_scale(dual_map: RouteMap,
                                                             cloudy1: Round) -> None:
    """Lost detection on a dual map (issue 28, dusk): the fused m keeps XFeat's chance level
    (zero stays zero), so DPSO's ratio to the far images (``distinct_ratio``) means "times
    chance" as on a single-type map. Mapping XFeat's chance level onto RootSIFT's ~0 (the
    first rule) made the best-looking wrong place of every darkened frame stand out."""
    fusion = dual_map.fusion
    assert fusion is not None and fusion.rule == "mean-scaled"
    p = DPSOParams()
    rng = np.random.default_rng(0)
    pos = np.asarray(dual_map.positions)
    ids = np.arange(dual_map.n_images)
    frames = range(5, len(cloudy1) - 5, 7)
    true_good = wrong_good = 0
    for i in frames:  # cloudy frames darkened towards dusk
        img = cloudy1.load_image(i).astype(float) * 0.25 + rng.normal(0, 2.0, (240, 320))
        f = extract(np.clip(img, 0, 255).astype(np.uint8), dual_map.feature_params)
        m = dual_map.similarity(f, ids)
        truth = np.asarray(cloudy1.xy[i])
        far = np.linalg.norm(pos - truth, axis=1) > 15.0
        wrong = pos[far][int(np.argmax(m[far]))]  # the best-looking place elsewhere
        for where, good_at_truth in ((truth, True), (wrong, False)):
            monitor = DistinctnessMonitor(p.distinct_ratio, p.distinct_floor_m,
                                          p.distinct_far_m, p.ema_alpha)
            ev = monitor.judge(pos, m, where, p.species_radius_m)
            true_good += ev.good and good_at_truth
            wrong_good += ev.good and not good_at_truth
    assert true_good >= len(frames) - 2  # the right place still stands out
    assert wrong_good <= 0.7 * len(frames)  # mean-affine: every one of them (20 of 20)


def test_a_map_of_the_first_fusion_rule_fuses_as_it_did() -> None:
    """Maps built with ``mean-affine`` keep their similarities bit for bit; an unknown rule
    is refused."""
    old = Fusion(0.002, 0.3, 0.025, 0.5, "mean-affine")
    first, second = np.array([0.0, 0.1, 0.0]), np.array([0.01, 0.3, 0.05])
    mapped = 0.002 + (second - 0.025) * (0.3 - 0.002) / (0.5 - 0.025)
    np.testing.assert_array_equal(old.fuse(first, second),
                                  np.maximum((first + mapped) / 2.0, 0.0))
    new = Fusion.from_dict({**old.as_dict(), "rule": "mean-scaled"})
    np.testing.assert_allclose(new.fuse(first, second), (first + second * 0.6) / 2.0)
    with pytest.raises(ValueError, match=r"unknown fusion rule 'max'.*mean-scaled"):
        Fusion(0.002, 0.3, 0.025, 0.5, "max")


def test_the_learner_locates_a_dark_frame_with_the_second_set(dual_map: RouteMap,
                                                              sunny2: Round) -> None:
    """Gate 4 on a map of two types: where RootSIFT's geometry cannot locate a dark frame,
    XFeat's does, at its true place; the localizer keeps RootSIFT's (``geometry``)."""
    assert dual_map.second_geometry is not None
    learner = Learner(LearnGates(1.5, 0.4, 40), lambda *a: None)
    rng = np.random.default_rng(0)
    p = GeometryParams()
    by_first = by_learner = 0
    frames = range(20, len(sunny2) - 20, 15)
    for i in frames:
        img = sunny2.load_image(i).astype(float) * 0.05 + rng.normal(0, 1.5, (240, 320))
        f = extract(np.clip(img, 0, 255).astype(np.uint8), dual_map.feature_params)
        truth = np.asarray(sunny2.xy[i], float)
        near = int(dual_map.nearest(truth[None, :])[0][0])
        by_first += dual_map.geometry.locate(f, near, p) is not None  # type: ignore[union-attr]
        at, _ = learner._located(dual_map, f, truth)
        by_learner += bool(at is not None and np.linalg.norm(at - truth) <= 1.0)
    assert by_first <= len(frames) // 4  # RootSIFT's matches cannot locate the dark frames
    assert by_learner >= len(frames) // 2


def test_a_confidently_wrong_session_on_a_dual_map_learns_nothing(
        dual_map: RouteMap, sunny1: Round, cloudy1: Round, tmp_path: Path) -> None:
    """The poisoning case of tests/test_experiences.py on a map of two types (gate 4 tries
    XFeat's geometry too): frames with a forced prior half the route away teach nothing."""
    assert dual_map.path is not None
    (tmp_path / "dual.swmap").write_bytes(dual_map.path.read_bytes())
    svc = LocalizationService(Settings(maps_dir=tmp_path, zenoh_enabled=False,
                                       session_store="memory", learn_commit_images=5))
    try:
        stats = feed_a_wrong_place(svc, "dual", sunny1, cloudy1, 30)
        assert svc.writer.wait(120)
        assert stats["seen"] == 30 and stats.get("taught", 0) == 0, stats
        assert svc.map_summary("dual").experiences == []
    finally:
        svc.close()


def test_warm_up_covers_a_step_on_a_map_of_both_types(dual_map: RouteMap, cloudy1: Round,
                                                      tmp_path: Path) -> None:
    """In a fresh process, the service's warm-ups compile every kernel signature a frame on a
    map of both types meets (XFeat's int8 dots in the shared scan included): the first frame
    compiles nothing. Without the warm-ups the step compiles. Each process has an empty
    kernel cache of its own, as on a fresh machine (the shared one holds whatever the suite's
    other processes compiled: a count then depends on their order)."""
    import subprocess
    import sys

    path = save_map(dual_map, tmp_path / "dual")
    frame = tmp_path / "frame.npy"
    np.save(frame, cloudy1.load_image(0))
    script = (
        "import sys, numpy as np\n"
        "from service.maps.route_map import load_map\n"
        "from service.engine.localizer import Localizer\n"
        "from service.vision.matcher import compiled_signatures, warm_up\n"
        "from service.vision.mnn_matcher import warm_up as warm_up_mnn\n"
        "if sys.argv[3] == 'both':\n"
        "    warm_up()\n"
        "    warm_up_mnn()\n"
        "before = compiled_signatures()\n"
        "loc = Localizer(load_map(sys.argv[1]), 'dpso', {}, 0)\n"
        "loc.step(loc.extract(np.load(sys.argv[2])), 0.0)\n"
        "print(compiled_signatures() - before)\n")
    root = Path(__file__).resolve().parent.parent
    added = {}
    for which in ("both", "none"):
        env = {**os.environ, "PYTHONPATH": str(root), "XDG_CACHE_HOME": str(tmp_path / which)}
        out = subprocess.run([sys.executable, "-c", script, str(path), str(frame), which],
                             capture_output=True, text=True, cwd=root, check=True, env=env)
        added[which] = int(out.stdout.strip().splitlines()[-1])
    assert added["both"] == 0
    assert added["none"] > 0


def test_the_first_types_own_m_reaches_the_lost_detection(dual_map: RouteMap, small_map: RouteMap,
                                                          cloudy1: Round) -> None:
    """The similarity tells the first type's own m beside the fused one it returns, and the
    localizer hands it to DPSO's second monitor (its vouching); a map of one type has none."""
    f = extract(cloudy1.load_image(30), dual_map.feature_params)
    ids = np.arange(dual_map.n_images)
    told: dict[int, float] = {}

    def tell(i: np.ndarray, m: np.ndarray) -> None:
        told.update(zip(i.tolist(), m, strict=True))
    fused = dual_map.similarity(f, ids, first=tell)
    first, _ = dual_map.type_similarities(f, ids)
    assert np.array_equal(fused, dual_map.similarity(f, ids))
    assert np.array_equal([told[i] for i in ids.tolist()], first)
    assert not np.array_equal(first, fused)
    loc = Localizer(dual_map, "dpso", {}, seed=2)
    for k in range(4):
        loc.localize(cloudy1.load_image(k), t=float(k))
    assert loc.estimator.first_monitor.background is not None  # type: ignore[attr-defined]
    one = Localizer(small_map, "dpso", {}, seed=2)
    for k in range(4):
        one.localize(cloudy1.load_image(k), t=float(k))
    assert one.estimator.first_monitor.background is None  # type: ignore[attr-defined]


def test_the_labs_table_keeps_the_first_types_own_m(dual_map: RouteMap, cloudy1: Round) -> None:
    """``swarmloc experiment``'s replays vouch as the service does: the table keeps each
    frame's first-type m beside the fused one."""
    from client.lab.experiments import SimilarityTable

    feats = [extract(cloudy1.load_image(i), dual_map.feature_params) for i in (5, 6)]
    table = SimilarityTable(dual_map, feats)
    ids = np.array([3, 7, 11])
    fused = table.scores(1, ids)
    first_of = table.first_of(1)
    assert first_of is not None
    first, _ = dual_map.type_similarities(feats[1], ids)
    assert np.array_equal(fused, dual_map.similarity(feats[1], ids))
    assert np.array_equal(first_of(ids), first)
    assert np.isnan(table.first[0]).all()  # type: ignore[index]  # frame 0: nothing compared
