"""Map files through Redis, for replicas on several machines with a maps directory each.

With ``SWARMLOC_MAPS_SYNC=redis`` (and the Redis session store) every map file a replica
writes (an upload, a build, a learned or removed experience) is published to Redis, and every
replica takes the newest published version into its own maps directory before it answers for
that map (a session, a map request, a listing). Redis holds, per map, one hash
``{prefix}:mapfile:{name}``:

- ``version``: the published file's checksum (its ``ETag``);
- ``data``: the file's bytes (absent once deleted);
- ``deleted``: ``1`` after a delete through any replica (a tombstone: a replica that was down
  meanwhile removes its copy when it next looks, instead of publishing it again).

A publish is a compare-and-set against the version the writer started from (the one its
preconditions were checked against): two replicas on two machines that replace one map at
once never overwrite each other unnoticed; the second gets ``412``. A map that Redis does not
hold (a map directory's own file at start-up, or after Redis lost its data) is published by
the first replica that looks at it. This module does the Redis side only; the map admin
(service/engine/map_admin.py) decides when.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MAX_MIRRORED_BYTES = 512 * 1024 * 1024 - 1  # Redis's largest value (proto-max-bulk-len)

# KEYS[1] the map's hash; ARGV: expected version ('' = none published, or deleted), new
# version, data ('' with deleted = '1': a tombstone), deleted flag
_PUBLISH = """
local cur = redis.call('HGET', KEYS[1], 'version')
local gone = redis.call('HGET', KEYS[1], 'deleted') == '1'
if gone or not cur then cur = '' end
if cur ~= ARGV[1] then return 0 end
if ARGV[4] == '1' then
  redis.call('HDEL', KEYS[1], 'data')
  redis.call('HSET', KEYS[1], 'version', ARGV[2], 'deleted', '1')
else
  redis.call('HSET', KEYS[1], 'version', ARGV[2], 'data', ARGV[3], 'deleted', '0')
end
return 1
"""


@dataclass(frozen=True)
class Head:
    """What Redis holds of a map: its published version, or a tombstone."""

    version: str
    deleted: bool


class MapMirror:
    """The maps' files in Redis (module docstring)."""

    def __init__(self, r: Any, prefix: str) -> None:
        import redis

        self.errors: tuple[type[Exception], ...] = (redis.exceptions.RedisError,)
        self.r = r
        self.prefix = prefix
        self._publish = r.register_script(_PUBLISH)

    def key(self, name: str) -> str:
        return f"{self.prefix}:mapfile:{name}"

    def head(self, name: str) -> Head | None:
        """The published version of map ``name``; None where Redis holds none."""
        version, deleted = self.r.hmget(self.key(name), ["version", "deleted"])
        if version is None:
            return None
        return Head(version.decode(), deleted == b"1")

    def names(self) -> list[str]:
        """Every map Redis holds (tombstones included)."""
        start = len(self.key(""))
        return sorted(k.decode()[start:] for k in
                      self.r.scan_iter(match=self.key("*"), count=500))

    def publish(self, name: str, path: Path, version: str, expect: str | None) -> bool:
        """Publish the file ``path`` (version ``version``) if Redis still holds ``expect``
        (None: no version, or a tombstone); whether it did."""
        data = path.read_bytes()
        return bool(self._publish(keys=[self.key(name)],
                                  args=[expect or "", version, data, "0"]))

    def delete(self, name: str, expect: str | None) -> bool:
        """Leave a tombstone for map ``name`` if Redis still holds ``expect``; whether it
        did."""
        return bool(self._publish(keys=[self.key(name)],
                                  args=[expect or "", f"deleted:{expect or ''}", "", "1"]))

    def fetch(self, name: str, directory: Path, prefix: str) -> Path | None:
        """The published file of map ``name`` in a new hidden temporary file of
        ``directory`` (the caller renames or removes it); None where Redis holds none."""
        data = self.r.hget(self.key(name), "data")
        if data is None:
            return None
        fd, tmp = tempfile.mkstemp(prefix=f"{prefix}mirror-", suffix=".part", dir=directory)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o644)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return Path(tmp)
