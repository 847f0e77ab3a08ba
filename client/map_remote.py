"""Remote map builds: pack a round as a zip and follow the service's build job."""

from __future__ import annotations

import time
import zipfile
from collections.abc import Callable
from pathlib import Path

from client.dataset import (
    CALIB_FILE,
    DATASET_FILE,
    ODOMETRY_FILE,
    POSES_FILE,
    TRUTH_FILE,
    read_round,
)
from client.transports import HttpClient, SwarmlocError
from service.api.models import JobInfo

_STORED = (".png", ".jpg", ".jpeg")  # already compressed


def zip_round(round_dir: str | Path, out: str | Path, odometry: bool = True) -> Path:
    """Write ``out`` (a zip): ``ROUND/poses.csv`` (+ truth.csv, calib.txt and, with
    ``odometry``, odometry.csv: the service fuses the map's positions with it), the images it
    names, and the dataset's ``dataset.json`` (its geodetic origin and camera) at the top.
    The round is validated first."""
    rnd = read_round(round_dir)
    out = Path(out)
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        meta = rnd.path.parent / DATASET_FILE
        if meta.is_file():
            zf.write(meta, DATASET_FILE)
        for extra in (POSES_FILE, TRUTH_FILE, CALIB_FILE) + ((ODOMETRY_FILE,) if odometry else ()):
            if (rnd.path / extra).is_file():
                zf.write(rnd.path / extra, f"{rnd.name}/{extra}")
        for name in rnd.images:
            kind = zipfile.ZIP_STORED if name.lower().endswith(_STORED) else zipfile.ZIP_DEFLATED
            zf.write(rnd.path / name, f"{rnd.name}/{name}", compress_type=kind)
    return out


def follow_job(client: HttpClient, job: JobInfo, on_progress: Callable[[JobInfo], None],
               poll_s: float = 0.5, timeout_s: float = 3600.0) -> JobInfo:
    """Poll ``GET /jobs/{id}`` until the job is done or failed; report every poll."""
    deadline = time.monotonic() + timeout_s
    while True:
        on_progress(job)
        if job.state in ("done", "failed"):
            return job
        if time.monotonic() > deadline:
            raise SwarmlocError(0, f"job {job.id} still {job.state} after {timeout_s:g} s")
        time.sleep(poll_s)
        job = client.job(job.id)
