"""The bare client (`pip install swarmloc`, no extras) in a fresh virtualenv talks to a real
server, and OpenCV, SciPy and FastAPI are not even installed there.

The virtualenv has no system site packages; pip installs the repository's wheel (built once
for the session, tests/conftest.py) with its base dependencies from the package index, reusing
pip's cache.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import venv
from pathlib import Path

PROBE = r"""
import importlib.util, json, sys
from pathlib import Path

from client.transports import AsyncHttpClient, HttpClient, SwarmlocError, connect

url, frame = sys.argv[1], Path(sys.argv[2]).read_bytes()
c = connect(url)
assert isinstance(c, HttpClient)
info = c.create_session("light", map_name="small", estimator="dpso", seed=3)
est = c.localize("light", frame, t=0.0)
try:
    c.localize("light", b"not an image", t=1.0)
    refused = None
except SwarmlocError as exc:
    refused = exc.status
c.delete_session("light")
c.close()
missing = {m: importlib.util.find_spec(m) is None for m in ("cv2", "scipy", "fastapi", "zenoh",
                                                            "matplotlib", "pyproj", "numba")}
print(json.dumps({"maps": [m.name for m in connect(url).maps()], "estimator": info.estimator,
                  "status": est.status, "comparisons": est.comparisons, "refused": refused,
                  "missing": missing, "loaded": sorted(m for m in ("cv2", "scipy", "fastapi")
                                                       if m in sys.modules)}))
"""


def _run(cmd: list[str], **kw: object) -> subprocess.CompletedProcess[str]:
    """``cmd`` in the bare virtualenv: without PYTHONPATH, so nothing of the source tree (or
    its egg-info) is seen there."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    res = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env, **kw)  # type: ignore[call-overload]
    assert res.returncode == 0, f"{cmd}\n{res.stdout}\n{res.stderr}"
    return res


def test_bare_client_install_talks_to_a_server(tmp_path: Path, wheel: Path, server, sunny2
                                               ) -> None:
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False).create(env_dir)
    bindir = env_dir / ("Scripts" if sys.platform == "win32" else "bin")
    py = bindir / "python"
    _run([str(py), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
          str(wheel)], cwd=tmp_path)

    res = _run([str(py), "-c", PROBE, server["url"], str(sunny2.image_path(5))], cwd=tmp_path)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["maps"] == ["small"] and out["estimator"] == "dpso"
    assert out["status"] in ("initializing", "tracking") and out["comparisons"] > 0
    assert out["refused"] == 400  # the service's own answer to a broken frame
    assert all(out["missing"].values()), out["missing"]
    assert out["loaded"] == []

    # the CLI of the light install: help, and a replay with its report (no plots: no lab)
    _run([str(bindir / "swarmloc"), "--help"], cwd=tmp_path)
    _run([str(bindir / "swarmloc"), "replay", str(sunny2.path), "--map", "small", "--via",
          server["url"], "--length", "6", "--out", str(tmp_path / "report")], cwd=tmp_path)
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["summary"]["runs"] == 1 and report["runs"][0]["metrics"]["frames"] == 6
    assert (tmp_path / "report" / "report.html").is_file()
    assert not (tmp_path / "report" / "route.png").exists()
