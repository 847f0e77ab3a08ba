"""Uploaded rounds: a zip or tar(.gz) archive of a round directory, extracted safely.

Extraction refuses, with a clear error and nothing left behind (the caller removes ``dest``):

- member names that are absolute, contain ``..`` or a backslash, or hold a NUL byte;
- anything but regular files and directories (symlinks, hard links, devices, FIFOs);
- more than ``max_members`` members, more than ``max_unpacked_bytes`` unpacked, or a
  compression ratio over ``max_ratio`` (a member's declared ratio in a zip, the bytes actually
  written against the archive's size for both formats): zip bombs;
- encrypted zip members;
- tar meta headers that could stall or swell the parser (Python's ``tarfile`` before 3.11.10
  has a quadratic pax regex, CVE-2024-6232, and reads a pax or GNU long-name header whole):
  ``_TarHeaderGuard`` reads every 512-byte header block before ``tarfile`` does and refuses
  pax / GNU long-name records over ``MAX_META_BYTES``, digit runs whose regex cost would add up
  past a budget, sparse members and pax ``size`` overrides (rounds never need them).

The round is the shallowest directory holding ``poses.csv`` (at the top or one folder down);
an optional ``dataset.json`` next to that folder gives the geodetic origin. Every image
``poses.csv`` names must lie inside the round, be a PNG or JPEG and decode within the pixel
limit; nothing outside ``dest`` is ever read.
"""

from __future__ import annotations

import bz2
import dataclasses
import gzip
import lzma
import re
import shutil
import stat
import tarfile
import zipfile
import zlib
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
    ODOMETRY_FILE,
    POSES_FILE,
    DatasetError,
    dataset_camera,
    parse_odometry,
    parse_positions,
    read_meta,
)
from service.vision.imaging import decode_frame

_CHUNK = 1 << 20
_RATIO_FLOOR = 1 << 20  # members smaller than this may compress well (blank images, CSV)
_BLOCK = 512
#: largest pax ('x', 'g') or GNU long-name ('L', 'K') record a tar may hold (bytes)
MAX_META_BYTES = 8192
_MAX_DIGIT_RUN = 64  # no pax value needs more digits in a row (a 64-bit mtime has 20)
# sum over every pax record of (digit run length)^2: what the quadratic regex costs (about
# 9 ns a unit, some 0.15 s in all); an ordinary pax header (a long path, an mtime with a
# fraction) costs about 200, so this budget takes some 80 000 of them
_DIGIT_COST_BUDGET = 1 << 24
_META_TYPES = (b"x", b"g", b"L", b"K")
_NO_DATA_TYPES = (b"1", b"2", b"3", b"4", b"5", b"6")  # links, devices, folders, FIFOs
_SHOWN = 120  # characters of a member name an error message shows
_DIGITS = re.compile(rb"\d+")


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
    odometry: np.ndarray | None = None  # (N, 3) x, y (m), yaw (rad) from odometry.csv

    def __len__(self) -> int:
        return len(self.images)

    def load_image(self, i: int) -> np.ndarray:
        data = (self.path / self.images[i]).read_bytes()
        return decode_frame(data, None, len(data) + 1, self.max_pixels)


def shown(name: str) -> str:
    """A member name as an error message shows it: at most ``_SHOWN`` characters."""
    return name if len(name) <= _SHOWN else f"{name[:_SHOWN]}... ({len(name)} characters)"


def _member_path(name: str) -> PurePosixPath:
    if "\x00" in name or "\\" in name:
        raise BadRequest(f"archive member {shown(name)!r} has a NUL byte or a backslash in its "
                         "name")
    p = PurePosixPath(name)
    if p.is_absolute() or (len(name) > 1 and name[1] == ":"):
        raise BadRequest(f"archive member '{shown(name)}' has an absolute path; paths must be "
                         "relative to the round")
    if ".." in p.parts:
        raise BadRequest(f"archive member '{shown(name)}' contains '..'; paths must stay "
                         "inside the round")
    return p


def _number(field: bytes) -> int | None:
    """A tar header number (octal, or GNU base-256); None when it is neither."""
    if field[:1] in (b"\x80", b"\xff"):
        n = int.from_bytes(field[1:], "big")
        return n - 256 ** (len(field) - 1) if field[:1] == b"\xff" else n
    text = field.split(b"\x00", 1)[0].strip()
    try:
        return int(text or b"0", 8)
    except ValueError:
        return None


def _checksum_ok(block: bytes) -> bool:
    stored = _number(block[148:156])
    unsigned = sum(block[:148]) + 256 + sum(block[156:])
    signed = sum(b - 256 if b > 127 else b for b in block[:148] + block[156:]) + 256
    return stored in (unsigned, signed)


class _TarHeaderGuard:
    """A plain tar stream as ``tarfile`` reads it (mode ``r|``), its headers checked first.

    Every byte passes through ``read`` in order, so each 512-byte header block is seen (and a
    pax or GNU long-name record refused) before ``tarfile`` parses it. The checks stop where
    ``tarfile`` stops (an empty or invalid block) or at a member it refuses anyway.
    """

    def __init__(self, raw: IO[bytes]) -> None:
        self.raw = raw
        self.pos = 0  # stream offset of the next byte read
        self.next_header = 0  # stream offset of the next header block
        self.block = bytearray()
        self.meta: bytearray | None = None  # the record being collected (pax or long name)
        self.meta_size = 0
        self.meta_kind = b""
        self.digit_cost = 0
        self.done = False

    def read(self, n: int = -1) -> bytes:
        data = self.raw.read(n if n is not None and n >= 0 else _CHUNK)
        at = 0
        while not self.done and at < len(data):
            at = self._take(data, at)
        self.pos += len(data)
        return data

    def _take(self, data: bytes, at: int) -> int:
        here = self.pos + at
        if self.meta is not None:
            take = min(self.meta_size - len(self.meta), len(data) - at)
            self.meta += data[at: at + take]
            if len(self.meta) == self.meta_size:
                self._check_meta(bytes(self.meta))
                self.meta = None
            return at + take
        if here < self.next_header:
            return at + min(self.next_header - here, len(data) - at)
        take = min(_BLOCK - len(self.block), len(data) - at)
        self.block += data[at: at + take]
        if len(self.block) == _BLOCK:
            self._header(bytes(self.block), here + take)
            self.block.clear()
        return at + take

    def _header(self, block: bytes, data_start: int) -> None:
        size = _number(block[124:136])
        if block.count(0) == _BLOCK or size is None or size < 0 or not _checksum_ok(block):
            self.done = True  # the end, or a block tarfile refuses itself
            return
        kind = block[156:157]
        padded = -(-size // _BLOCK) * _BLOCK
        if kind in _META_TYPES:
            if size > MAX_META_BYTES:
                what = "pax" if kind in (b"x", b"g") else "GNU long-name"
                raise PayloadTooLarge(f"archive has a {what} header of {size} bytes; the limit "
                                      f"is {MAX_META_BYTES} bytes")
            self.meta, self.meta_size, self.meta_kind = bytearray(), size, kind
            self.next_header = data_start + padded
            if size == 0:
                self.meta = None
        elif kind == b"S":
            raise BadRequest("archive has a sparse file; rounds hold only plain files")
        elif kind in _NO_DATA_TYPES:
            self.next_header = data_start
        else:  # regular files, and the types tarfile skips (refused as special files)
            self.next_header = data_start + padded

    def _check_meta(self, record: bytes) -> None:
        if self.meta_kind not in (b"x", b"g"):
            return
        runs = [m.end() - m.start() for m in _DIGITS.finditer(record)]
        if runs and max(runs) > _MAX_DIGIT_RUN:
            raise BadRequest(f"archive has a pax header with {max(runs)} digits in a row; no "
                             f"pax value needs more than {_MAX_DIGIT_RUN}")
        self.digit_cost += sum(n * n for n in runs)
        if self.digit_cost > _DIGIT_COST_BUDGET:
            raise PayloadTooLarge("archive has too many numbers in its pax headers to parse "
                                  "safely; write it without pax headers (tar --format=gnu)")
        for line in record.split(b"\n"):
            keyword = line.partition(b" ")[2].partition(b"=")[0]
            if keyword == b"size" or keyword.startswith(b"GNU.sparse"):
                raise BadRequest(f"archive has a pax '{keyword.decode('latin-1')}' record "
                                 "(a member over 8 GiB or a sparse file); rounds hold only "
                                 "plain files")


def _decompressed(archive: Path) -> IO[bytes]:
    """The archive's bytes, gunzipped / bunzipped / unxz-ed as its magic number says."""
    with archive.open("rb") as fh:
        magic = fh.read(6)
    if magic.startswith(b"\x1f\x8b"):
        return gzip.open(archive, "rb")  # type: ignore[return-value]
    if magic.startswith(b"BZh"):
        return bz2.open(archive, "rb")
    if magic.startswith(b"\xfd7zXZ\x00"):
        return lzma.open(archive, "rb")
    return archive.open("rb")


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
            raise BadRequest(f"archive member '{shown(info.filename)}' is a symbolic link; "
                             "only files and folders are accepted")
        if info.flag_bits & 0x1:
            raise BadRequest(f"archive member '{shown(info.filename)}' is encrypted")
        if (info.file_size > _RATIO_FLOOR
                and info.file_size > limits.max_ratio * max(info.compress_size, 1)):
            raise PayloadTooLarge(
                f"archive member '{shown(info.filename)}' expands {info.compress_size} bytes to "
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
        raw = _decompressed(archive)
    except OSError as exc:
        raise BadRequest(f"cannot read the archive: {exc}") from None
    try:
        with raw:
            _extract_tar(_TarHeaderGuard(raw), dest, budget)
    except (EOFError, OSError, lzma.LZMAError, zlib.error) as exc:
        raise BadRequest(f"corrupted tar archive: {exc}") from None


def _extract_tar(stream: _TarHeaderGuard, dest: Path, budget: _Budget) -> None:
    try:
        tf = tarfile.open(fileobj=stream, mode="r|")  # type: ignore[call-overload]
    except tarfile.TarError:
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
                    raise BadRequest(f"archive member '{shown(member.name)}' is a {kind}; only "
                                     "files and folders are accepted")
                member_src = tf.extractfile(member)
                if member_src is None:
                    raise BadRequest(f"archive member '{shown(member.name)}' cannot be read")
                _copy(member_src, target, budget)
    except tarfile.TarError as exc:
        raise BadRequest(f"corrupted tar archive: {str(exc)[:_SHOWN]}") from None


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
        if (root / ODOMETRY_FILE).is_file():  # the map's positions are fused with it
            rnd = dataclasses.replace(rnd, odometry=parse_odometry(root / ODOMETRY_FILE,
                                                                   list(names)))
    except DatasetError as exc:
        raise InvalidParameters(f"invalid round: {_relative(exc, dest)}") from None
    return rnd


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
