"""The round format's positions file, read on both sides (client datasets, service builds).

``poses.csv`` has the header ``image,x,y[,t]`` (local metres east/north) or ``image,lat,lon[,t]``
(WGS84 degrees, projected around an origin with pyproj); an optional ``dataset.json`` one level
up carries that ``origin``. Every problem is reported with the file and line.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from service.api.geo import LocalFrame
from service.api.models import COORD_LIMIT_M

POSES_FILE = "poses.csv"
TRUTH_FILE = "truth.csv"
ODOMETRY_FILE = "odometry.csv"  # optional: image,x,y,yaw (the robot's odometry pose)
DATASET_FILE = "dataset.json"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class DatasetError(ValueError):
    """A round or dataset does not follow the format; the message names the file and row."""


def read_table(csv_path: Path) -> tuple[list[str], list[list[str]]]:
    if not csv_path.is_file():
        raise DatasetError(f"{csv_path}: missing (a round needs {POSES_FILE})")
    try:
        with csv_path.open(newline="", encoding="utf-8") as fh:
            rows = [row for row in csv.reader(fh) if any(cell.strip() for cell in row)]
    except (UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(f"{csv_path}: not a UTF-8 CSV file ({exc})") from None
    if not rows:
        raise DatasetError(f"{csv_path}: empty file, expected a header line like 'image,x,y'")
    header = [h.strip().lower() for h in rows[0]]
    return header, rows[1:]


def parse_positions(
    csv_path: Path, origin: tuple[float, float] | None
) -> tuple[list[str], np.ndarray, np.ndarray | None, tuple[float, float] | None]:
    header, rows = read_table(csv_path)
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
        _check_extent(csv_path, xy)
        return names, xy, times, origin
    _check_extent(csv_path, values)
    return names, values, times, None


def _check_extent(csv_path: Path, xy: np.ndarray) -> None:
    """Positions a map can be built on: |x|, |y| within the bound of every pose."""
    far = np.abs(xy).max(axis=1) > COORD_LIMIT_M
    if far.any():
        k = int(np.argmax(far))
        raise DatasetError(f"{csv_path}, line {k + 2}: position ({xy[k, 0]:g}, {xy[k, 1]:g}) m "
                           f"is beyond +-{COORD_LIMIT_M:g} m; give local coordinates (metres "
                           "from a nearby origin) or lat,lon")


def parse_odometry(csv_path: Path, names: list[str]) -> np.ndarray:
    """The (N, 3) odometry poses (x, y m; yaw rad) of ``odometry.csv``, one row per image of
    ``poses.csv`` in the same order; every problem named with the file and line."""
    header, rows = read_table(csv_path)
    want = ("image", "x", "y", "yaw")
    if not set(want) <= set(header):
        raise DatasetError(f"{csv_path}: header {header} needs the columns image,x,y,yaw")
    cols = [header.index(c) for c in want]
    if [r[cols[0]].strip() if len(r) > cols[0] else "" for r in rows] != names:
        raise DatasetError(f"{csv_path}: must list the same images in the same order as "
                           f"{POSES_FILE}")
    out = np.empty((len(rows), 3))
    for k, row in enumerate(rows):
        try:
            out[k] = [float(row[c]) for c in cols[1:]]
        except (ValueError, IndexError):
            raise DatasetError(f"{csv_path}, line {k + 2}: x, y and yaw must be numbers"
                               ) from None
        if not (np.isfinite(out[k]).all() and np.abs(out[k, :2]).max() <= COORD_LIMIT_M):
            raise DatasetError(f"{csv_path}, line {k + 2}: x, y and yaw must be finite, "
                               f"|x|, |y| <= {COORD_LIMIT_M:g} m")
    return out


def dataset_origin(round_dir: Path) -> tuple[float, float] | None:
    meta_path = round_dir.parent / DATASET_FILE
    if not meta_path.is_file():
        return None
    meta = read_meta(meta_path)
    o = meta.get("origin")
    if o is None:
        return None
    try:
        return float(o["lat"]), float(o["lon"])
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{meta_path}: 'origin' must be {{\"lat\": .., \"lon\": ..}}") from None


CALIB_FILE = "calib.txt"  # KITTI's projection matrices (P0: ...) in a round directory


def camera_from_hfov(hfov_deg: float, width: float, height: float) -> dict[str, float]:
    """Intrinsics as fractions of the image size for square pixels and a centred principal
    point, from the horizontal field of view (degrees) and the image size."""
    if not (0 < hfov_deg < 180 and width > 0 and height > 0):
        raise ValueError(f"need 0 < hfov_deg < 180 and a positive size, got {hfov_deg}, "
                         f"{width}x{height}")
    fx = 0.5 / math.tan(math.radians(hfov_deg) / 2)
    return {"fx": fx, "fy": fx * width / height, "cx": 0.5, "cy": 0.5}


def dataset_camera(round_dir: Path, image_size: tuple[int, int] | None = None,
                   dataset_json: bool = True) -> dict[str, float] | None:
    """The camera's intrinsics as fractions of the image size ({fx, fy, cx, cy}), from the
    dataset.json ``camera`` one level up ({"hfov_deg", "width", "height"}: square pixels,
    centred; or {"fx", "fy", "cx", "cy"} already as fractions), else from a KITTI
    ``calib.txt`` in the round (its first line, P0, in pixels of ``image_size`` = (width,
    height)); None when neither is there. ``dataset_json=False``: the round has no dataset
    above it (an uploaded round at the top of its archive)."""
    meta_path = round_dir.parent / DATASET_FILE
    cam = (read_meta(meta_path).get("camera") if dataset_json and meta_path.is_file()
           else None)
    if cam is not None:
        try:
            if "hfov_deg" in cam:
                out = camera_from_hfov(float(cam["hfov_deg"]), float(cam["width"]),
                                       float(cam["height"]))
            else:
                out = {k: float(cam[k]) for k in ("fx", "fy", "cx", "cy")}
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{meta_path}: 'camera' must be {{\"hfov_deg\", \"width\", "
                               "\"height\"} or {\"fx\", \"fy\", \"cx\", \"cy\"} as "
                               "fractions of the image size, all positive") from None
        if not all(math.isfinite(v) and v > 0 for v in out.values()):
            raise DatasetError(f"{meta_path}: camera intrinsics must be positive numbers")
        return out
    calib = round_dir / CALIB_FILE
    if not calib.is_file() or image_size is None:
        return None
    lines = [ln for ln in calib.read_text(encoding="utf-8", errors="replace").splitlines()
             if ln.strip()]
    # the first line is P0 (the left camera), with or without its 'P0:' label
    first = lines[0].split() if lines else []
    try:
        p = [float(v) for v in (first[1:] if first and first[0].endswith(":") else first)]
        if len(p) == 12:
            w, h = image_size
            out = {"fx": p[0] / w, "fy": p[5] / h, "cx": p[2] / w, "cy": p[6] / h}
            if all(math.isfinite(v) and v > 0 for v in out.values()):
                return out
    except ValueError:
        pass
    raise DatasetError(f"{calib}: the first line is not a projection matrix P0 (12 "
                       "numbers, optionally after 'P0:', with positive focal lengths)")


def read_meta(meta_path: Path) -> dict:
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{meta_path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{meta_path}: expected a JSON object")
    return meta
