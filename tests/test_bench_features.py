"""``swarmloc bench webcam-night`` and ``swarmloc bench extract`` on data the suite renders
(fixed-camera scenes made of one rendered frame; no photo from ../shared)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from client.cli import app
from client.dataset import Round
from client.lab.bench_webcam import bench_webcam, classify


def _rows(output: str, first: str) -> list[list[str]]:
    """Cells of the table lines whose first cell is ``first``."""
    out = []
    for line in output.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0] == first:
            out.append(cells)
    return out


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory, sunny1: Round) -> Path:
    """``fixed``: one camera, 3 day photos (brightness +0, +10, +20) and 2 night photos (the
    same view darkened), so the identity holds; ``moved``: the night photo shows the view
    shifted by 30 px (no match is correct under the identity); ``daylight``: no night."""
    root = tmp_path_factory.mktemp("webcams")
    img = sunny1.load_image(len(sunny1) // 2).astype(np.float32)
    day = [np.clip(img + k, 0, 255) for k in (0, 10, 20)]
    night = [img * 0.3, img * 0.3 + 8]
    views = {"fixed": day + night, "moved": [*day, np.roll(img * 0.3, 30, axis=1)],
             "daylight": day}
    for name, photos in views.items():
        (root / name).mkdir()
        for k, photo in enumerate(photos):
            cv2.imwrite(str(root / name / f"{k}.png"), photo.astype(np.uint8))
    (root / "notes").mkdir()  # no photos: not a scene
    return root


def test_day_and_night_by_mean_grey() -> None:
    night, day = classify([30.0, 79.9, 80.0, 120.0, 150.0, 160.0])
    assert night == [0, 1] and day == [3, 4, 5]  # the median is 100
    # a dark scene's median is no day
    assert classify([10.0, 20.0, 30.0])[1] == []


def test_webcam_bench_counts_correct_matches_under_the_identity(scenes: Path) -> None:
    b = bench_webcam(scenes)
    by = {s.name: s for s in b.scenes}
    assert set(by) == {"fixed", "moved", "daylight"}
    assert (len(by["fixed"].night), len(by["fixed"].day)) == (2, 3)
    assert by["daylight"].pairs == 0
    assert by["moved"].day == ("1.png", "2.png")  # the median lies between +0 and +10
    for kind in ("clahe-rootsift", "xfeat"):
        fixed = np.array(b.per_scene[("fixed", kind)])
        moved = np.array(b.per_scene[("moved", kind)])
        assert len(fixed) == 6 and fixed.min() >= 50, (kind, fixed)
        assert len(moved) == 2
        assert moved.max() < 10, (kind, moved)  # matched, but not at the same pixel
        assert b.share(kind, 20) == pytest.approx(6 / 8)


def test_cli_prints_the_scenes_the_shares_and_the_ratio(scenes: Path) -> None:
    out = CliRunner().invoke(app, ["bench", "webcam-night", str(scenes), "--area", "40000"])
    assert out.exit_code == 0, out.output
    assert _rows(out.output, "fixed")[0][1:] == ["5", "231x173", "2", "3", "6"]
    assert _rows(out.output, "daylight")[0][3:] == ["0", "2", "0"]
    for kind in ("clahe-rootsift", "xfeat"):
        rows = {r[1]: r for r in _rows(out.output, kind)}
        assert set(rows) == {"all", "fixed", "moved"}  # no row for a scene without pairs
        assert rows["all"][2] == "8" and rows["fixed"][2:6] == ["6", "1.000", "1.000", "1.000"]
        assert rows["moved"][3:6] == ["0.000", "0.000", "0.000"]
    assert "ratio xfeat / clahe-rootsift of the shares: >= 10: 1.00, >= 20: 1.00, >= 50: " \
        "1.00" in out.output
    bad = CliRunner().invoke(app, ["bench", "webcam-night", str(scenes / "notes")])
    assert bad.exit_code != 0 and "no scene folder" in bad.output


def test_cli_extract_bench_prints_both_types_and_their_ratio(rounds_dir: Path) -> None:
    out = CliRunner().invoke(app, ["bench", "extract", str(rounds_dir), "--map", "sunny1",
                                   "--query", "sunny1", "--sizes", "320x240,256x192",
                                   "--features", "clahe-rootsift,xfeat",
                                   "--repeats", "2", "--frames", "8", "--warmup", "12"])
    assert out.exit_code == 0, out.output
    for kind in ("clahe-rootsift", "xfeat"):
        rows = {r[1]: r for r in _rows(out.output, kind)}
        assert set(rows) == {"320x240", "256x192"}
        for size, r in rows.items():
            features, extract_ms, step_ms, tracked = float(r[2]), float(r[3]), float(r[4]), \
                int(r[5])
            assert features > 50 and extract_ms > 0 and step_ms > 0, (kind, size, r)
            assert 0 < tracked <= 8
    assert float(_rows(out.output, "xfeat")[0][2]) <= 1024  # its top-k
    ratios = re.findall(r"ratio xfeat / clahe-rootsift at (\d+x\d+): extract x([\d.]+), "
                        r"step x([\d.]+)", out.output)
    assert [r[0] for r in ratios] == ["320x240", "256x192"]
    assert all(float(r[1]) > 0 and float(r[2]) > 0 for r in ratios)


def test_cli_extract_bench_times_an_image_alone_and_refuses_bad_sizes(
        tmp_path: Path, sunny1: Round) -> None:
    out = CliRunner().invoke(app, ["bench", "extract", "--image", str(sunny1.image_path(0)),
                                   "--sizes", "160x128", "--repeats", "1"])
    assert out.exit_code == 0, out.output
    assert len(_rows(out.output, "xfeat")) == 1 and _rows(out.output, "xfeat")[0][4] == "n/a"
    assert "extract x" in out.output and "step n/a" in out.output
    # the map of both types by default, its features counted as RootSIFT's
    dual = _rows(out.output, "clahe-rootsift+xfeat")
    assert len(dual) == 1 and dual[0][2] == _rows(out.output, "clahe-rootsift")[0][2]
    assert float(dual[0][3]) > 0 and "ratio clahe-rootsift+xfeat / clahe-rootsift at " \
        "160x128: extract x" in out.output
    for sizes in ("640", "20x20", "axb"):
        bad = CliRunner().invoke(app, ["bench", "extract", "--image",
                                       str(sunny1.image_path(0)), "--sizes", sizes])
        assert bad.exit_code != 0 and "--sizes" in bad.output, sizes
    none = CliRunner().invoke(app, ["bench", "extract"])
    assert none.exit_code != 0 and "DATASET" in none.output


def test_cli_extract_bench_sweeps_features_per_frame(rounds_dir: Path) -> None:
    """The sweep caps the features of map and frames at each count: a larger cap gives more
    features (the detector's threshold is low enough) and every row has its step."""
    out = CliRunner().invoke(app, ["bench", "extract", str(rounds_dir), "--map", "sunny1",
                                   "--query", "sunny1", "--sweep", "100,300",
                                   "--sweep-size", "320x240", "--skip-sizes",
                                   "--features", "clahe-rootsift", "--repeats", "1",
                                   "--frames", "4", "--warmup", "10"])
    assert out.exit_code == 0, out.output
    rows = _rows(out.output, "clahe-rootsift")
    assert [r[1] for r in rows] == ["100", "300"]
    assert float(rows[0][2]) <= 100 < float(rows[1][2]) <= 300
    assert all(float(r[4]) > 0 for r in rows) and rows[0][6] == "1.00"
    line = re.search(r"clahe-rootsift: 100 → 300: step x([0-9.]+) for features x([0-9.]+)",
                     out.output)
    assert line is not None, out.output  # the growth from cap to cap, beside the table's
    assert float(line[1]) == pytest.approx(float(rows[1][4]) / float(rows[0][4]), rel=0.05)
    assert float(line[2]) == pytest.approx(float(rows[1][2]) / float(rows[0][2]), rel=0.01)
    bad = CliRunner().invoke(app, ["bench", "extract", "--image", str(rounds_dir / "x.png"),
                                   "--sweep", "100"])
    assert bad.exit_code != 0 and "DATASET" in bad.output


def test_cli_approx_bench_prints_both_matchers_side_by_side(rounds_dir: Path) -> None:
    out = CliRunner().invoke(app, ["bench", "approx", str(rounds_dir), "--map", "sunny1",
                                   "--query", "sunny2", "--words", "16", "--frames", "4",
                                   "--warmup", "6", "--exact-geometry"])
    assert out.exit_code == 0, out.output
    [row] = _rows(out.output, "sunny2 (default features)")
    assert row[2] == "16" and float(row[3]) > 0  # k, its training ms
    steps = [float(v) for v in row[5].split(" / ")]
    assert len(steps) == 2 and min(steps) > 0
    assert 0.5 < float(row[8]) < 1.5  # the words matcher's counts near the exact ones
    assert "similarity only" in out.output
    bad = CliRunner().invoke(app, ["bench", "approx", str(rounds_dir), "--query", "nope"])
    assert bad.exit_code != 0
