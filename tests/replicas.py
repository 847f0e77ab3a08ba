"""Checks shared by the replica tests (tests/test_scale_out.py, tests/test_map_mirror.py)."""

from __future__ import annotations

import httpx


def upload_served_by_the_other(a: str, b: str, name: str, data: bytes, robot: str,
                               frame: bytes, seed: int) -> str:
    """Upload map file ``data`` as ``name`` through replica ``a`` (a new map: If-None-Match
    *), then check that replica ``b`` serves it without a restart: the same ETag, listed, and
    a robot's session there localizes ``frame`` on it. Returns the ETag."""
    r = httpx.put(f"{a}/maps/{name}", content=data, timeout=60,
                  headers={"content-type": "application/octet-stream", "if-none-match": "*"})
    assert r.status_code == 201, r.text
    got = httpx.get(f"{b}/maps/{name}", timeout=30)
    assert got.status_code == 200 and got.headers["ETag"] == r.headers["ETag"]
    assert name in [m["name"] for m in httpx.get(f"{b}/maps", timeout=30).json()]
    s = httpx.put(f"{b}/sessions/{robot}", timeout=30, json={"map": name, "seed": seed})
    assert s.status_code == 201, s.text
    est = httpx.post(f"{b}/sessions/{robot}/frames", params={"t": 0.0, "seq": 0},
                     content=frame, headers={"Content-Type": "image/png"}, timeout=60)
    assert est.status_code == 200 and est.json()["frame_id"] == name, est.text
    return str(r.headers["ETag"])
