"""Uploaded rounds: a zip or tar(.gz) archive of a round directory, extracted safely.

Extraction refuses, with a clear error and nothing left behind (the caller removes ``dest``):

- member names that are absolute, contain ``..`` or a backslash, or hold a NUL byte;
- anything but regular files and directories (symlinks, hard links, devices, FIFOs);
- more than ``max_members`` members, more than ``max_unpacked_bytes`` unpacked, or a
  compression ratio over ``max_ratio`` (a member's declared ratio in a zip, the bytes actually
  written against the archive's size for both formats): zip bombs;
- encrypted zip members.

The round is the shallowest directory holding ``poses.csv`` (at the top or one folder down);
an optional ``dataset.json`` next to that folder gives the geodetic origin. Every image
``poses.csv`` names must lie inside the round, be a PNG or JPEG and decode within the pixel
limit; nothing outside ``dest`` is ever read.
"""

from __future__ import annotations

import dataclasses
import shutil
import stat
import tarfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

import numpy as np

from service.api.errors import BadRequest, InvalidParameters, PayloadTooLarge
from service.api.round_format import (
    CALIB_FILE,
    DATASET_FILE,
    IMAGE_SUFFIXES,
    POSES_FILE,
    DatasetError,
    dataset_camera,
    parse_positions,
    read_meta,
)
from service.vision.imaging import decode_frame

_CHUNK = 1 << 20
_RATIO_FLOOR = 1 << 20  # members smaller than this may compress well (blank images, CSV)


@dataclass(frozen=True)
class ArchiveLimits:
    max_members: int = 100_000
    max_unpacked_bytes: int = 2 << 30
    max_ratio: float = 100.0
    max_pixels: int = 16_000_000


@dataclass(frozen=True)
class UploadedRound:
    """A validated round inside an extraction directory (positions as in ``map build``)."""

    name: str
    path: Path
    images: tuple[str, ...]
    xy: np.ndarray
    t: np.ndarray | None
    origin: tuple[float, float] | None
    max_pixels: int
    camera: dict[str, float] | None = None  # intrinsics as fractions of the image size

    def __len__(self) -> int:
        return len(self.images)

    def load_image(self, i: int) -> np.ndarray:
        data = (self.path / self.images[i]).read_bytes()
        return decode_frame(data, None, len(data) + 1, self.max_pixels)


def _member_path(name: str) -> PurePosixPath:
    if "\x00" in name or "\\" in name:
        raise BadRequest(f"archive member '{name!r}' has a NUL byte or a backslash in its name")
    p = PurePosixPath(name)
    if p.is_absolute() or (len(name) > 1 and name[1] == ":"):
        raise BadRequest(f"archive member '{name}' has an absolute path; paths must be relative "
                         "to the round")
    if ".." in p.parts:
        raise BadRequest(f"archive member '{name}' contains '..'; paths must stay inside the "
                         "round")
    return p


class _Budget:
    """Counts members and unpacked bytes against the limits."""

    def __init__(self, limits: ArchiveLimits, archive_bytes: int) -> None:
        self.limits = limits
        self.members = 0
        self.written = 0
        self.ratio_cap = max(limits.max_ratio * archive_bytes, _RATIO_FLOOR)

    def member(self) -> None:
        self.members += 1
        if self.members > self.limits.max_members:
            raise PayloadTooLarge(f"archive has more than {self.limits.max_members} members "
                                  "(SWARMLOC_MAX_ARCHIVE_MEMBERS)")

    def add(self, n: int) -> None:
        self.written += n
        if self.written > self.limits.max_unpacked_bytes:
            raise PayloadTooLarge(f"archive unpacks to more than {self.limits.max_unpacked_bytes}"
                                  " bytes (SWARMLOC_MAX_UNPACKED_BYTES); is it a zip bomb?")
        if self.written > self.ratio_cap:
            raise PayloadTooLarge(f"archive unpacks to more than {self.limits.max_ratio:g} times "
                                  "its size (SWARMLOC_MAX_ARCHIVE_RATIO): refused as a zip bomb")


def _copy(src: IO[bytes], target: Path, budget: _Budget) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    with target.open("xb") as out:
        while chunk := src.read(_CHUNK):
            budget.add(len(chunk))
            out.write(chunk)


def _zip_members(zf: zipfile.ZipFile, limits: ArchiveLimits) -> Iterator[zipfile.ZipInfo]:
    for info in zf.infolist():
        mode = info.external_attr >> 16
        if mode and stat.S_ISLNK(mode):
            raise BadRequest(f"archive member '{info.filename}' is a symbolic link; only files "
                             "and folders are accepted")
        if info.flag_bits & 0x1:
            raise BadRequest(f"archive member '{info.filename}' is encrypted")
        if (info.file_size > _RATIO_FLOOR
                and info.file_size > limits.max_ratio * max(info.compress_size, 1)):
            raise PayloadTooLarge(
                f"archive member '{info.filename}' expands {info.compress_size} bytes to "
                f"{info.file_size} (over {limits.max_ratio:g}x): refused as a zip bomb")
        yield info


def _extract(archive: Path, dest: Path, limits: ArchiveLimits) -> None:
    budget = _Budget(limits, archive.stat().st_size)
    if zipfile.is_zipfile(archive):
        try:
            with zipfile.ZipFile(archive) as zf:
                declared = sum(i.file_size for i in zf.infolist())
                if declared > limits.max_unpacked_bytes:
                    raise PayloadTooLarge(
                        f"archive declares {declared} unpacked bytes; the limit is "
                        f"{limits.max_unpacked_bytes} (SWARMLOC_MAX_UNPACKED_BYTES)")
                for info in _zip_members(zf, limits):
                    budget.member()
                    target = dest / _member_path(info.filename)
                    if info.is_dir():
                        target.mkdir(parents=True, exist_ok=True)
                        continue
                    with zf.open(info) as src:
                        _copy(src, target, budget)
        except (zipfile.BadZipFile, EOFError, OSError, NotImplementedError) as exc:
            raise BadRequest(f"corrupted zip archive: {exc}") from None
        return
    try:
        tf = tarfile.open(archive, "r:*")
    except (tarfile.TarError, OSError, EOFError):
        raise BadRequest("body is neither a zip nor a tar archive (plain, .gz, .bz2 or .xz) "
                         "of a round directory") from None
    try:
        with tf:
            while (member := tf.next()) is not None:
                budget.member()
                target = dest / _member_path(member.name)
                if member.isdir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                if not member.isfile():
                    kind = "link" if member.issym() or member.islnk() else "special file"
                    raise BadRequest(f"archive member '{member.name}' is a {kind}; only files "
                                     "and folders are accepted")
                member_src = tf.extractfile(member)
                if member_src is None:
                    raise BadRequest(f"archive member '{member.name}' cannot be read")
                _copy(member_src, target, budget)
    except (tarfile.TarError, EOFError, OSError, zipfile.BadZipFile) as exc:
        raise BadRequest(f"corrupted tar archive: {exc}") from None


def _round_dir(dest: Path) -> Path:
    found = [p for p in dest.rglob(POSES_FILE) if p.is_file()]
    if not found:
        raise InvalidParameters(f"the archive has no {POSES_FILE}: send a round directory "
                                f"({POSES_FILE} with the header image,x,y[,t] or "
                                "image,lat,lon[,t], and its images)")
    depth = min(len(p.relative_to(dest).parts) for p in found)
    top = [p for p in found if len(p.relative_to(dest).parts) == depth]
    if len(top) > 1 or depth > 2:
        where = sorted(str(p.relative_to(dest)) for p in found)
        raise InvalidParameters(f"the archive must hold one round ({POSES_FILE} at the top or "
                                f"one folder down); found {where}")
    return top[0].parent


def _relative(exc: Exception, dest: Path) -> str:
    return str(exc).replace(str(dest) + "/", "").replace(str(dest), ".")


def extract_round(archive: Path, dest: Path, limits: ArchiveLimits) -> UploadedRound:
    """Extract ``archive`` into the empty directory ``dest`` and validate the round in it.

    Raises a ServiceError (400 malformed archive, 413 limits, 422 invalid round); the caller
    removes ``dest`` on error.
    """
    dest.mkdir(parents=True, exist_ok=True)
    _extract(archive, dest, limits)
    root = _round_dir(dest)
    try:
        origin = None
        if root != dest and (root.parent / DATASET_FILE).is_file():
            o = read_meta(root.parent / DATASET_FILE).get("origin")
            origin = (float(o["lat"]), float(o["lon"])) if o else None
        names, xy, t, origin = parse_positions(root / POSES_FILE, origin)
    except (DatasetError, KeyError, TypeError, ValueError) as exc:
        raise InvalidParameters(f"invalid round: {_relative(exc, dest)}") from None
    rnd = UploadedRound(root.name if root != dest else "round", root, tuple(names), xy, t,
                        origin, limits.max_pixels)
    base = root.resolve()
    for line, name in enumerate(names, start=2):
        where = f"{POSES_FILE}, line {line}: image '{name}'"
        img = (root / name).resolve()
        if not img.is_relative_to(base):
            raise InvalidParameters(f"{where} lies outside the round")
        if not img.is_file():
            raise InvalidParameters(f"{where} is not in the archive")
        if img.suffix.lower() not in IMAGE_SUFFIXES:
            raise InvalidParameters(f"{where} is not a PNG or JPEG file")
        try:
            rnd.load_image(line - 2)
        except Exception as exc:  # ServiceError from decode_frame, or OSError
            msg = getattr(exc, "message", str(exc))
            raise InvalidParameters(f"{where} is unreadable: {msg}") from None
    # the camera (every image is checked by now): dataset.json one level up, or a KITTI
    # calib.txt in the round
    try:
        size = None
        if (root / CALIB_FILE).is_file() and names:
            h, w = rnd.load_image(0).shape[:2]
            size = (w, h)
        rnd = dataclasses.replace(rnd, camera=dataset_camera(root, size, root != dest))
    except DatasetError as exc:
        raise InvalidParameters(f"invalid round: {_relative(exc, dest)}") from None
    return rnd


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
