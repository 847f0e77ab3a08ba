from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from client.dataset import DatasetError, read_dataset, read_round, write_dataset_meta, write_round


def _round(tmp_path: Path, rows: str, images: tuple[str, ...] = ("a.png", "b.png")) -> Path:
    d = tmp_path / "r1"
    d.mkdir()
    for name in images:
        cv2.imwrite(str(d / name), np.full((24, 32), 128, np.uint8))
    (d / "poses.csv").write_text(rows)
    return d


def test_reads_metric_round_with_time(tmp_path: Path) -> None:
    d = _round(tmp_path, "image,x,y,t\na.png,1.5,2,0\nb.png,3,4,1.0\n")
    r = read_round(d, decode_images=True)
    assert r.images == ("a.png", "b.png")
    np.testing.assert_allclose(r.xy, [[1.5, 2], [3, 4]])
    np.testing.assert_allclose(r.t, [0, 1])
    assert r.truth_xy is None and r.origin is None
    assert r.load_image(1).shape == (24, 32)


def test_geographic_round_uses_dataset_origin(tmp_path: Path) -> None:
    d = _round(tmp_path, "image,lat,lon\na.png,48.5,9.05\nb.png,48.5009,9.05\n")
    write_dataset_meta(tmp_path, {"name": "geo", "origin": {"lat": 48.5, "lon": 9.05}})
    r = read_round(d)
    assert r.origin == (48.5, 9.05)
    np.testing.assert_allclose(r.xy[0], [0, 0], atol=1e-6)
    assert r.xy[1, 0] == pytest.approx(0, abs=1e-6)
    assert r.xy[1, 1] == pytest.approx(100.0, rel=0.01)  # 0.0009 deg of latitude ~ 100 m
    ds = read_dataset(tmp_path)
    assert ds.name == "geo" and list(ds.rounds) == ["r1"]


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ("image,x\na.png,1\n", "needs columns 'x,y'"),
        ("x,y\n1,2\n", "no 'image' column"),
        ("image,x,y\n", "empty"),
        ("image,x,y\na.png,1,2\na.png,3,4\n", "line 3: duplicate image name 'a.png'"),
        ("image,x,y\na.png,1,nan\n", "line 2: y=nan is not finite"),
        ("image,x,y\na.png,1,abc\n", "line 2: y='abc' is not a number"),
        ("image,x,y\na.png,1,2\nmissing.png,3,4\n", "line 3: image 'missing.png' does not exist"),
        ("image,x,y,t\na.png,1,2,5\nb.png,3,4,1\n", "t goes backwards"),
        ("image,x,y\na.png,1\n", "line 2: 2 fields"),
        ("image,lat,lon\na.png,95,9\n", "out of range"),
    ],
)
def test_validation_errors_name_file_and_row(tmp_path: Path, rows: str, message: str) -> None:
    d = _round(tmp_path, rows)
    with pytest.raises(DatasetError) as exc:
        read_round(d)
    assert message in str(exc.value)
    assert "poses.csv" in str(exc.value)


def test_unreadable_image_is_reported(tmp_path: Path) -> None:
    d = _round(tmp_path, "image,x,y\na.png,1,2\nb.png,3,4\n")
    (d / "b.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"line 3: image 'b\.png' is unreadable"):
        read_round(d, decode_images=True)


def test_missing_poses_and_truth_mismatch(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not a directory"):
        read_round(tmp_path / "nope")
    d = _round(tmp_path, "image,x,y\na.png,1,2\nb.png,3,4\n")
    write_round(d, ["b.png", "a.png"], np.zeros((2, 2)))
    (d / "truth.csv").write_text("image,x,y\na.png,1,2\nb.png,3,4\n")
    with pytest.raises(DatasetError, match="same images in the same order"):
        read_round(d)


def test_write_round_roundtrip(tmp_path: Path) -> None:
    d = _round(tmp_path, "image,x,y\na.png,0,0\nb.png,0,0\n")
    xy = np.array([[1.25, -2.5], [3.0, 4.0]])
    write_round(d, ["a.png", "b.png"], xy, np.array([0.0, 0.5]), truth_xy=xy + 0.1)
    r = read_round(d)
    np.testing.assert_allclose(r.xy, xy)
    np.testing.assert_allclose(r.reference_xy, xy + 0.1)
