"""A session's complete state as compact, versioned bytes (the session stores' wire format).

Layout of a blob: ``b"SWST"``, format version (u8), CRC-32 of the body (u32, little endian),
then the body in MessagePack. A blob whose magic, version or checksum is wrong is refused
with ``StateError``, never half-read.

The estimators change often, so their state is not listed field by field: an object's state
is *every* attribute in its ``__dict__`` (arrays, numbers, strings, enums, None, tuples,
lists, dicts, nested small objects such as the lost-detection monitor, NumPy generators with
their ``bit_generator.state``), minus the attributes that derive from the map or from the
session's configuration and are rebuilt when the state is loaded. Those are named in ONE
place, ``REBUILT`` below. An attribute of a type the codec cannot carry stops encoding with
an error naming it, and a state that lacks an attribute the estimator now has is refused on
load, so a new attribute can never be silently dropped (tests/test_state_codec.py steps every
estimator kind through an encode/decode and checks the continuation bit for bit).

Arrays travel as dtype + shape + raw bytes; floats as IEEE doubles; integers beyond 64 bits
(PCG64's 128-bit state) as decimal strings. An object referenced twice (the same array in
two attributes) is written once and shared again on load.
"""

from __future__ import annotations

import enum
import importlib
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from service.api.models import Estimate
from service.engine.localizer import Localizer
from service.maps.route_map import RouteMap

MAGIC = b"SWST"
FORMAT_VERSION = 1
_HEADER = struct.Struct("<4sBI")

# What is rebuilt on load instead of stored: it derives from the map (the map index, its
# positions) or from the session configuration (the validated parameter object), and the
# Localizer's constructor makes it again from (map, estimator name, params, seed).
REBUILT: dict[str, frozenset[str]] = {
    # the estimator is stored on its own; the place seeder derives from the map and params,
    # and so does the map's same-light level (computed again when a search needs it)
    "localizer": frozenset({"map", "estimator", "seeder", "_level"}),
    "estimator": frozenset({"index", "params", "_map_positions", "_x_order",
                            "_x_sorted"}),
}

# Attributes added after states were first stored: a state written before one existed lacks
# it, and the freshly built object's value (its constructor's start value) is kept. Every
# other missing attribute is still refused. (Odometry, issue 33: the previous frame's
# odometry pose and the map heading fitted from odometry, both empty at the start, and the
# located frames' odometry gate, empty at the start; experience
# maps, issue 34: the layer choice, so a session stored before maps had experiences matches
# the map's own images. The first feature type's lost-detection monitor on maps of two
# types, issue 28: its background starts again at the next frame. The jump hold, issue 28:
# empty, so the first frame after loading is judged against no previous position. The
# particle filters' heading offsets per particle: drawn again at the next odometry step.
# DPSO's ``confirmed``, issue 28: a session stored before it keeps reporting its place as
# before.)
ADDED: dict[str, frozenset[str]] = {
    "localizer": frozenset({"odom_prev", "choice"}),
    "estimator": frozenset({"odometry", "gate", "first_monitor", "jump", "theta", "sequence",
                            "confirmed"}),
}

# classes an object in a state may be rebuilt as (a blob names its classes: never import
# anything outside the service from it)
_ALLOWED_MODULES = ("service.",)

# MessagePack extension codes
_EXT_ARRAY, _EXT_SCALAR, _EXT_TUPLE, _EXT_BIGINT, _EXT_ENUM, _EXT_OBJECT, _EXT_RNG, \
    _EXT_REF, _EXT_SET = range(1, 10)
_INT64 = (-(1 << 63), (1 << 64) - 1)


class StateError(ValueError):
    """A blob that is not a session state of this format, or a state that does not fit."""


# ---- generic values ----------------------------------------------------------------------
def _qualname(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


# modules of states stored before service/ moved into sub-packages (wave 3): old -> new
MOVED_MODULES: dict[str, str] = {
    f"service.{old}": f"service.{new}" for old, new in {
        "models": "api.models", "params": "api.params", "errors": "api.errors",
        "round_format": "api.round_format", "geo": "api.geo",
        "imaging": "vision.imaging", "features": "vision.features",
        "matcher": "vision.matcher", "place_index": "vision.place_index",
        "metric_pose": "vision.metric_pose", "map_geometry": "vision.map_geometry",
        "route_map": "maps.route_map", "round_archive": "maps.round_archive",
        "estimator": "estimators.base", "swarm": "estimators.paper_dpso",
        "multi_swarm": "estimators.multi_swarm_dpso",
        "particle_filter": "estimators.particle_filter",
        "lost_detection": "estimators.lost_detection",
        "along_track": "estimators.along_track", "located_noise": "estimators.located_noise",
        "registry": "estimators.registry", "fitness": "estimators.fitness",
        "localizer": "engine.localizer", "sessions": "engine.localization_service",
        "store": "engine.store", "state_codec": "engine.state_codec",
    }.items()
}


def _resolve(name: str) -> type:
    module, _, qual = name.partition(":")
    module = MOVED_MODULES.get(module, module)
    if not module.startswith(_ALLOWED_MODULES):
        raise StateError(f"state names class {name}, outside the service")
    obj: Any = importlib.import_module(module)
    for part in qual.split("."):
        obj = getattr(obj, part)
    if not isinstance(obj, type):
        raise StateError(f"state names {name}, which is not a class")
    return obj


class _Encoder:
    def __init__(self) -> None:
        self._seen: dict[int, int] = {}
        self._keep: list[Any] = []  # keeps ids unique while encoding

    def _ref(self, v: Any) -> msgpack.ExtType | None:
        idx = self._seen.get(id(v))
        if idx is not None:
            return msgpack.ExtType(_EXT_REF, msgpack.packb(idx))
        self._seen[id(v)] = len(self._seen)
        self._keep.append(v)
        return None

    def _pack(self, v: Any) -> bytes:
        return msgpack.packb(self.lower(v), use_bin_type=True, strict_types=True)

    def lower(self, v: Any, where: str = "state") -> Any:
        """``v`` as MessagePack-native values and extension types."""
        t = type(v)
        if v is None or t is bool or t is float or t is str or t is bytes:
            return v
        if t is int:
            if _INT64[0] <= v <= _INT64[1]:
                return v
            return msgpack.ExtType(_EXT_BIGINT, str(v).encode())
        if t is list:
            return [self.lower(x, f"{where}[{i}]") for i, x in enumerate(v)]
        if t is dict:
            out = {}
            for k, x in v.items():
                if type(k) is not str:
                    raise StateError(f"{where}: dict key {k!r} is not a string")
                out[k] = self.lower(x, f"{where}.{k}")
            return out
        if t is tuple:
            return msgpack.ExtType(_EXT_TUPLE, self._pack(list(v)))
        if t in (set, frozenset):
            return msgpack.ExtType(_EXT_SET, self._pack([t is frozenset, sorted(v)]))
        if isinstance(v, enum.Enum):
            return msgpack.ExtType(_EXT_ENUM, self._pack([_qualname(t), v.value]))
        if isinstance(v, np.generic):
            return msgpack.ExtType(_EXT_SCALAR, msgpack.packb([v.dtype.str, v.tobytes()]))
        if isinstance(v, np.ndarray):
            ref = self._ref(v)
            if ref is not None:
                return ref
            if v.dtype.hasobject:
                raise StateError(f"{where}: arrays of Python objects cannot be stored")
            a = np.ascontiguousarray(v)
            return msgpack.ExtType(_EXT_ARRAY, msgpack.packb(
                [a.dtype.str, list(a.shape), a.tobytes()], use_bin_type=True))
        if isinstance(v, np.random.Generator):
            ref = self._ref(v)
            if ref is not None:
                return ref
            bg = v.bit_generator
            return msgpack.ExtType(_EXT_RNG, self._pack([type(bg).__name__, bg.state]))
        if hasattr(v, "__dict__") and t.__module__.startswith(_ALLOWED_MODULES) \
                and not callable(v):
            ref = self._ref(v)
            if ref is not None:
                return ref
            # the attributes are lowered once here (lowering them again would meet the
            # extension types of their arrays)
            return msgpack.ExtType(_EXT_OBJECT, msgpack.packb(
                [_qualname(t), self.attrs(v, frozenset(), where)], use_bin_type=True,
                strict_types=True))
        raise StateError(f"{where}: cannot store a value of type {t.__module__}.{t.__qualname__}"
                         " in a session state (add it to state_codec.REBUILT if it derives "
                         "from the map, or give it a plain type)")

    def attrs(self, obj: object, skip: frozenset[str], where: str) -> dict[str, Any]:
        return {k: self.lower(x, f"{where}.{k}") for k, x in vars(obj).items() if k not in skip}


class _Decoder:
    def __init__(self) -> None:
        self._objs: list[Any] = []

    def unpack(self, data: bytes) -> Any:
        return msgpack.unpackb(data, raw=False, ext_hook=self.ext, strict_map_key=True,
                               use_list=True)

    def ext(self, code: int, data: bytes) -> Any:
        if code == _EXT_REF:
            return self._objs[msgpack.unpackb(data)]
        if code == _EXT_ARRAY:
            dtype, shape, raw = msgpack.unpackb(data, raw=False)
            a = np.frombuffer(raw, dtype=np.dtype(dtype)).reshape(shape).copy()
            self._objs.append(a)
            return a
        if code == _EXT_SCALAR:
            dtype, raw = msgpack.unpackb(data, raw=False)
            return np.frombuffer(raw, dtype=np.dtype(dtype))[0]
        if code == _EXT_BIGINT:
            return int(data.decode())
        if code == _EXT_TUPLE:
            return tuple(self.unpack(data))
        if code == _EXT_SET:
            frozen, items = self.unpack(data)
            return frozenset(items) if frozen else set(items)
        if code == _EXT_ENUM:
            name, value = self.unpack(data)
            return _resolve(name)(value)
        if code == _EXT_RNG:
            slot = len(self._objs)
            self._objs.append(None)
            name, state = self.unpack(data)
            bg_cls = getattr(np.random, name, None)
            if not (isinstance(bg_cls, type) and issubclass(bg_cls, np.random.BitGenerator)):
                raise StateError(f"unknown bit generator {name!r}")
            bg = bg_cls()
            bg.state = state
            g = np.random.Generator(bg)
            self._objs[slot] = g
            return g
        if code == _EXT_OBJECT:
            # registered before its attributes, in the order the encoder numbered it
            slot = len(self._objs)
            self._objs.append(None)
            name, attrs = self.unpack(data)
            obj: Any = object.__new__(_resolve(name))
            for k, v in attrs.items():
                object.__setattr__(obj, k, v)
            self._objs[slot] = obj
            return obj
        raise StateError(f"unknown extension code {code} in a session state")


def dumps(tree: dict[str, Any]) -> bytes:
    """A state tree (dict of storable values) as a versioned, checksummed blob."""
    body = msgpack.packb(_Encoder().lower(tree), use_bin_type=True, strict_types=True)
    return _HEADER.pack(MAGIC, FORMAT_VERSION, zlib.crc32(body)) + body


def loads(blob: bytes) -> dict[str, Any]:
    """The tree of a blob written by ``dumps``; StateError if it is not one."""
    if len(blob) < _HEADER.size:
        raise StateError(f"session state of {len(blob)} bytes is truncated")
    magic, version, crc = _HEADER.unpack_from(blob)
    if magic != MAGIC:
        raise StateError("not a swarmloc session state (bad magic)")
    if version != FORMAT_VERSION:
        raise StateError(f"session state format {version}; this version reads "
                         f"{FORMAT_VERSION}")
    body = memoryview(blob)[_HEADER.size:]
    if zlib.crc32(body) != crc:
        raise StateError("session state checksum mismatch (corrupt)")
    try:
        tree = _Decoder().unpack(bytes(body))
    except StateError:
        raise
    except Exception as exc:  # malformed MessagePack despite a matching checksum
        raise StateError(f"unreadable session state: {exc}") from None
    if not isinstance(tree, dict):
        raise StateError("session state is not a mapping")
    return tree


def apply_object(obj: object, state: dict[str, Any], skip: frozenset[str], where: str,
                 added: frozenset[str] = frozenset()) -> None:
    """Set the stored attributes on a freshly built ``obj``; the attribute sets must agree,
    except that attributes in ``added`` may be missing (they keep the fresh value)."""
    have = set(vars(obj)) - skip
    missing = sorted(have - set(state) - added)
    extra = sorted(set(state) - have - skip)
    if missing or extra:
        raise StateError(f"{where}: stored state does not fit this version (missing "
                         f"{missing}, unknown {extra}); written by another version?")
    for k, v in state.items():
        object.__setattr__(obj, k, v)


def _localizer(route_map: RouteMap, estimator: str, params: dict[str, Any] | None, seed: int,
               localizer: dict[str, Any], state: dict[str, Any],
               added: dict[str, frozenset[str]]) -> Localizer:
    """A localizer on ``route_map`` built from its configuration, then given a session's
    state (``localizer`` and ``state``: the localizer's and the estimator's attributes, less
    ``REBUILT``); what derives from the map is the freshly built one's. ``added``: the
    attributes a state may lack (``ADDED``)."""
    loc = Localizer(route_map, estimator, params, seed)
    apply_object(loc, localizer, REBUILT["localizer"] | {"last"}, "localizer",
                 added.get("localizer", frozenset()))
    apply_object(loc.estimator, state, REBUILT["estimator"], "estimator",
                 added.get("estimator", frozenset()))
    return loc


def continued_on(loc: Localizer, route_map: RouteMap) -> Localizer:
    """``loc`` continued on ``route_map``, another version of its map that differs only by
    experiences (``service.maps.experiences.compatible``): built as ``decode_session`` builds
    a stored session loaded onto such a version, from ``loc``'s state as it is. ``loc`` is
    left to be dropped: the two share its arrays."""
    skip_loc = REBUILT["localizer"] | {"last"}
    new = _localizer(route_map, loc.estimator_name, loc.params, loc.seed,
                     {k: v for k, v in vars(loc).items() if k not in skip_loc},
                     {k: v for k, v in vars(loc.estimator).items()
                      if k not in REBUILT["estimator"]}, {})
    new.last = loc.last
    return new


# ---- one robot's session -----------------------------------------------------------------
@dataclass
class SessionState:
    """Everything of a session that is not its lock: what a store keeps per robot."""

    robot_id: str
    localizer: Localizer
    created: float
    last_used: float
    last_t: float | None = None  # timestamp of the last frame (frames must not go back)
    last_input_seq: int | None = None  # the robot's seq of the last applied frame
    learn: bool = False  # the session's confident frames teach its map (experiences)
    condition: str | None = None  # the light of its frames, as the robot gave it
    # a learning session's last two tracked frames (service/engine/learning.py
    # ``path_gate``): (estimate seq, x, y); kept here so that any replica continues the path
    learn_path: list[tuple[int, float, float]] = field(default_factory=list)


MapResolver = Callable[[str, "str | None"], RouteMap]  # (map name, checksum) -> the map


def encode_session(s: SessionState) -> bytes:
    loc = s.localizer
    skip_loc, skip_est = REBUILT["localizer"] | {"last"}, REBUILT["estimator"]
    return dumps({  # one tree, one encoder: references shared across objects stay shared
        "robot_id": s.robot_id, "created": s.created, "last_used": s.last_used,
        "last_t": s.last_t, "last_input_seq": s.last_input_seq,
        "learn": s.learn, "condition": s.condition,
        "learn_path": [[int(q), float(x), float(y)] for q, x, y in s.learn_path],
        "map": loc.map.name, "map_checksum": loc.map.meta.get("checksum"),
        "estimator_name": loc.estimator_name, "seed": loc.seed, "params": loc.params,
        "last": loc.last.model_dump(mode="python") if loc.last is not None else None,
        "localizer": {k: v for k, v in vars(loc).items() if k not in skip_loc},
        "estimator": {k: v for k, v in vars(loc.estimator).items() if k not in skip_est},
    })


def decode_session(blob: bytes, resolve_map: MapResolver) -> SessionState:
    """The session of ``blob`` on the map ``resolve_map(name, checksum)`` returns (it raises
    when that map version is not loaded)."""
    d = loads(blob)
    try:
        route_map = resolve_map(d["map"], d["map_checksum"])
        loc = _localizer(route_map, d["estimator_name"], d["params"], d["seed"],
                         d["localizer"], d["estimator"], ADDED)
        loc.last = Estimate.model_validate(d["last"]) if d["last"] is not None else None
        return SessionState(d["robot_id"], loc, d["created"], d["last_used"], d["last_t"],
                            d["last_input_seq"], bool(d.get("learn", False)),
                            d.get("condition"),
                            [(int(q), float(x), float(y))  # absent before it was kept
                             for q, x, y in d.get("learn_path") or []])
    except KeyError as exc:
        raise StateError(f"session state lacks {exc}") from None
    except (TypeError, ValueError) as exc:  # e.g. a learn_path entry that is not (seq, x, y)
        raise StateError(f"session state is malformed: {exc}") from None
