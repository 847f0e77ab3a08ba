"""Property-based fuzzing (hypothesis) of every parser that reads outside input: image
decoding, the dataset reader, the map file reader and the Zenoh payload parsers. Each either
returns a valid value or raises the module's own error with a message; nothing else."""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import struct
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from client.dataset import read_round
from service.api.errors import ServiceError
from service.api.round_format import DatasetError
from service.engine.localization_service import LocalizationService
from service.maps.round_archive import ArchiveLimits, extract_round
from service.maps.route_map import MAGIC, MapError, _canonical, _pad, load_map, save_map
from service.settings import Settings
from service.vision.imaging import decode_frame, encode_jpeg, encode_png
from service.zenoh.bridge import _frame_args, control, parse_attachment
from service.zenoh.maps import _options
from service.zenoh.replies import parse_json

# `swarmloc bench fuzz --minutes N` raises the number of examples and draws fresh ones; the
# suite's own run (no SWARMLOC_FUZZ_SCALE) uses fixed examples, so a CI run is reproducible
SCALE = float(os.environ.get("SWARMLOC_FUZZ_SCALE", "1"))
FUZZ = settings(max_examples=int(60 * SCALE), deadline=None, database=None,
                derandomize="SWARMLOC_FUZZ_SCALE" not in os.environ,
                suppress_health_check=[HealthCheck.too_slow,
                                       HealthCheck.function_scoped_fixture])
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=6), kids,
                                                               max_size=3),
    max_leaves=8)


def _mutate(data: bytes, edits: list[tuple[int, int]], cut: int | None) -> bytes:
    out = bytearray(data)
    for pos, val in edits:
        out[pos % len(out)] = val
    return bytes(out[:cut] if cut is not None else out)


_IMG = (np.arange(48 * 64, dtype=np.uint32).reshape(48, 64) * 2654435761 % 251).astype(
    np.uint8)
_SEEDS = [encode_png(_IMG), encode_jpeg(_IMG)]


@FUZZ
@given(seed=st.sampled_from(_SEEDS),
       edits=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6),
       cut=st.none() | st.integers(0, 2000),
       ctype=st.sampled_from([None, "image/png", "image/jpeg", "application/octet-stream",
                              "text/plain"]))
def test_decode_frame_accepts_or_refuses_with_a_4xx(seed: bytes, edits: list, cut: int | None,
                                                    ctype: str | None) -> None:
    data = _mutate(seed, edits, cut)
    try:
        img = decode_frame(data, ctype, max_bytes=1 << 20, max_pixels=1 << 16, min_side=16)
    except ServiceError as exc:
        assert 400 <= exc.status < 500 and exc.message
        return
    assert img.dtype == np.uint8 and img.ndim == 2 and min(img.shape) >= 16
    assert img.size <= 1 << 16


@FUZZ
@given(data=st.binary(max_size=300))
def test_decode_frame_on_random_bytes(data: bytes) -> None:
    try:
        decode_frame(data, None, 1 << 20, 1 << 16, 16)
    except ServiceError as exc:
        assert 400 <= exc.status < 500


# ---- dataset reader -------------------------------------------------------------------------
csv_cells = st.one_of(st.sampled_from(["a.png", "b.png", "x", "y", "t", "lat", "lon", "image",
                                       "nan", "inf", "-1e308", "1e400", "", " 3.5", "91"]),
                      st.text(max_size=6), st.floats().map(repr))


@FUZZ
@given(header=st.lists(st.sampled_from(["image", "x", "y", "t", "lat", "lon", "z"]),
                       min_size=1, max_size=4),
       rows=st.lists(st.lists(csv_cells, max_size=5), max_size=4),
       raw_tail=st.binary(max_size=8),
       meta=st.none() | json_values.map(json.dumps) | st.binary(max_size=10))
def test_read_round_accepts_or_names_the_problem(header: list[str], rows: list[list[str]],
                                                 raw_tail: bytes, meta: Any) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        rnd = root / "r1"
        rnd.mkdir(parents=True)
        for name in ("a.png", "b.png"):
            (rnd / name).write_bytes(_SEEDS[0])
        text = "\n".join(",".join(r) for r in [header, *rows]).encode() + raw_tail
        (rnd / "poses.csv").write_bytes(text)
        if meta is not None:
            (root / "dataset.json").write_bytes(meta if isinstance(meta, bytes)
                                                else meta.encode())
        try:
            r = read_round(rnd)
        except DatasetError as exc:
            assert str(exc)
            return
        assert len(r.images) == len(r.xy) and np.isfinite(r.xy).all()


# ---- map file reader ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_map_file(tmp_path_factory: pytest.TempPathFactory, small_map) -> Path:
    from service.maps.route_map import RouteMap

    n = 6
    end = int(small_map.offsets[n])
    m = RouteMap("tiny", dict(small_map.meta), np.array(small_map.positions[:n]),
                 small_map.image_names[:n], np.array(small_map.codes[:end]),
                 np.array(small_map.offsets[: n + 1]), np.array(small_map.keypoints[:end]))
    return save_map(m, tmp_path_factory.mktemp("tiny") / "tiny")


def _resign(header: dict, blob: bytes) -> bytes:
    """A map file with ``header`` over the original arrays, checksum recomputed."""
    header = {k: v for k, v in header.items() if k != "checksum"}
    if header.get("format_version") == 6 and isinstance(header.get("arrays"), dict):
        # version 6 (as 3-5): every array carries its own digest, the checksum covers the header
        for spec in header["arrays"].values():
            try:
                off, nb = int(spec["offset"]), int(spec["nbytes"])
                spec["sha256"] = hashlib.sha256(blob[off: off + nb]).hexdigest()
            except (KeyError, TypeError, ValueError):
                pass
        header["checksum"] = hashlib.sha256(_canonical(header)).hexdigest()
        head = json.dumps(header).encode()
        prefix = MAGIC + struct.pack("<Q", len(head)) + head
        return prefix + b"\x00" * _pad(len(prefix)) + blob
    digest = hashlib.sha256(_canonical(header))
    for spec in header.get("arrays", {}).values() if isinstance(header.get("arrays"),
                                                                dict) else []:
        try:
            off, nb = int(spec["offset"]), int(spec["nbytes"])
            digest.update(blob[off: off + nb])
        except (KeyError, TypeError, ValueError):
            pass
    header["checksum"] = digest.hexdigest()
    head = json.dumps(header).encode()
    prefix = MAGIC + struct.pack("<Q", len(head)) + head
    return prefix + b"\x00" * _pad(len(prefix)) + blob


def _split(path: Path) -> tuple[dict, bytes]:
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[8:16])
    start = 16 + n
    return json.loads(raw[16:start]), raw[start + _pad(start):]


@FUZZ
@given(key=st.sampled_from(["format_version", "arrays", "delta", "feature", "name",
                            "positions", "offsets", "codes", "image_names", "layers",
                            "place_words", "place_descriptors", "image_digests"]),
       field=st.sampled_from(["dtype", "shape", "offset", "nbytes"]),
       value=json_values,
       blob_edits=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=3))
def test_load_map_accepts_or_raises_map_error(tiny_map_file: Path, key: str, field: str,
                                              value: Any, blob_edits: list) -> None:
    header, blob = _split(tiny_map_file)
    if key in header["arrays"]:
        header["arrays"][key][field] = value
    else:
        header[key] = value
    if blob_edits:
        blob = _mutate(blob, blob_edits, None)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.swmap"
        path.write_bytes(_resign(header, blob))  # a valid checksum over bad content
        try:
            m = load_map(path)
        except MapError as exc:
            assert str(path) in str(exc)
            return
        assert np.isfinite(m.positions).all() and len(m.image_names) == m.n_images
        m.nearest(np.zeros((1, 2)))


@FUZZ
@given(data=st.binary(max_size=200))
def test_load_map_on_random_bytes(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.swmap"
        path.write_bytes(MAGIC + data)
        with pytest.raises(MapError):
            load_map(path)


# ---- Zenoh payload parsers ------------------------------------------------------------------
@FUZZ
@given(raw=st.one_of(st.binary(max_size=40), json_values.map(lambda v: json.dumps(v).encode())))
def test_attachment_parsers(raw: bytes) -> None:
    for parse in (parse_attachment, _options):
        try:
            out = parse(raw)
        except ServiceError as exc:
            assert exc.status == 400
            continue
        assert isinstance(out, dict)
    try:
        meta = parse_attachment(raw)
        t, _seq, prior, _odom = _frame_args(meta)
    except ServiceError as exc:
        assert exc.status in (400, 422)
        return
    assert t is None or np.isfinite(t)
    assert prior is None or np.isfinite([prior.x, prior.y, prior.radius]).all()


# the reproducers of issue 30: nested 100 000 deep, a 5 000-digit number, a non-string option
hostile_json = st.one_of(
    st.integers(1, 120_000).map(lambda n: b"[" * n),
    st.integers(1, 6000).map(lambda n: b'{"seq": ' + b"7" * n + b"}"),
    st.fixed_dictionaries({}, optional={k: json_values for k in (
        "action", "if_match", "if_none_match", "force", "t", "seq")}).map(
        lambda d: json.dumps(d).encode()))


@FUZZ
@given(raw=hostile_json)
@example(raw=b"[" * 100_000)
@example(raw=b'{"seq": ' + b"1" * 5000 + b"}")
@example(raw=b'{"if_match": 5}')
def test_zenoh_json_parsers_answer_400_or_a_value(raw: bytes) -> None:
    for parse in (parse_attachment, _options, lambda r: parse_json(r, "payload")):
        try:
            parse(raw)
        except ServiceError as exc:
            assert exc.status == 400 and len(exc.message) < 300
    try:
        _frame_args(parse_attachment(raw))
    except ServiceError as exc:
        assert exc.status in (400, 422)


frame_meta = st.fixed_dictionaries({}, optional={
    "t": json_values, "seq": json_values,
    "prior": st.fixed_dictionaries({}, optional={"x": json_values, "y": json_values,
                                                 "radius": json_values}) | json_values})


@FUZZ
@given(meta=frame_meta)
def test_frame_attachment_fields(meta: dict) -> None:
    try:
        t, _seq, prior, _odom = _frame_args(meta)
    except ServiceError as exc:
        assert exc.status == 422 and exc.message.startswith("invalid attachment")
        return
    assert t is None or np.isfinite(t)
    assert prior is None or np.isfinite([prior.x, prior.y, prior.radius]).all()


@pytest.fixture(scope="module")
def engine(tmp_path_factory: pytest.TempPathFactory, small_map) -> LocalizationService:
    maps = tmp_path_factory.mktemp("fuzz_maps")
    save_map(small_map, maps / "small")
    return LocalizationService(Settings(maps_dir=maps, zenoh_enabled=False, max_particles=500))


control_bodies = st.one_of(
    json_values,
    st.fixed_dictionaries({"action": st.sampled_from(["put", "get", "reset", "delete", "x"])},
                          optional={"x": json_values, "y": json_values, "radius": json_values,
                                    "seed": json_values, "map": json_values,
                                    "estimator": st.sampled_from(["dpso", "pf-g", "kalman"]),
                                    "params": st.dictionaries(
                                        st.sampled_from(["n_particles", "omega", "variant",
                                                         "bogus"]), json_values, max_size=2),
                                    "initial_pose": json_values}))


@FUZZ
@given(body=control_bodies)
def test_zenoh_control_answers_or_refuses_with_a_4xx(engine: LocalizationService,
                                                     body: Any) -> None:
    engine.ensure_session("fuzz")  # something to get, reset or delete
    try:
        reply = control(engine, "fuzz", body)
    except ServiceError as exc:
        assert 400 <= exc.status < 500, exc.message
        return
    assert isinstance(reply, dict)
    json.dumps(reply, allow_nan=False)  # every answer is strict JSON


@pytest.mark.parametrize("layer_id", [2**40, 5])
def test_a_stray_layer_id_is_refused_not_allocated(tiny_map_file: Path, layer_id: int) -> None:
    """Found by the fuzzer: a layer id of 2**40 made the per-layer index a list of 2**40
    entries (the process took 24 GB). Ids must be 0..L-1, each with images."""
    header, blob = _split(tiny_map_file)
    spec = header["arrays"]["layers"]
    off = int(spec["offset"])
    blob = blob[:off] + struct.pack("<q", layer_id) + blob[off + 8:]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "layers.swmap"
        path.write_bytes(_resign(header, blob))  # a valid checksum over the bad ids
        with pytest.raises(MapError, match=r"layer ids are not 0\.\.L-1"):
            load_map(path)


# ---- round archives: tar headers of any shape -----------------------------------------------
def _tar_header(name: bytes, size: int, kind: bytes) -> bytes:
    h = bytearray(512)
    h[0:len(name)] = name[:100]
    h[100:124] = b"0000644\x000000000\x000000000\x00"
    h[124:136] = (b"%011o\x00" % size) if size < 8**11 else b"\x80" + size.to_bytes(11, "big")
    h[136:148] = b"00000000000\x00"
    h[156:157] = kind
    h[257:265] = b"ustar\x0000"
    h[148:156] = b" " * 8
    h[148:156] = b"%06o\x00 " % sum(h)
    return bytes(h)


tar_records = st.lists(st.tuples(
    st.sampled_from([b"0", b"5", b"x", b"g", b"L", b"K", b"S", b"2", b"V", b"\x00"]),
    st.sampled_from([b"a.txt", b"r/poses.csv", b"../x", b"/abs", b"d/"]),
    st.one_of(st.binary(max_size=64), st.sampled_from([b"1" * 9000, b"30 path=" + b"9" * 80,
                                                       b"20 size=99999999\n", b"x" * 600])),
    st.one_of(st.none(), st.integers(0, 1 << 40))),  # the declared size (None: the true one)
    max_size=5)


def _tar(records: list[tuple[bytes, bytes, bytes, int | None]], compress: bool) -> bytes:
    out = b""
    for kind, name, data, declared in records:
        out += _tar_header(name, len(data) if declared is None else declared, kind)
        out += data + b"\x00" * (-len(data) % 512)
    out += b"\x00" * 1024
    return gzip.compress(out) if compress else out


@FUZZ
@given(records=tar_records, compress=st.booleans(), cut=st.none() | st.integers(0, 3000))
@example(records=[(b"x", b"p", b"1" * 150_000, None), (b"0", b"a.txt", b"", None)],
         compress=True, cut=None)
@example(records=[(b"L", b"l", b"a" * 100, 1 << 30), (b"0", b"a.txt", b"", None)],
         compress=True, cut=None)
def test_round_archive_reader_accepts_or_refuses_with_a_4xx(records: list, compress: bool,
                                                            cut: int | None) -> None:
    data = _tar(records, compress)
    data = data[:cut] if cut is not None else data
    with tempfile.TemporaryDirectory() as tmp:
        archive = Path(tmp) / "round.tgz"
        archive.write_bytes(data)
        try:
            extract_round(archive, Path(tmp) / "out", ArchiveLimits(max_members=20,
                                                                     max_unpacked_bytes=1 << 22))
        except ServiceError as exc:
            assert 400 <= exc.status < 500 and len(exc.message) < 1000, exc.message[:200]
            return
        raise AssertionError("no round (poses.csv with images) is ever in these archives")
