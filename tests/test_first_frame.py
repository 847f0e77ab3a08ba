"""The first frame costs what a later one does: every matcher kernel is compiled (or loaded
from its cache directory) before the service reports ready, and nothing is written into the
installed package, which may be read-only (a container).

Timings are printed by ``swarmloc bench first-frame``; these tests assert behaviour only."""

from __future__ import annotations

import shutil
from pathlib import Path

import numba
import numpy as np

from client.lab.processes import ServiceProcess
from client.transports import HttpClient
from service.engine.localizer import Localizer
from service.maps.route_map import save_map
from service.server import free_port
from service.vision.matcher import cache_kernels_in, compiled_signatures, warm_up

ROOT = Path(__file__).resolve().parent.parent


def test_warm_up_compiles_every_signature_a_step_meets(small_map, sunny2) -> None:
    """After ``warm_up`` a step on a map loaded from disk (read-only memory-mapped codes)
    compiles nothing more: the first frame pays no compilation."""
    warm_up()
    before = compiled_signatures()
    loc = Localizer(small_map, "dpso", {}, 0)
    for i in range(3):
        loc.step(loc.extract(sunny2.load_image(i)), float(i))
    assert compiled_signatures() == before


def _add_one(x):  # a kernel for the cache test (numba caches functions with a source file)
    return x + 1


def test_kernels_cache_in_the_given_directory_or_compile_without_one(tmp_path: Path) -> None:
    kernel = numba.njit(nogil=True)(_add_one)
    assert cache_kernels_in(tmp_path / "cache", [kernel]) == tmp_path / "cache"
    assert kernel(41) == 42
    assert list((tmp_path / "cache").rglob("*.nbi")), "no cache index written"
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    fresh = numba.njit(nogil=True)(_add_one)
    assert cache_kernels_in(blocker / "cache", [fresh]) is None  # cannot be created
    assert fresh(1) == 2  # compiled in the process, uncached


def test_server_serves_from_a_package_copy_with_an_unwritable_cache_dir(
        tmp_path: Path, small_map, sunny2) -> None:
    """``swarmloc serve`` run from a copy of the package, with a cache directory that cannot
    be created: it says so in its banner, serves frames, and writes nothing into the copy."""
    pkg = tmp_path / "pkg"
    for name in ("service", "client"):
        shutil.copytree(ROOT / name, pkg / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    marker = tmp_path / "imported-the-copy"  # the copy's package writes it when imported
    init = pkg / "service" / "__init__.py"
    init.write_text(init.read_text() + f"\nopen({str(marker)!r}, 'w').close()\n")
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    maps = tmp_path / "maps"
    save_map(small_map, maps / "small")
    proc = ServiceProcess("first-frame", {
        "PYTHONPATH": str(pkg), "SWARMLOC_MAPS_DIR": str(maps),
        "SWARMLOC_NUMBA_CACHE_DIR": str(blocker / "numba"),
        "SWARMLOC_ZENOH_LISTEN": f'["tcp/127.0.0.1:{free_port()}"]',
        "SWARMLOC_SESSION_STORE": "memory"}, tmp_path)
    try:
        proc.start().wait_ready(timeout_s=300)
        log = proc.log_tail(20_000)
        client = HttpClient(proc.url, timeout=120)
        try:
            client.create_session("r1", "small")
            estimates = [client.localize("r1", sunny2.load_image(i), t=float(i))
                         for i in range(2)]
        finally:
            client.close()
    finally:
        proc.stop()
    assert "kernels" in log and "compiled at each start" in log and "not writable" in log, log
    assert "exact GEMM" in log and "XFeat's" in log, log  # the faster of NumKong and BLAS,
    # measured at start-up for each code type
    assert all(np.isfinite(e.x) for e in estimates)
    assert marker.exists(), "the server did not run from the package copy"
    written = [p for p in pkg.rglob("*") if p.suffix in (".nbi", ".nbc")]
    assert not written, f"numba cache written into the package: {written[:3]}"
