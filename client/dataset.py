"""Route dataset format: read, validate and write rounds.

A dataset is a directory with one sub-directory per traversal ("round"). Each round holds
``poses.csv`` (header ``image,x,y[,t]`` in local metres east/north, or ``image,lat,lon[,t]`` in
WGS84 degrees) and the PNG/JPEG images it names by relative path. An optional ``truth.csv``
beside it (same header, same images, same order) holds exact positions; ``poses.csv`` then holds
the GPS-like ones. An optional ``dataset.json`` at the top carries a name, a description and,
for geographic data, the ``origin`` ({"lat": .., "lon": ..}) of the shared local frame.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from service.geo import LocalFrame

POSES_FILE = "poses.csv"
TRUTH_FILE = "truth.csv"
DATASET_FILE = "dataset.json"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class DatasetError(ValueError):
    """A round or dataset does not follow the format; the message names the file and row."""


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

    def __len__(self) -> int:
        return len(self.images)

    @property
    def reference_xy(self) -> np.ndarray:
        """Exact positions when the round has a truth.csv, the poses otherwise."""
        return self.truth_xy if self.truth_xy is not None else self.xy

    def image_path(self, i: int) -> Path:
        return self.path / self.images[i]

    def load_image(self, i: int) -> np.ndarray:
        """The i-th image as 8-bit grayscale."""
        path = self.image_path(i)
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
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


def _read_table(csv_path: Path) -> tuple[list[str], list[list[str]]]:
    if not csv_path.is_file():
        raise DatasetError(f"{csv_path}: missing (a round needs {POSES_FILE})")
    with csv_path.open(newline="") as fh:
        rows = [row for row in csv.reader(fh) if any(cell.strip() for cell in row)]
    if not rows:
        raise DatasetError(f"{csv_path}: empty file, expected a header line like 'image,x,y'")
    header = [h.strip().lower() for h in rows[0]]
    return header, rows[1:]


def _parse_positions(
    csv_path: Path, origin: tuple[float, float] | None
) -> tuple[list[str], np.ndarray, np.ndarray | None, tuple[float, float] | None]:
    header, rows = _read_table(csv_path)
    if "image" not in header:
        raise DatasetError(f"{csv_path}: header {header} has no 'image' column")
    if {"x", "y"} <= set(header):
        coords = ("x", "y")
    elif {"lat", "lon"} <= set(header):
        coords = ("lat", "lon")
    else:
        raise DatasetError(
            f"{csv_path}: header {header} needs columns 'x,y' (metres) or 'lat,lon' (degrees)"
        )
    cols = [header.index(c) for c in ("image", *coords)]
    t_col = header.index("t") if "t" in header else None
    if not rows:
        raise DatasetError(f"{csv_path}: the round is empty (no rows after the header)")

    names: list[str] = []
    values = np.empty((len(rows), 2))
    times = np.empty(len(rows)) if t_col is not None else None
    seen: dict[str, int] = {}
    for k, row in enumerate(rows):
        line = k + 2  # 1-based, header is line 1
        if len(row) < len(header):
            raise DatasetError(
                f"{csv_path}, line {line}: {len(row)} fields, the header has {len(header)}"
            )
        name = row[cols[0]].strip()
        if not name:
            raise DatasetError(f"{csv_path}, line {line}: empty image name")
        if name in seen:
            raise DatasetError(
                f"{csv_path}, line {line}: duplicate image name '{name}' "
                f"(first on line {seen[name]})"
            )
        seen[name] = line
        names.append(name)
        wanted = [(coords[0], cols[1]), (coords[1], cols[2])]
        if t_col is not None:
            wanted.append(("t", t_col))
        for j, (col_name, col) in enumerate(wanted):
            cell = row[col].strip()
            try:
                v = float(cell)
            except ValueError:
                raise DatasetError(
                    f"{csv_path}, line {line}: {col_name}='{cell}' is not a number"
                ) from None
            if not math.isfinite(v):
                raise DatasetError(f"{csv_path}, line {line}: {col_name}={cell} is not finite")
            if j < 2:
                values[k, j] = v
            else:
                assert times is not None
                times[k] = v
    if times is not None and np.any(np.diff(times) < 0):
        bad = int(np.argmax(np.diff(times) < 0)) + 3
        raise DatasetError(f"{csv_path}, line {bad}: t goes backwards")

    if coords == ("lat", "lon"):
        lat, lon = values[:, 0], values[:, 1]
        if np.any(np.abs(lat) > 90) or np.any(np.abs(lon) > 180):
            bad = int(np.argmax((np.abs(lat) > 90) | (np.abs(lon) > 180))) + 2
            raise DatasetError(f"{csv_path}, line {bad}: lat/lon out of range")
        if origin is None:
            origin = (float(lat[0]), float(lon[0]))
        xy = LocalFrame(*origin).to_local(lat, lon)
        return names, xy, times, origin
    return names, values, times, None


def _dataset_origin(round_dir: Path) -> tuple[float, float] | None:
    meta_path = round_dir.parent / DATASET_FILE
    if not meta_path.is_file():
        return None
    meta = _read_meta(meta_path)
    o = meta.get("origin")
    if o is None:
        return None
    try:
        return float(o["lat"]), float(o["lon"])
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{meta_path}: 'origin' must be {{\"lat\": .., \"lon\": ..}}") from None


def _read_meta(meta_path: Path) -> dict:
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{meta_path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{meta_path}: expected a JSON object")
    return meta


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
    origin = origin or _dataset_origin(path)
    names, xy, t, origin = _parse_positions(path / POSES_FILE, origin)
    for line, name in enumerate(names, start=2):
        img_path = path / name
        if not img_path.is_file():
            raise DatasetError(f"{path / POSES_FILE}, line {line}: image '{name}' does not exist")
        if img_path.suffix.lower() not in IMAGE_SUFFIXES:
            raise DatasetError(
                f"{path / POSES_FILE}, line {line}: '{name}' is not a PNG or JPEG file"
            )
        if decode_images and cv2.imread(str(img_path), cv2.IMREAD_GRAYSCALE) is None:
            raise DatasetError(f"{path / POSES_FILE}, line {line}: image '{name}' is unreadable")

    truth_xy = None
    if (path / TRUTH_FILE).is_file():
        t_names, truth_xy, _, _ = _parse_positions(path / TRUTH_FILE, origin)
        if t_names != names:
            raise DatasetError(
                f"{path / TRUTH_FILE}: must list the same images in the same order as {POSES_FILE}"
            )
    return Round(
        name=path.name,
        path=path,
        images=tuple(names),
        xy=xy,
        t=t,
        truth_xy=truth_xy,
        origin=origin,
    )


def read_dataset(path: str | Path) -> Dataset:
    """Read every round (sub-directory with a poses.csv) of a dataset directory."""
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: not a directory")
    meta = _read_meta(path / DATASET_FILE) if (path / DATASET_FILE).is_file() else {}
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


def write_dataset_meta(path: str | Path, meta: dict) -> None:
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    tmp = path / (DATASET_FILE + ".tmp")
    with tmp.open("w") as fh:
        fh.write(json.dumps(meta, indent=2) + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path / DATASET_FILE)
