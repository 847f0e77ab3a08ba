"""Pairs known only by frame correspondence (``swarmloc eval-pair``, the Gardens Point case)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from client.cli import app
from client.dataset import DatasetError, Round
from client.lab.eval_pair import eval_pair, read_indexed_frames

FRAMES = 12


def _indexed(folder: Path, images: list[Path], order: list[int]) -> Path:
    """A folder with ``images`` and a poses.csv of filename,index (rows in ``order``)."""
    folder.mkdir()
    rows = ["filename,index"]
    for k in order:
        name = f"{k}{images[k].suffix}"
        shutil.copy(images[k], folder / name)
        rows.append(f"{name},{k}")
    (folder / "poses.csv").write_text("\n".join(rows) + "\n")
    return folder


@pytest.fixture(scope="module")
def day(tmp_path_factory: pytest.TempPathFactory, sunny1: Round) -> Path:
    root = tmp_path_factory.mktemp("pair")
    images = [sunny1.image_path(i * 2) for i in range(FRAMES)]
    return _indexed(root / "day", images, list(range(FRAMES))[::-1])  # rows in any order


@pytest.fixture(scope="module")
def blank(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Frames with no structure at all (a camera at night): nothing can match them."""
    root = tmp_path_factory.mktemp("blank")
    src = root / "src"
    src.mkdir()
    images = []
    for k in range(FRAMES):
        p = src / f"{k}.png"
        cv2.imwrite(str(p), np.full((240, 320), 20 + k, np.uint8))
        images.append(p)
    return _indexed(root / "night", images, list(range(FRAMES)))


def test_indexed_frames_are_placed_by_their_index(day: Path) -> None:
    rnd = read_indexed_frames(day, 2.5)
    assert rnd.images[:3] == ("0.png", "1.png", "2.png")
    assert np.allclose(rnd.xy[:, 0], 2.5 * np.arange(FRAMES)) and np.all(rnd.xy[:, 1] == 0)


@pytest.mark.parametrize(("csv", "message"), [
    ("name,idx\n0.png,0\n1.png,1\n", "header must name the columns filename,index"),
    ("filename,index\n0.png,zero\n1.png,1\n", "line 2: index 'zero' is not an integer"),
    ("filename,index\n0.png,0\nmissing.png,1\n", "line 3: image 'missing.png' does not exist"),
    ("filename,index\n0.png,0\nposes.csv,1\n", "line 3: 'poses.csv' is not a PNG or JPEG"),
    ("filename,index\n0.png,0\n1.png,0\n", "an index appears twice"),
    ("filename,index\n0.png,0\n", "needs at least 2 frames"),
])
def test_bad_correspondence_files_are_refused(tmp_path: Path, day: Path, csv: str,
                                              message: str) -> None:
    for name in ("0.png", "1.png"):
        shutil.copy(day / name, tmp_path / name)
    (tmp_path / "poses.csv").write_text(csv)
    with pytest.raises(DatasetError, match=message):
        read_indexed_frames(tmp_path, 2.5)


def test_the_same_traversal_is_tracked(day: Path) -> None:
    r = eval_pair(day, day, width=320, height=240, passes=2, seeds=2)
    assert r.best_is_true == FRAMES and r.true_similarity_median > 0.5
    assert r.status.get("tracking", 0) > 0.8 * r.replayed and r.tracking_wrong == 0
    assert r.best_within_one == FRAMES and r.frames_tracked == FRAMES
    assert 0.8 * r.replayed < r.tracking_within_one <= r.status["tracking"]


def test_frames_that_cannot_match_are_never_tracked(day: Path, blank: Path) -> None:
    r = eval_pair(day, blank, width=320, height=240, passes=2, seeds=2)
    assert r.true_similarity_median == 0.0
    assert r.status.get("tracking", 0) == 0 and r.tracking_wrong == 0
    assert r.tracking_within_one == 0 and r.frames_tracked == 0
    assert r.replayed == 2 * 2 * (2 * FRAMES - 2)


def test_cli_reports_the_pair_and_refuses_a_folder_without_poses(
        tmp_path: Path, day: Path) -> None:
    runner = CliRunner()
    out = runner.invoke(app, ["eval-pair", str(day), str(day), "--width", "320", "--height",
                              "240", "--passes", "1", "--seeds", "1"])
    assert out.exit_code == 0, out.output
    assert f"own place for {FRAMES}/{FRAMES} frames" in out.output
    bad = runner.invoke(app, ["eval-pair", str(day), str(tmp_path)])
    assert bad.exit_code != 0 and "no poses.csv" in bad.output


def test_cli_judges_the_pair_with_xfeat_and_takes_estimator_parameters(day: Path) -> None:
    runner = CliRunner()
    out = runner.invoke(app, ["eval-pair", str(day), str(day), "--features", "xfeat",
                              "--width", "320", "--height", "240", "--passes", "2",
                              "--seeds", "1", "--param", "v0=0.05"])
    assert out.exit_code == 0, out.output
    assert "(xfeat, 320x240)" in out.output
    assert f"own place for {FRAMES}/{FRAMES} frames, within +-1 frame for {FRAMES}/{FRAMES}" \
        in out.output
    line = next(x for x in out.output.splitlines() if x.startswith("reported tracking within"))
    within, replayed = (int(v) for v in line.split(": ")[1].split(" ")[0].split("/"))
    assert replayed == 2 * (2 * FRAMES - 2) and within > 0.75 * replayed  # after initializing
    bad = runner.invoke(app, ["eval-pair", str(day), str(day), "--param", "v0=5"])
    assert bad.exit_code != 0 and "v0" in bad.output
    unknown = runner.invoke(app, ["eval-pair", str(day), str(day), "--features", "orb"])
    assert unknown.exit_code != 0 and "unknown feature type 'orb'" in unknown.output
