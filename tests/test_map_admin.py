"""Map lifecycle on a real server (uvicorn + Zenoh on loopback): upload, build, replace,
delete, preconditions, a robot streaming through a replacement, and every bad upload."""

from __future__ import annotations

import io
import shutil
import tarfile
import threading
import time
import zipfile
from pathlib import Path
from types import SimpleNamespace

import httpx
import numpy as np
import pytest
from typer.testing import CliRunner

from client.cli import app as cli_app
from client.dataset import write_odometry, write_round
from client.map_remote import zip_round
from client.transports import HttpClient, SwarmlocError, ZenohClient
from service.api.models import JobInfo
from service.engine.localization_service import LocalizationService
from service.maps.route_map import build_map, save_map
from service.server import free_port, running_server
from service.settings import Settings
from service.vision.xfeat import XFeatParams


def _start(tmp: Path, small_map, zenoh: bool = True, **kw):
    maps = tmp / "maps"
    maps.mkdir()
    save_map(small_map, maps / "small")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(),
                        zenoh_enabled=zenoh, zenoh_listen=[endpoint],
                        zenoh_multicast_scouting=False, workers=4, **kw)
    service = LocalizationService(settings)
    return service, endpoint, maps


@pytest.fixture(scope="module")
def srv(tmp_path_factory: pytest.TempPathFactory, small_map):
    service, endpoint, maps = _start(tmp_path_factory.mktemp("admin"), small_map,
                                     max_archive_members=400)
    with running_server(service) as url:
        http = HttpClient(url)
        yield SimpleNamespace(url=url, zenoh=endpoint, maps=maps, service=service, http=http)
        http.close()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory, small_map):
    """A server with small upload limits (oversize bodies, member counts)."""
    service, _, maps = _start(tmp_path_factory.mktemp("tiny"), small_map, zenoh=False,
                              max_map_bytes=4096, max_archive_bytes=4096,
                              max_archive_members=3)
    with running_server(service, zenoh=False) as url:
        yield SimpleNamespace(url=url, maps=maps, service=service)


@pytest.fixture(scope="module")
def map_files(tmp_path_factory: pytest.TempPathFactory, sunny1) -> dict[str, Path]:
    """Two versions of map 'alt' (40 and 60 images of sunny1), outside the maps dir."""
    out = tmp_path_factory.mktemp("map_files")
    files = {}
    for key, n in (("v1", 40), ("v2", 60)):
        m = build_map("alt", [sunny1.load_image(i) for i in range(n)], sunny1.xy[:n],
                      list(sunny1.images[:n]))
        files[key] = save_map(m, out / key / "alt")
    return files


@pytest.fixture(scope="module")
def small_round(tmp_path_factory: pytest.TempPathFactory, sunny2) -> Path:
    """The first 20 images of sunny2 as a round directory."""
    d = tmp_path_factory.mktemp("rounds") / "part"
    d.mkdir()
    for name in sunny2.images[:20]:
        shutil.copy(sunny2.path / name, d / name)
    write_round(d, sunny2.images[:20], sunny2.xy[:20], sunny2.t[:20])
    return d


def _etag(r: httpx.Response) -> str:
    return r.headers["etag"].strip('"')


def _put(url: str, name: str, data: bytes, **headers: str) -> httpx.Response:
    return httpx.put(f"{url}/maps/{name}", content=data, timeout=60,
                     headers={"content-type": "application/octet-stream", **headers})


def _wait(http: HttpClient, job_id: str, timeout_s: float = 120) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = http.job(job_id)
        if job.state in ("done", "failed"):
            return job.model_dump()
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish")


def test_upload_replace_preconditions_and_download(srv, map_files, sunny1) -> None:
    v1, v2 = map_files["v1"].read_bytes(), map_files["v2"].read_bytes()
    r = _put(srv.url, "alt", v1, **{"if-none-match": "*"})
    assert r.status_code == 201, r.text
    etag1 = _etag(r)
    assert r.json()["checksum"] == etag1 and r.json()["n_images"] == 40
    assert (srv.maps / "alt.swmap").read_bytes() == v1
    got = httpx.get(f"{srv.url}/maps/alt")
    assert _etag(got) == etag1 and got.json()["build_date"]
    assert "alt" in httpx.get(f"{srv.url}/readyz").json()["maps"]
    # a second create loses: the map exists
    r = _put(srv.url, "alt", v2, **{"if-none-match": "*"})
    assert r.status_code == 412 and "already exists" in r.json()["error"]
    # a replace based on a stale version loses too
    r = _put(srv.url, "alt", v2, **{"if-match": '"0123"'})
    assert r.status_code == 412 and etag1 in r.json()["error"]
    assert (srv.maps / "alt.swmap").read_bytes() == v1
    # the right version wins: 200 replaced, a new ETag
    r = _put(srv.url, "alt", v2, **{"if-match": f'"{etag1}"'})
    assert r.status_code == 200 and r.json()["n_images"] == 60
    etag2 = _etag(r)
    assert etag2 != etag1 and (srv.maps / "alt.swmap").read_bytes() == v2
    # the stored name must be the URL's
    r = _put(srv.url, "other", v2)
    assert r.status_code == 422 and "named 'alt'" in r.json()["error"]
    # download: the current version's bytes, 304 when the client has it
    f = httpx.get(f"{srv.url}/maps/alt/file")
    assert f.content == v2 and _etag(f) == etag2
    assert httpx.get(f"{srv.url}/maps/alt/file",
                     headers={"if-none-match": f'"{etag2}"'}).status_code == 304
    # a session on the uploaded map localizes
    srv.http.create_session("up-bot", "alt")
    est = srv.http.localize("up-bot", sunny1.image_path(5).read_bytes(), t=0.0)
    assert est.frame_id == "alt"
    srv.http.delete_session("up-bot")
    assert srv.http.delete_map("alt").ended_sessions == []
    assert not (srv.maps / "alt.swmap").exists()


def test_streaming_robot_keeps_its_version_until_reset(srv, map_files, sunny1) -> None:
    v1, v2 = map_files["v1"], map_files["v2"]
    etag1 = _etag(_put(srv.url, "alt", v1.read_bytes()))
    srv.http.create_session("streamer", "alt", seed=1)
    errors: list[str] = []
    done: list[int] = []
    replaced = threading.Event()
    after = [0]

    def stream() -> None:
        c = HttpClient(srv.url)
        try:
            for k in range(200):
                try:
                    c.localize("streamer", sunny1.image_path(k % 40).read_bytes(), t=float(k))
                except SwarmlocError as exc:
                    errors.append(str(exc))
                done.append(k)
                if replaced.is_set():
                    after[0] += 1
                    if after[0] >= 10:
                        return
        finally:
            c.close()

    t = threading.Thread(target=stream)
    t.start()
    while len(done) < 5:
        time.sleep(0.01)
    r = _put(srv.url, "alt", v2.read_bytes(), **{"if-match": f'"{etag1}"'})
    replaced.set()
    t.join(120)
    assert r.status_code == 200 and not errors and after[0] >= 10
    etag2 = _etag(r)
    info = srv.http.session("streamer")
    assert info.map_checksum == etag1 and info.frames == len(done)  # still the old version
    srv.http.create_session("newcomer", "alt")
    assert srv.http.session("newcomer").map_checksum == etag2  # new sessions: new version
    # reset moves the robot onto the current version
    assert srv.http.reset("streamer").map_checksum == etag2
    est = srv.http.localize("streamer", sunny1.image_path(50).read_bytes(), t=1000.0)
    assert est.frame_id == "alt" and est.nearest_image < 60
    # delete: refused while sessions use it, naming them; force ends them
    r = httpx.delete(f"{srv.url}/maps/alt")
    assert r.status_code == 409
    assert "newcomer" in r.json()["error"] and "streamer" in r.json()["error"]
    assert "alt" in srv.service.maps
    r = httpx.delete(f"{srv.url}/maps/alt", params={"force": "true"})
    assert r.status_code == 200 and r.json()["ended_sessions"] == ["newcomer", "streamer"]
    assert httpx.get(f"{srv.url}/sessions/streamer").status_code == 404
    assert httpx.get(f"{srv.url}/maps/alt").status_code == 404
    assert httpx.delete(f"{srv.url}/maps/alt").status_code == 404


def test_build_job_progress_and_map_appears_complete(srv, small_round, sunny2) -> None:
    archive = zip_round(small_round, small_round.parent / "part.zip")
    r = httpx.post(f"{srv.url}/maps/built/build", content=archive.read_bytes(),
                   headers={"content-type": "application/zip"}, timeout=60)
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/jobs/{job['id']}" and job["total"] == 20
    assert job["state"] in ("queued", "running", "done")
    seen = []
    while job["state"] not in ("done", "failed"):
        if job["state"] != "done":
            # never half-built: either absent, or complete with every image
            m = httpx.get(f"{srv.url}/maps/built")
            assert m.status_code == 404 or m.json()["n_images"] == 20, m.text
        seen.append(job["done"])
        time.sleep(0.05)
        job = srv.http.job(job["id"]).model_dump()
    assert job["state"] == "done", job
    assert job["done"] == job["total"] == 20 and seen == sorted(seen)
    assert job["features"] == "clahe-rootsift+xfeat"  # the default build: both types
    assert (job["max_features"], job["width"], job["height"]) == (2048, 320, 240)  # defaults
    detail = httpx.get(f"{srv.url}/maps/built").json()
    assert detail["checksum"] == job["checksum"] and detail["n_images"] == 20
    assert detail["meta"]["source"]["name"] == "part"
    assert np.allclose(detail["positions"], sunny2.xy[:20])
    assert (srv.maps / "built.swmap").is_file()
    assert job["id"] in [j.id for j in srv.http.jobs()]
    srv.http.create_session("builder-bot", "built")
    est = srv.http.localize("builder-bot", sunny2.image_path(10).read_bytes(), t=0.0)
    assert est.frame_id == "built"
    srv.http.delete_map("built", force=True)
    assert not list(srv.maps.glob(".swarmloc-*"))  # the extracted round is gone


def test_a_round_uploaded_with_its_odometry_gets_fused_positions(srv, small_round,
                                                                  sunny2) -> None:
    """The service aligns an uploaded round's odometry.csv to its poses (as ``map build``
    does); ``build-remote --positions recorded`` leaves the file out and keeps the poses."""
    rnd = small_round.parent / "part-odom"
    shutil.copytree(small_round, rnd)
    write_odometry(rnd, sunny2.images[:20], sunny2.odometry[:20])
    built = {}
    for rule in ("fused", "recorded"):
        archive = zip_round(rnd, rnd.parent / f"odom-{rule}.zip", odometry=rule == "fused")
        assert ("part-odom/odometry.csv" in zipfile.ZipFile(archive).namelist()) is (
            rule == "fused")
        job = srv.http.build_map_remote(f"odom-{rule}", archive)
        assert _finished(srv, job).state == "done"
        built[rule] = httpx.get(f"{srv.url}/maps/odom-{rule}").json()
        srv.http.delete_map(f"odom-{rule}", force=True)
    assert built["fused"]["meta"]["source"]["positions"][0].startswith("fused with odometry")
    assert not np.allclose(built["fused"]["positions"], sunny2.xy[:20])
    assert built["recorded"]["meta"]["source"]["positions"] == ["recorded"]
    assert np.allclose(built["recorded"]["positions"], sunny2.xy[:20])


def _finished(srv, job: JobInfo, timeout_s: float = 240) -> JobInfo:
    """The build job once it is done (asserted), polled over HTTP."""
    deadline = time.monotonic() + timeout_s
    while job.state not in ("done", "failed") and time.monotonic() < deadline:
        time.sleep(0.1)
        job = srv.http.job(job.id)
    assert job.state == "done", job
    return job


def test_a_build_makes_the_feature_type_asked_for(srv, small_round, sunny2) -> None:
    archive = zip_round(small_round, small_round.parent / "part-x.zip")
    r = httpx.post(f"{srv.url}/maps/xbuilt/build", content=archive.read_bytes(),
                   params={"features": "surf"}, headers={"content-type": "application/zip"})
    assert r.status_code == 422 and "features" in r.text  # refused before anything is staged
    assert httpx.get(f"{srv.url}/maps/xbuilt").status_code == 404
    job = srv.http.build_map_remote("xbuilt", archive, features="xfeat")
    assert job.features == "xfeat"
    job = _finished(srv, job)
    m = srv.service.get_map("xbuilt")
    assert isinstance(m.feature_params, XFeatParams)
    srv.http.create_session("xfeat-bot", "xbuilt")
    est = srv.http.localize("xfeat-bot", sunny2.image_path(10).read_bytes(), t=0.0)
    assert est.frame_id == "xbuilt"
    srv.http.delete_map("xbuilt", force=True)


def test_a_build_keeps_the_sift_features_and_the_size_asked_for(srv, small_round) -> None:
    """``?max_features=N``: the built map's images hold at most N RootSIFT features (OpenCV
    keeps the N strongest and their ties) and its frames are extracted alike;
    ``?width=&height=``: its working size. A cap on XFeat alone, or a cap or size out of
    range, is refused before anything is built."""
    archive = zip_round(small_round, small_round.parent / "part-cap.zip")
    body, zipped = archive.read_bytes(), {"content-type": "application/zip"}
    r = httpx.post(f"{srv.url}/maps/capped/build", content=body, headers=zipped,
                   params={"features": "xfeat", "max_features": 60}, timeout=60)
    assert r.status_code == 400 and "XFeat keeps its own" in r.text, r.text
    for bad in ({"max_features": -1}, {"width": 10}, {"height": 5000}):
        r = httpx.post(f"{srv.url}/maps/capped/build", content=body, headers=zipped,
                       params=bad, timeout=60)
        assert r.status_code == 422 and next(iter(bad)) in r.text, r.text
    assert httpx.get(f"{srv.url}/maps/capped").status_code == 404
    assert not list(srv.maps.glob(".swarmloc-*"))  # nothing staged is left
    job = srv.http.build_map_remote("capped", archive, features="clahe-rootsift",
                                    max_features=60, width=256, height=192)
    assert job.max_features == 60 and (job.width, job.height) == (256, 192)
    job = _finished(srv, job)
    m = srv.service.get_map("capped")
    counts = np.diff(m.offsets)
    assert m.feature_params.n_features == 60 and np.all((counts >= 60) & (counts <= 64))
    assert (m.feature_params.width, m.feature_params.height) == (256, 192)
    assert httpx.get(f"{srv.url}/maps/capped").json()["meta"]["matcher"] == "exact"
    srv.http.delete_map("capped", force=True)


def test_build_fails_cleanly_when_the_map_changed_meanwhile(srv, map_files, small_round
                                                            ) -> None:
    etag1 = _etag(_put(srv.url, "alt", map_files["v1"].read_bytes()))
    archive = zip_round(small_round, small_round.parent / "part2.zip").read_bytes()
    first = srv.http.build_map_remote("slow", archive)  # occupies the one build worker
    second = httpx.post(f"{srv.url}/maps/alt/build", content=archive, timeout=60,
                        headers={"if-match": f'"{etag1}"'}).json()
    etag2 = _etag(_put(srv.url, "alt", map_files["v2"].read_bytes()))  # while it waits
    assert _wait(srv.http, first.id)["state"] == "done"
    job = _wait(srv.http, second["id"])
    assert job["state"] == "failed" and job["status"] == 412 and "If-Match" in job["error"]
    assert srv.http.map_detail("alt").checksum == etag2  # the newer upload was kept
    for name in ("alt", "slow"):
        srv.http.delete_map(name, force=True)


# ---- bad uploads: a clear 4xx; maps dir, loaded maps untouched; no temp file left ----------
def _zip(entries: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _tar_with_symlink() -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        poses = b"image,x,y\na.png,0,0\n"
        info = tarfile.TarInfo("r/poses.csv")
        info.size = len(poses)
        tf.addfile(info, io.BytesIO(poses))
        link = tarfile.TarInfo("r/a.png")
        link.type, link.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tf.addfile(link)
    return buf.getvalue()


def _bad_inputs(map_bytes: bytes, png: bytes) -> list[tuple[str, str, bytes, int, str]]:
    corrupt = bytearray(map_bytes)
    corrupt[-100] ^= 0xFF
    poses = b"image,x,y\na.png,0,0\nb.png,1,0\n"
    return [
        ("map", "truncated", map_bytes[: len(map_bytes) // 2], 400, "truncated"),
        ("map", "corrupt", bytes(corrupt), 400, "checksum mismatch"),
        ("map", "wrong magic", b"NOTAMAP!" + map_bytes[8:], 400, "bad magic"),
        ("map", "empty", b"", 400, "empty body"),
        ("archive", "not an archive", b"hello" * 100, 400, "neither a zip nor a tar"),
        ("archive", "dot-dot", _zip({"r/poses.csv": poses, "../evil.png": png}), 400,
         "contains '..'"),
        ("archive", "absolute", _zip({"/tmp/evil.png": png, "poses.csv": poses}), 400,
         "absolute path"),
        ("archive", "symlink", _tar_with_symlink(), 400, "is a link"),
        ("archive", "zip bomb", _zip({"poses.csv": poses, "a.png": bytes(30 << 20)}), 413,
         "zip bomb"),
        ("archive", "no poses.csv", _zip({"r/a.png": png, "r/b.png": png}), 422,
         "no poses.csv"),
        ("archive", "unreadable image",
         _zip({"r/poses.csv": poses, "r/a.png": png, "r/b.png": png[:60]}), 422,
         "line 3: image 'b.png' is unreadable"),
        ("archive", "image outside", _zip({"r/poses.csv": b"image,x,y\n../../x.png,0,0\n"}),
         422, "outside the round"),
        ("archive", "bad poses", _zip({"r/poses.csv": b"image,x,y\na.png,zero,0\n",
                                       "r/a.png": png}), 422, "line 2: x='zero'"),
    ]


def _state(s) -> tuple:
    files = sorted(p.name for p in s.maps.iterdir())
    maps = sorted((m["name"], m["checksum"]) for m in httpx.get(f"{s.url}/maps").json())
    return files, maps


def test_every_bad_upload_is_refused_cleanly(srv, map_files, sunny1) -> None:
    before = _state(srv)
    bad = _bad_inputs(map_files["v1"].read_bytes(), sunny1.image_path(0).read_bytes())
    for kind, label, body, status, message in bad:
        if kind == "map":
            r = _put(srv.url, "alt", body)
        else:
            r = httpx.post(f"{srv.url}/maps/fresh/build", content=body, timeout=60)
        assert r.status_code == status, (label, r.text)
        assert message in r.json()["error"], (label, r.json())
        assert _state(srv) == before, label  # nothing new, nothing half-written
    assert not [j for j in srv.http.jobs() if j.map == "fresh"]


def test_limits_oversize_bodies_and_member_counts(tiny, map_files, sunny1) -> None:
    before = _state(tiny)
    big = map_files["v1"].read_bytes()
    r = _put(tiny.url, "alt", big)  # declared Content-Length over the limit
    assert r.status_code == 413 and "limit is 4096 bytes" in r.json()["error"]

    def chunks():  # no Content-Length: the streamed size is counted
        for i in range(0, len(big), 1000):
            yield big[i:i + 1000]

    r = httpx.put(f"{tiny.url}/maps/alt", content=chunks(), timeout=60)
    assert r.status_code == 413 and "over the limit of 4096" in r.json()["error"]
    png = sunny1.image_path(0).read_bytes()[:1000]
    many = _zip({f"r/{i}.png": png[:10] for i in range(5)})
    r = httpx.post(f"{tiny.url}/maps/x/build", content=many, timeout=60)
    assert r.status_code == 413 and "more than 3 members" in r.json()["error"]
    r = _put(tiny.url, "alt", b"x", **{"content-type": "text/plain"})
    assert r.status_code == 415
    r = _put(tiny.url, "bad name!", b"x")
    assert r.status_code == 422 and "map name" in r.json()["error"]
    assert _state(tiny) == before
    text = httpx.get(f"{tiny.url}/metrics").text
    assert 'swarmloc_map_uploads_total{result="rejected"}' in text


def test_zenoh_map_operations_match_http(srv, map_files, small_round) -> None:
    z = ZenohClient([srv.zenoh], mode="peer")
    try:
        summary, created = z.push_map(map_files["v1"], "alt")
        assert created and summary.n_images == 40
        assert z.map_info("alt").checksum == summary.checksum
        with pytest.raises(SwarmlocError) as ez:
            z.push_map(map_files["v2"], "alt", if_none_match="*")
        with pytest.raises(SwarmlocError) as eh:
            srv.http.push_map(map_files["v2"], "alt", if_none_match="*")
        assert ez.value.status == eh.value.status == 412
        assert ez.value.message == eh.value.message
        truncated = small_round.parent / "trunc.swmap"
        truncated.write_bytes(map_files["v1"].read_bytes()[:5000])
        with pytest.raises(SwarmlocError) as ez:
            z.push_map(truncated, "alt")
        assert ez.value.status == 400 and "truncated" in ez.value.message
        z.create_session("zbot", "alt")
        with pytest.raises(SwarmlocError) as ez:
            z.delete_map("alt")
        with pytest.raises(SwarmlocError) as eh:
            srv.http.delete_map("alt")
        assert ez.value.status == eh.value.status == 409 and ez.value.message == eh.value.message
        assert z.delete_map("alt", force=True).ended_sessions == ["zbot"]
        buf = io.BytesIO()  # a .tar.gz this time
        with tarfile.open(fileobj=buf, mode="w:gz") as tf:
            tf.add(small_round, arcname="part")
        with pytest.raises(SwarmlocError) as ez:
            z.build_map_remote("zbad", buf.getvalue(), features="surf")
        assert ez.value.status == 400 and "xfeat" in ez.value.message
        with pytest.raises(SwarmlocError) as ez:  # a size out of range, as over HTTP
            z.build_map_remote("zbad", buf.getvalue(), width=8)
        assert ez.value.status == 400 and "working size" in ez.value.message
        job = z.build_map_remote("zbuilt", buf.getvalue(), max_features=80, width=288,
                                 height=216)
        assert (job.max_features, job.width, job.height) == (80, 288, 216)
        deadline = time.monotonic() + 120
        while job.state not in ("done", "failed") and time.monotonic() < deadline:
            time.sleep(0.1)
            job = z.job(job.id)
        assert job.state == "done" and z.map_info("zbuilt").checksum == job.checksum
        assert job.done == job.total == 20
        p = srv.service.get_map("zbuilt").feature_params
        assert (p.width, p.height, p.sift.n_features) == (288, 216, 80)  # the default type
        with pytest.raises(SwarmlocError) as ez:
            z.job("nope")
        assert ez.value.status == 404
        z.delete_map("zbuilt")
    finally:
        z.close()


def test_cli_push_pull_build_remote(srv, map_files, small_round, tmp_path: Path) -> None:
    runner = CliRunner()
    r = runner.invoke(cli_app, ["map", "push", str(map_files["v1"]), "--to", srv.url, "--new"])
    assert r.exit_code == 0, r.output
    assert "created map 'alt'" in r.output
    r = runner.invoke(cli_app, ["map", "push", str(map_files["v2"]), "--to", srv.url, "--new"])
    assert r.exit_code == 2 and "412" in r.output
    r = runner.invoke(cli_app, ["map", "pull", "alt", "--from", srv.url, "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "alt.swmap").read_bytes() == map_files["v1"].read_bytes()
    r = runner.invoke(cli_app, ["map", "build-remote", str(small_round), "--to", srv.url,
                                "--name", "clibuilt"])
    assert r.exit_code == 0, r.output
    assert "built map 'clibuilt'" in r.output and "20 images" in r.output
    r = runner.invoke(cli_app, ["map", "delete", "clibuilt", "--at", srv.url])
    assert r.exit_code == 0 and "deleted map 'clibuilt'" in r.output
    srv.http.delete_map("alt", force=True)
    text = httpx.get(f"{srv.url}/metrics").text
    for series in ('swarmloc_map_uploads_total{result="created"}',
                   'swarmloc_map_builds_total{result="done"}',
                   'swarmloc_map_loads_total{result="ok",source="build"}',
                   "swarmloc_map_deletes_total"):
        assert series in text, series


def test_stale_temporaries_go_and_other_maps_files_stay(tmp_path: Path, small_map) -> None:
    import dataclasses
    import os

    from service.api.errors import Conflict

    maps = tmp_path / "maps"
    maps.mkdir()
    save_map(small_map, maps / "x")  # x.swmap holds the map named "small"
    old = maps / ".swarmloc-upload-1.part"
    old.write_bytes(b"left by a crash")
    os.utime(old, (time.time() - 2 * 86400,) * 2)
    (maps / ".swarmloc-build-2").mkdir()
    (maps / ".swarmloc-build-2" / "poses.csv").write_text("image,x,y\n")
    os.utime(maps / ".swarmloc-build-2", (time.time() - 2 * 86400,) * 2)
    fresh = maps / ".swarmloc-upload-3.part"  # another service's upload in progress
    fresh.write_bytes(b"busy")
    service = LocalizationService(Settings(maps_dir=maps, zenoh_enabled=False))
    assert sorted(p.name for p in maps.iterdir()) == [fresh.name, "x.swmap"]
    named_x = save_map(dataclasses.replace(small_map, name="x"), tmp_path / "up" / "x")
    staged = service.admin.staging_file("upload")
    staged.write_bytes(named_x.read_bytes())
    with pytest.raises(Conflict, match=r"x\.swmap holds the loaded map 'small'"):
        service.admin.install_upload("x", staged)
    assert not staged.exists() and service.maps["small"].path == maps / "x.swmap"


def test_a_map_write_killed_midway_leaves_the_map_and_no_lasting_temporary(
        tmp_path: Path, small_map) -> None:
    """Regression: a process killed (kill -9) while it wrote a map version (an experience, a
    build's save) left its temporary file (as big as the map) in the maps directory, and no
    service ever removed it. The map file is untouched; the temporary goes once it is old
    (a fresh one may be another service's write in progress)."""
    import os
    import signal
    import subprocess
    import sys

    maps = tmp_path / "maps"
    maps.mkdir()
    path = save_map(small_map, maps / "small")
    version = small_map.meta["checksum"]
    script = (  # writes the map again, and is killed after its first image
        "import sys, time\n"
        "import numpy as np\n"
        "from service.maps.route_map import load_map, write_map\n"
        "m = load_map(sys.argv[1])\n"
        "counts = np.diff(m.offsets)\n"
        "def chunks():\n"
        "    yield m.codes[: counts[0]], m.keypoints[: counts[0]], counts[:1]\n"
        "    print('writing', flush=True)\n"
        "    time.sleep(60)\n"
        "write_map(m.path, m.name, m.meta, m.positions, m.image_names, m.layers, counts,\n"
        "          chunks(), m.place_index)\n")
    root = Path(__file__).resolve().parent.parent
    proc = subprocess.Popen([sys.executable, "-c", script, str(path)], cwd=root, text=True,
                            stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(root)})
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "writing"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    (left,) = [p for p in maps.iterdir() if p != path]
    assert left.stat().st_size > 0
    service = LocalizationService(Settings(maps_dir=maps, zenoh_enabled=False))
    assert service.get_map("small").meta["checksum"] == version  # the map as it was
    assert left.exists()  # fresh: maybe a write in progress
    service.close()
    os.utime(left, (time.time() - 2 * 86400,) * 2)
    service = LocalizationService(Settings(maps_dir=maps, zenoh_enabled=False))
    assert sorted(p.name for p in maps.iterdir()) == ["small.swmap"]
    service.close()


def test_services_on_one_maps_directory_follow_each_others_maps(tmp_path: Path, small_map,
                                                                map_files, caplog) -> None:
    """Two services on one maps directory (replicas): a map uploaded through one is served by
    the other; a replace through one is the version the other's preconditions see (no lost
    update); a delete through one ends it on the other; a half-copied file is left out of
    listings, logged once, and served once it is whole."""
    import dataclasses
    import logging

    from service.api.errors import NotFound, PreconditionFailed
    from service.api.models import SessionConfig

    maps = tmp_path / "maps"
    maps.mkdir()
    save_map(small_map, maps / "small")
    a, b = (LocalizationService(Settings(maps_dir=maps, zenoh_enabled=False,
                                         warm_geometry=False)) for _ in range(2))

    def upload(svc: LocalizationService, key: str, **pre: str | None) -> str:
        staged = svc.admin.staging_file("upload")
        staged.write_bytes(map_files[key].read_bytes())
        return svc.admin.install_upload("alt", staged, **pre)[0].checksum or ""

    assert [s.name for s in b.map_summaries()] == ["small"]
    etag1 = upload(a, "v1", if_none_match="*")
    assert b.map_summary("alt").checksum == etag1  # B serves what A uploaded
    assert [s.name for s in b.map_summaries()] == ["alt", "small"]
    with pytest.raises(PreconditionFailed, match="already exists"):
        upload(b, "v1", if_none_match="*")  # B knows it exists on disk
    etag2 = upload(a, "v2", if_match=etag1)
    with pytest.raises(PreconditionFailed, match=f"at version {etag2}"):
        upload(b, "v1", if_match=etag1)  # before: B checked its own v1 and overwrote v2
    info, _ = b.put_session("r1", SessionConfig(map="alt"))
    assert info.map_checksum == etag2
    a.admin.delete("alt", force=True)
    with pytest.raises(NotFound, match="was deleted"):
        b.put_session("r2", SessionConfig(map="alt"))
    assert [s.name for s in b.map_summaries()] == ["small"]
    # a map file copied in by hand, half-way: not served, logged once; whole: served
    data = map_files["v1"].read_bytes()
    (maps / "alt.swmap").write_bytes(data[: len(data) // 2])
    with caplog.at_level(logging.WARNING, logger="swarmloc"):
        assert [s.name for s in b.map_summaries()] == ["small"]
        assert [s.name for s in b.map_summaries()] == ["small"]
        with pytest.raises(NotFound):
            b.get_map("alt")
    assert sum("alt.swmap" in r.getMessage() for r in caplog.records) == 1
    (maps / "alt.swmap").write_bytes(data)
    assert b.get_map("alt").meta["checksum"] == etag1
    # a name never names a path: a map file beside the directory, named like a path to it
    save_map(dataclasses.replace(small_map, name="../outside"), tmp_path / "outside")
    for path_like in ("../outside", ".alt", "alt.swmap/"):
        with pytest.raises(NotFound):
            b.get_map(path_like)
