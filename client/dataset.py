"""Route dataset format: read, validate and write rounds.

A dataset is a directory with one sub-directory per traversal ("round"). Each round holds
``poses.csv`` (header ``image,x,y[,t]`` in local metres east/north, or ``image,lat,lon[,t]`` in
WGS84 degrees) and the PNG/JPEG images it names by relative path. An optional ``truth.csv``
beside it (same header, same images, same order) holds exact positions; ``poses.csv`` then holds
the GPS-like ones. An optional ``odometry.csv`` (header ``image,x,y,yaw``, same images, same
order) holds the robot's wheel-odometry pose at each image (m, m, rad in its own odometry
frame), which a replay sends with the frames. An optional ``dataset.json`` at the top
carries a name, a description and, for geographic data, the ``origin``
({"lat": .., "lon": ..}) of the shared local frame.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.api.round_format import (
    CALIB_FILE,
    DATASET_FILE,
    IMAGE_SUFFIXES,
    ODOMETRY_FILE,
    POSES_FILE,
    TRUTH_FILE,
    DatasetError,
    dataset_camera,
    dataset_origin,
    parse_odometry,
    parse_positions,
    read_meta,
)


def imread_gray(path: Path) -> np.ndarray | None:
    """An image file as 8-bit grayscale (None when it does not decode); needs OpenCV, which
    the light client install does not have: replaying sends the files' bytes."""
    try:
        import cv2
    except ImportError as exc:
        raise ImportError("decoding images needs OpenCV: pip install 'swarmloc[service]'"
                          ) from exc
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    return None if img is None else np.asarray(img)


@dataclass(frozen=True)
class Round:
    """One traversal: image names, positions in a local metric frame, optional times and truth."""

    name: str
    path: Path
    images: tuple[str, ...]
    xy: np.ndarray  # (N, 2) metres east/north, from poses.csv
    t: np.ndarray | None  # (N,) seconds
    truth_xy: np.ndarray | None  # (N, 2) metres, from truth.csv
    origin: tuple[float, float] | None  # (lat0, lon0) when the round was geographic
    # intrinsics as fractions of the image size {fx, fy, cx, cy}: dataset.json or calib.txt
    camera: dict[str, float] | None = None
    odometry: np.ndarray | None = None  # (N, 3) x, y (m), yaw (rad) from odometry.csv

    def __len__(self) -> int:
        return len(self.images)

    @property
    def reference_xy(self) -> np.ndarray:
        """Exact positions when the round has a truth.csv, the poses otherwise."""
        return self.truth_xy if self.truth_xy is not None else self.xy

    def subset(self, idx: Sequence[int], use_truth: bool = False) -> Round:
        """These frames only, in this order; ``use_truth``: the exact positions as poses."""
        i = np.asarray(idx, int)
        return Round(self.name, self.path, tuple(self.images[k] for k in i),
                     (self.reference_xy if use_truth else self.xy)[i],
                     self.t[i] if self.t is not None else None,
                     self.truth_xy[i] if self.truth_xy is not None else None, self.origin,
                     self.camera, self.odometry[i] if self.odometry is not None else None)

    def image_path(self, i: int) -> Path:
        return self.path / self.images[i]

    def load_image(self, i: int) -> np.ndarray:
        """The i-th image as 8-bit grayscale."""
        path = self.image_path(i)
        img = imread_gray(path)
        if img is None:
            raise DatasetError(f"{path}: cannot be decoded as an image")
        return img


@dataclass(frozen=True)
class Dataset:
    path: Path
    name: str
    description: str
    meta: dict
    rounds: dict[str, Round]


def check_image(folder: Path, name: str, where: str, decode: bool = False) -> None:
    """Raise DatasetError (prefixed by ``where``) unless ``folder/name`` is an existing PNG or
    JPEG file (and, with ``decode``, decodes)."""
    img_path = folder / name
    if not img_path.is_file():
        raise DatasetError(f"{where}: image '{name}' does not exist")
    if img_path.suffix.lower() not in IMAGE_SUFFIXES:
        raise DatasetError(f"{where}: '{name}' is not a PNG or JPEG file")
    if decode and imread_gray(img_path) is None:
        raise DatasetError(f"{where}: image '{name}' is unreadable")


def read_round(
    path: str | Path, origin: tuple[float, float] | None = None, decode_images: bool = False
) -> Round:
    """Read and validate one round directory.

    ``origin`` (lat0, lon0) fixes the local frame for geographic rounds; by default the
    dataset.json origin is used, else the first row. With ``decode_images`` every image is
    decoded once to prove it is readable (otherwise only its existence is checked).
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: not a directory (a round is a directory with {POSES_FILE})")
    origin = origin or dataset_origin(path)
    names, xy, t, origin = parse_positions(path / POSES_FILE, origin)
    for line, name in enumerate(names, start=2):
        check_image(path, name, f"{path / POSES_FILE}, line {line}", decode_images)

    truth_xy = None
    if (path / TRUTH_FILE).is_file():
        t_names, truth_xy, _, _ = parse_positions(path / TRUTH_FILE, origin)
        if t_names != names:
            raise DatasetError(
                f"{path / TRUTH_FILE}: must list the same images in the same order as {POSES_FILE}"
            )
    camera = dataset_camera(path, _image_size(path / names[0]))
    odometry = parse_odometry(path / ODOMETRY_FILE, names) \
        if (path / ODOMETRY_FILE).is_file() else None
    return Round(
        name=path.name,
        path=path,
        images=tuple(names),
        xy=xy,
        t=t,
        truth_xy=truth_xy,
        origin=origin,
        camera=camera,
        odometry=odometry,
    )


def _image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image, for a calib.txt in pixels; None without OpenCV or where
    it does not decode."""
    if not (path.parent / CALIB_FILE).is_file():
        return None
    try:
        img = imread_gray(path)
    except ImportError:
        return None
    return None if img is None else (img.shape[1], img.shape[0])


def read_dataset(path: str | Path) -> Dataset:
    """Read every round (sub-directory with a poses.csv) of a dataset directory."""
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: not a directory")
    meta = read_meta(path / DATASET_FILE) if (path / DATASET_FILE).is_file() else {}
    rounds = {
        d.name: read_round(d)
        for d in sorted(path.iterdir())
        if d.is_dir() and (d / POSES_FILE).is_file()
    }
    if not rounds:
        raise DatasetError(f"{path}: no rounds (sub-directories with {POSES_FILE})")
    return Dataset(
        path=path,
        name=str(meta.get("name", path.name)),
        description=str(meta.get("description", "")),
        meta=meta,
        rounds=rounds,
    )


def _write_csv(path: Path, names: Sequence[str], xy: np.ndarray, t: np.ndarray | None,
               geographic: bool = False) -> None:
    tmp = path.with_suffix(".csv.tmp")
    cols, fmt = (["lat", "lon"], "{:.9f}") if geographic else (["x", "y"], "{:.4f}")
    with tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", *cols, "t"] if t is not None else ["image", *cols])
        for k, name in enumerate(names):
            row = [name, fmt.format(xy[k, 0]), fmt.format(xy[k, 1])]
            if t is not None:
                row.append(f"{t[k]:.3f}")
            w.writerow(row)
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)


def write_round(
    path: str | Path,
    names: Sequence[str],
    xy: np.ndarray,
    t: np.ndarray | None = None,
    truth_xy: np.ndarray | None = None,
    geographic: bool = False,
) -> None:
    """Write poses.csv (and truth.csv) of a round whose images are already in ``path``;
    ``geographic``: ``xy`` holds (lat, lon) degrees and the header is ``image,lat,lon``."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    _write_csv(path / POSES_FILE, names, np.asarray(xy, float), t, geographic)
    if truth_xy is not None:
        _write_csv(path / TRUTH_FILE, names, np.asarray(truth_xy, float), t)


def write_odometry(path: str | Path, names: Sequence[str], poses: np.ndarray) -> None:
    """Write ``odometry.csv`` (image,x,y,yaw) of a round, atomically."""
    path = Path(path) / ODOMETRY_FILE
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", "x", "y", "yaw"])
        for name, (x, y, yaw) in zip(names, np.asarray(poses, float), strict=True):
            w.writerow([name, f"{x:.4f}", f"{y:.4f}", f"{yaw:.6f}"])
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)


def write_dataset_meta(path: str | Path, meta: dict) -> None:
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    tmp = path / (DATASET_FILE + ".tmp")
    with tmp.open("w") as fh:
        fh.write(json.dumps(meta, indent=2) + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path / DATASET_FILE)
