"""The performance benchmarks run and measure what they say (correctness only, never time):
``bench frame``'s stage breakdown, ``bench load --via local`` and the binary-descriptor
similarity of the feature-type study."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from client.dataset import Round
from client.lab.bench_frame import STAGES, bench_frame
from client.lab.bench_load import bench_load, fuzz_test_files
from client.lab.feature_study import (
    FeatureTable,
    HammingMatcher,
    extractor,
    hamming_reference,
)
from service.maps.route_map import RouteMap, save_map


@pytest.fixture(scope="module")
def maps_dir(tmp_path_factory: pytest.TempPathFactory, small_map: RouteMap) -> Path:
    d = tmp_path_factory.mktemp("perf_maps")
    save_map(small_map, d / "small")
    return d


def test_bench_frame_breakdown(maps_dir: Path, rounds_dir: Path) -> None:
    b = bench_frame(maps_dir, rounds_dir / "cloudy1", frames=4, warmup=2)
    assert set(b.paths) == {"in-process", "http", "zenoh"}
    assert b.identical  # same seed, same frames: the same estimates on every path
    assert b.frames == 4 and b.map_images > 0 and b.features > 0 and b.comparisons > 0
    assert b.matcher == "auto (exact on this map)"  # the setting, and what it chose here
    for name, p in b.paths.items():
        assert set(p.stages) == set(STAGES)
        assert all(len(v) == 4 for v in p.stages.values()) and len(p.total) == 4
        for stage in ("decode", "extract", "step"):
            assert min(p.stages[stage]) > 0, (name, stage)
        # the timed stages fit inside process_frame, whose rest (glue) is what is left
        assert min(p.stages["glue"]) >= 0
        assert all(pr <= st for pr, st in zip(p.stages["prepare"], p.stages["step"],
                                              strict=True))
        for k in range(4):  # the robot's round trip holds every stage, frame by frame
            parts = sum(p.stages[s][k] for s in ("decode", "extract", "step", "glue",
                                                  "serialise", "transport"))
            assert parts == pytest.approx(p.total[k], rel=1e-9, abs=1e-9)
            assert p.server[k] <= p.total[k]
        assert min(p.stages["request"]) >= 0 and min(p.stages["response"]) >= 0
        if name == "in-process":  # the LocalClient call around process_frame
            assert min(p.stages["transport"]) >= 0
            assert p.stages["serialise"] == [0.0] * 4  # no encoding: the Estimate itself
        else:
            assert min(p.stages["serialise"]) > 0
        for k in range(4):
            assert (p.stages["request"][k] + p.stages["response"][k]) == pytest.approx(
                p.stages["transport"][k] + p.stages["serialise"][k], rel=1e-9, abs=1e-9)
    assert b.beyond_extraction > 0
    assert b.ratio("http") > 0 and b.ratio("zenoh") > 0


def test_bench_frame_leaves_the_service_code_as_it_was(maps_dir: Path, rounds_dir: Path
                                                       ) -> None:
    import service.engine.localization_service
    import service.maps.route_map
    from service.engine.localizer import Localizer

    before = (service.engine.localization_service.decode_frame, service.maps.route_map.prepare,
              Localizer.extract, Localizer.step)
    bench_frame(maps_dir, rounds_dir / "sunny2", frames=1, warmup=0, transports=())
    assert (service.engine.localization_service.decode_frame, service.maps.route_map.prepare,
            Localizer.extract, Localizer.step) == before


def test_bench_load_local_and_http(maps_dir: Path, rounds_dir: Path) -> None:
    lines: list[str] = []
    res = bench_load(maps_dir, rounds_dir / "sunny2", [2], 3, ["local", "http"], lines.append)
    assert [r.name for r in res] == ["local", "http"]
    for r in res:
        assert r.robots == 2 and r.frames == 6 and r.errors == 0 and r.drops == 0
        assert r.frames_per_s > 0 and r.p99_ms >= r.p50_ms > 0
        assert r.cpu_pct >= 0 and r.rss_mib > 0
    ratio = [ln for ln in lines if ln.startswith("2 robots: http")]
    assert len(ratio) == 1 and "/ local" in ratio[0]


def test_hamming_similarity_equals_the_plain_reference(sunny1: Round, cloudy1: Round
                                                       ) -> None:
    orb = extractor("orb")
    frames = [orb(sunny1.load_image(i)) for i in (3, 4, 5, 20)]
    query = orb(cloudy1.load_image(4))
    m = HammingMatcher()
    counts = m.counts(query, [m.prepare(f) for f in frames])
    assert counts.tolist() == [hamming_reference(query, f) for f in frames]
    assert counts.max() > 0  # the frames do match
    tiny = np.zeros((1, 32), np.uint8)
    assert m.counts(tiny, [m.prepare(frames[0])]).tolist() == [0]
    assert hamming_reference(tiny, frames[0]) == 0


def test_hamming_ties_never_pass() -> None:
    a = np.array([[0b1111_0000] + [0] * 31, [0] * 32], np.uint8)
    b = np.array([[0b1111_0000] + [0] * 31, [0b1111_0000] + [0] * 31,
                  [255] * 32], np.uint8)  # two equal nearest neighbours for a[0]
    m = HammingMatcher()
    assert m.counts(a, [m.prepare(b)]).tolist() == [hamming_reference(a, b)] == [0]


def test_feature_table_rootsift_is_the_maps_similarity(small_map: RouteMap,
                                                       cloudy1: Round) -> None:
    rootsift = extractor("rootsift")
    ids = np.arange(small_map.n_images)
    sets = [np.asarray(small_map.codes[small_map.offsets[i]:small_map.offsets[i + 1]])
            for i in ids]
    query = rootsift(cloudy1.load_image(6))
    table = FeatureTable("rootsift", [query], sets, small_map)
    pick = ids[::5]
    assert table.scores(0, pick).tolist() == small_map.similarity(query, pick).tolist()
    assert table.computed == len(pick)
    table.scores(0, pick)  # kept: not computed again
    assert table.computed == len(pick)


def test_bench_fuzz_finds_the_suites_fuzz_tests() -> None:
    """`swarmloc bench fuzz` runs this checkout's fuzz tests (it looked in client/tests
    after the package moved, and refused to run)."""
    files = fuzz_test_files()
    assert [f.name for f in files] == ["test_fuzz_parsers.py", "test_schemathesis.py"]
    assert all(f.is_file() and f.parent == Path(__file__).resolve().parent for f in files)
