"""The ``swarmloc`` command: world rendering, maps, benchmarks, experiments, serving, replay.

Importing this module costs typer only: every command imports what it needs (NumPy, OpenCV,
the service, the lab) when it runs, so ``swarmloc --help`` stays fast and the light client
install runs ``replay`` without the heavy extras.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn, cast

import typer

from client.lab.bench_experience_cli import register as register_experience_bench
from client.lab.bench_features_cli import register as register_feature_benches
from client.lab.bench_frame_cli import register as register_frame_bench
from client.lab.bench_load_cli import register as register_load_bench
from client.lab.bench_odometry import register as register_odometry_bench
from client.lab.experiment_cli import experiment, sweep
from client.lab.night_places_cli import register as register_night_places
from client.lab.scale_map_cli import register as register_scale_map
from service.api.models import DEFAULT_FEATURES, MAX_FEATURES_CAP, SessionInfo
from service.cli import DebugOpt, run_cli, serve

if TYPE_CHECKING:
    import numpy as np

    from client.dataset import Round
    from client.transports import Client, HttpClient
    from service.api.models import MapSummary
    from service.maps.positions import PositionsRule
    from service.vision.features import FeatureParams

# plain click help (rich_markup_mode=None): rich's import alone costs more than the 0.3 s
# that `swarmloc --help` may take
_PLAIN = {"no_args_is_help": True, "rich_markup_mode": None}
app = typer.Typer(help="swarmloc: visual localization service (SIFT maps + Dynamic PSO).",
                  pretty_exceptions_enable=False, **_PLAIN)  # type: ignore[arg-type]
world_app = typer.Typer(help="Synthetic route world.", **_PLAIN)  # type: ignore[arg-type]
map_app = typer.Typer(help="Route maps.", **_PLAIN)  # type: ignore[arg-type]
bench_app = typer.Typer(help="Benchmarks (print numbers).", **_PLAIN)  # type: ignore[arg-type]
dataset_app = typer.Typer(help="Datasets: import recordings.", **_PLAIN)  # type: ignore[arg-type]
app.add_typer(world_app, name="world")
app.add_typer(dataset_app, name="dataset")
app.add_typer(map_app, name="map")
app.add_typer(bench_app, name="bench")
register_load_bench(bench_app)  # bench load, bench fuzz (client/lab/bench_load_cli.py)
register_frame_bench(bench_app)  # bench frame (client/lab/bench_frame_cli.py)
register_experience_bench(bench_app)  # bench experiences (client/lab/bench_experience_cli.py)
register_night_places(bench_app)  # bench night-places (client/lab/night_places_cli.py)
register_odometry_bench(bench_app)  # bench odometry (client/lab/bench_odometry.py)
# bench webcam-night, bench extract (client/lab/bench_features_cli.py)
register_feature_benches(bench_app)
register_scale_map(world_app, bench_app)  # world long-route, bench scale-map


@app.callback()
def _main(debug: DebugOpt = False) -> None:
    """swarmloc: visual localization service (SIFT maps + Dynamic PSO).

    Errors print one line saying what to do; --debug (before the command) shows the
    traceback."""
    _one_blas_thread()


def _one_blas_thread() -> None:
    """NumPy's BLAS on one thread, as the service runs it (service/server.py): the lab's
    matrix products are small and run beside threads and processes of their own, and
    OpenBLAS's spinning pool made them up to 100x slower on a busy 2-core machine (a frame's
    VLAD: 58 ms against 0.5 ms). Results do not depend on it. A light client install has no
    threadpoolctl and skips it."""
    try:
        import numpy  # noqa: F401  (threadpoolctl limits the BLAS libraries already loaded)
        from threadpoolctl import threadpool_limits
    except ImportError:
        return
    threadpool_limits(1, "blas")


def _fail(msg: str) -> NoReturn:
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(2)


def _read_round(path: Path) -> Round:
    """Read a round, or exit with the validation message (file and line)."""
    from client.dataset import DatasetError, read_round

    try:
        return read_round(path)
    except DatasetError as exc:
        _fail(str(exc))


LAB_FEATURES = "clahe-rootsift"  # the evaluators' default: the published tables' maps
FeaturesOpt = Annotated[str, typer.Option(
    help="clahe-rootsift+xfeat (both per image, their similarities fused: the default of "
         "map build), clahe-rootsift (contrast-normalised RootSIFT: the evaluators' "
         "default), sift (the papers') or xfeat (learned features that hold at night; ONNX "
         "Runtime on the CPU)")]
PruneOpt = Annotated[bool, typer.Option(
    help="the papers' neighbour pruning (drops the features that survive lighting changes)")]


MaxFeaturesOpt = Annotated[int | None, typer.Option(
    min=0, max=MAX_FEATURES_CAP, help="SIFT's features kept per map image and frame, the strongest "
    "(default 2,048; 0: all). Above 2,048 the service compares the map through its inverted "
    "file (SWARMLOC_MATCHER=auto); XFeat keeps its 1,024")]


def _positions_rule(value: str) -> PositionsRule:
    """``--positions``, checked: fused or recorded (service/maps/positions.py)."""
    from service.maps.positions import POSITIONS_RULES

    if value not in POSITIONS_RULES:
        _fail(f"--positions must be one of {', '.join(POSITIONS_RULES)}, got {value!r}")
    return cast("PositionsRule", value)


def feature_params(name: str, width: int = 320, height: int = 240,
                   max_features: int | None = None) -> FeatureParams:
    """The feature parameters of a feature type name (the CLI's --features)."""
    from service.vision.features import named_params

    try:
        return named_params(name, width, height, max_features)
    except ValueError as exc:
        _fail(str(exc))


# ---- world ------------------------------------------------------------------------------
@world_app.command("render")
def world_render(
    out: Annotated[Path, typer.Argument(help="dataset directory to write")],
    seed: int = 0,
    length: Annotated[float, typer.Option(help="loop length, m")] = 260.0,
    spacing: Annotated[float, typer.Option(help="distance between frames, m")] = 0.6,
    rounds: Annotated[str, typer.Option(
        help="comma-separated subset, e.g. sunny1,cloudy1; also lowsun1-2, dusk1-2, night1-2"
    )] = "",
    width: Annotated[int, typer.Option(min=32, max=4096, help="image width, pixels")] = 320,
    height: Annotated[int, typer.Option(min=32, max=4096, help="image height, pixels")] = 240,
) -> None:
    """Render rounds (default: sunny1-3, cloudy1-3) in the dataset format."""
    from client.lab.world import DatasetSpec, render_dataset

    spec = DatasetSpec(seed=seed, length_m=length, spacing_m=spacing, width=width,
                       height=height)
    only = [r for r in rounds.split(",") if r] or None
    try:
        render_dataset(out, spec, progress=True, only=only)
    except ValueError as exc:
        _fail(str(exc))
    typer.echo(f"wrote {out}")


@world_app.command("sheet")
def world_sheet(
    round_dir: Path,
    out: Annotated[Path, typer.Option(help="PNG to write")] = Path("sheet.png"),
    count: int = 12,
) -> None:
    """Write a contact sheet PNG of evenly spaced frames of a round."""
    import cv2
    import numpy as np

    from client.lab.world import contact_sheet

    rnd = _read_round(round_dir)
    idx = np.linspace(0, len(rnd) - 1, min(count, len(rnd))).astype(int)
    sheet = contact_sheet([rnd.load_image(i) for i in idx], 4, [f"{rnd.images[i]}" for i in idx])
    cv2.imwrite(str(out), sheet)
    typer.echo(f"wrote {out}")


@world_app.command("eval")
def world_eval(
    map_round: Path, query_round: Path,
    radius: Annotated[float, typer.Option(help="success radius, m")] = 3.0,
    every: Annotated[int, typer.Option(help="use every k-th query frame")] = 2,
    features: FeaturesOpt = LAB_FEATURES,
    prune: PruneOpt = False,
) -> None:
    """Features per frame, pruning, and the fraction of query frames whose best-matching
    map image lies within RADIUS of the truth (symmetric ratio matching)."""
    import numpy as np

    from service.maps.route_map import build_map_from_rounds
    from service.vision.features import extract

    mr, qr = _read_round(map_round), _read_round(query_round)
    m = build_map_from_rounds([mr], params=feature_params(features), prune_features=prune)
    hits, n_feat = [], []
    for i in range(0, len(qr), every):
        f = extract(qr.load_image(i), m.feature_params)
        n_feat.append(len(f))
        best = int(np.argmax(m.similarity(f, range(m.n_images))))
        hits.append(np.linalg.norm(m.positions[best] - qr.reference_xy[i]) <= radius)
    pr = m.meta["pruning"]
    typer.echo(f"map {mr.name}: {len(mr)} images, {pr['features_before'] / len(mr):.0f} SIFT "
               f"features/frame, pruning removed {100 * pr['removed_fraction']:.1f} %")
    typer.echo(f"query {qr.name}: {np.mean(n_feat):.0f} SIFT features/frame; best match within "
               f"{radius:g} m of the truth for {100 * np.mean(hits):.1f} % of {len(hits)} frames")


# ---- datasets ---------------------------------------------------------------------------
ImageTopic = Annotated[str | None, typer.Option(
    help="rosbag2: sensor_msgs/CompressedImage or Image topic")]
GpsTopic = Annotated[str | None, typer.Option(help="rosbag2: sensor_msgs/NavSatFix topic")]
PoseTopic = Annotated[str | None, typer.Option(
    help="rosbag2: nav_msgs/Odometry, PoseStamped or PoseWithCovarianceStamped topic")]
OdomTopic = Annotated[str | None, typer.Option(
    help="rosbag2: nav_msgs/Odometry topic of the wheel odometry, written to odometry.csv")]
MinDistance = Annotated[float, typer.Option(
    help="rosbag2: keep an image every this many metres travelled (0: all)")]


def _convert_bag(bag: Path, image_topic: str | None, out: Path, gps_topic: str | None,
                 pose_topic: str | None, min_distance: float, odom_topic: str | None = None
                 ) -> None:
    """Convert a rosbag2 recording to a round, or exit with what is wrong."""
    if not image_topic:
        _fail("a rosbag2 needs --image-topic (and --gps-topic or --pose-topic)")
    from client.bag import BagError, convert_bag

    try:
        c = convert_bag(bag, image_topic, out, gps_topic, pose_topic, min_distance,
                        odom_topic)
    except BagError as exc:
        _fail(str(exc))
    except ImportError as exc:
        _fail(f"rosbag2 support needs the 'ros' extra: pip install 'swarmloc[ros]' ({exc})")
    kind = f"lat/lon (origin {c.origin[0]:.7f}, {c.origin[1]:.7f} in " \
        f"{out.parent / 'dataset.json'})" if c.origin else "x/y"
    typer.echo(f"wrote {c.path}: {c.images} images along {c.length_m:.1f} m, positions "
               f"{kind}; left out {c.outside} outside the positions' time span and "
               f"{c.subsampled} by --min-distance")


@dataset_app.command("from-bag")
def dataset_from_bag(
    bag: Annotated[Path, typer.Argument(help="rosbag2 directory, or a .mcap / .db3 file")],
    image_topic: Annotated[str, typer.Option(help="sensor_msgs/CompressedImage or Image")],
    out: Annotated[Path, typer.Option(help="round directory to write (must not exist)")],
    gps_topic: GpsTopic = None,
    pose_topic: PoseTopic = None,
    min_distance: MinDistance = 0.0,
    odom_topic: OdomTopic = None,
) -> None:
    """Convert a rosbag2 recording (sqlite3 or MCAP) into a round of the dataset format."""
    _convert_bag(bag, image_topic, out, gps_topic, pose_topic, min_distance, odom_topic)


# ---- maps -------------------------------------------------------------------------------
@map_app.command("build")
def map_build(
    round_dirs: Annotated[list[Path], typer.Argument(
        help="one round, or several traversals of one route (e.g. a sunny and a cloudy "
             "round) merged into one multi-condition map")],
    out: Annotated[Path, typer.Option(help="map path, e.g. maps/NAME (.swmap is added)")],
    delta: Annotated[float, typer.Option(help="ratio-test threshold")] = 0.6,
    width: int = 320,
    height: int = 240,
    features: FeaturesOpt = DEFAULT_FEATURES,
    prune: PruneOpt = False,
    hfov: Annotated[float | None, typer.Option(
        help="the camera's horizontal field of view (degrees; square pixels, centred), where "
             "the rounds' dataset.json 'camera' or calib.txt do not give it; with a camera "
             "the service locates frames between map images")] = None,
    max_features: MaxFeaturesOpt = None,
    positions: Annotated[str, typer.Option(
        help="the images' positions: 'fused' aligns a round's odometry.csv, where it has "
             "one, to its poses.csv (GPS-like noise averaged out over 15 m of travel); "
             "'recorded' keeps poses.csv as it is (exact positions, e.g. RTK or SLAM)")]
    = "fused",
) -> None:
    """Build a map from one or more rounds: features, optional pruning, atomic write."""
    from dataclasses import replace

    from tqdm import tqdm

    from service.api.round_format import camera_from_hfov
    from service.maps.route_map import MapError, build_map_from_rounds, save_map

    rule = _positions_rule(positions)
    rounds = [_read_round(r) for r in round_dirs]
    if hfov is not None:
        h, w = rounds[0].load_image(0).shape[:2]
        try:
            cam = camera_from_hfov(hfov, w, h)
        except ValueError as exc:
            _fail(f"--hfov: {exc}")
        rounds = [replace(r, camera=cam) for r in rounds]
    try:
        m = build_map_from_rounds(
            rounds, name=out.name.removesuffix(".swmap"),
            params=feature_params(features, width, height, max_features), delta=delta,
            prune_features=prune, positions=rule,
            source={"rounds": [{"round": str(r.path), "name": r.name} for r in rounds]},
            wrap=lambda it: tqdm(it, total=sum(len(r) for r in rounds), desc="features",
                                 unit="img"))
    except MapError as exc:
        _fail(str(exc))
    path = save_map(m, out)
    pr = m.meta["pruning"]
    typer.echo(f"wrote {path}: {m.n_images} images in {m.n_layers} layer(s), "
               f"{pr['features_after']} features ({pr['features_after'] / m.n_images:.0f} per "
               f"image; pruning removed {100 * pr['removed_fraction']:.1f} %); positions "
               f"{', '.join(m.meta['source']['positions'])}; "
               + ("with the camera: frames are located between images" if m.camera else
                  "no camera (dataset.json 'camera', calib.txt or --hfov): frames are placed "
                  "at map images"))


@map_app.command("info")
def map_info(path: Path) -> None:
    """Verify a map and print its metadata."""
    from service.maps.route_map import MapError, load_map

    try:
        m = load_map(path)
    except MapError as exc:
        _fail(str(exc))
    typer.echo(json.dumps(m.summary(), indent=2))


# ---- maps on a running service ----------------------------------------------------------
def _remote(url: str, token: str | None) -> HttpClient:
    from client.transports import HttpClient

    return HttpClient(url, token)


def _remote_fail(exc: Exception) -> NoReturn:
    from service.cli import explain

    _fail(explain(exc, "")[0])


Url = Annotated[str, typer.Option("--to", help="service URL, e.g. http://127.0.0.1:8080")]
Token = Annotated[str | None, typer.Option(help="bearer token [SWARMLOC_AUTH_TOKEN]",
                                           envvar="SWARMLOC_AUTH_TOKEN")]


@map_app.command("push")
def map_push(
    path: Path, to: Url,
    name: Annotated[str | None, typer.Option(help="default: the name in the map's header")]
    = None,
    if_match: Annotated[str | None, typer.Option(help="replace only this version (ETag)")]
    = None,
    new: Annotated[bool, typer.Option(help="fail if the map exists (If-None-Match: *)")]
    = False,
    token: Token = None,
) -> None:
    """Upload a .swmap to a running service (new or replacing; no restart, no session lost)."""
    from client.transports import SwarmlocError
    from service.maps.route_map import MapError, load_map

    try:
        local = load_map(path)
    except MapError as exc:
        _fail(str(exc))
    client = _remote(to, token)
    try:
        summary, created = client.push_map(path, name or local.name, if_match,
                                           "*" if new else None)
    except SwarmlocError as exc:
        _remote_fail(exc)
    finally:
        client.close()
    typer.echo(f"{'created' if created else 'replaced'} map '{summary.name}' "
               f"({summary.n_images} images), version {summary.checksum}")


@map_app.command("pull")
def map_pull(
    name: str,
    from_: Annotated[str, typer.Option("--from", help="service URL")],
    out: Annotated[Path, typer.Option(help="file or folder")] = Path("."),
    token: Token = None,
) -> None:
    """Download a map's current .swmap from a running service."""
    from client.transports import SwarmlocError
    from service.maps.route_map import MapError, load_map

    client = _remote(from_, token)
    try:
        path = client.pull_map(name, out)
    except SwarmlocError as exc:
        _remote_fail(exc)
    finally:
        client.close()
    try:
        m = load_map(path)
    except MapError as exc:
        _fail(f"downloaded file does not verify: {exc}")
    typer.echo(f"wrote {path}: {m.n_images} images, version {m.meta['checksum']}")


@map_app.command("delete")
def map_delete(
    name: str,
    at: Annotated[str, typer.Option("--at", help="service URL")],
    force: Annotated[bool, typer.Option(help="end the sessions on the map")] = False,
    token: Token = None,
) -> None:
    """Delete a map on a running service (refused while sessions use it, unless --force)."""
    from client.transports import SwarmlocError

    client = _remote(at, token)
    try:
        res = client.delete_map(name, force)
    except SwarmlocError as exc:
        _remote_fail(exc)
    finally:
        client.close()
    ended = f"; ended sessions {', '.join(res.ended_sessions)}" if res.ended_sessions else ""
    typer.echo(f"deleted map '{name}'{ended}")


@map_app.command("build-remote")
def map_build_remote(
    round_dir: Path, to: Url,
    name: Annotated[str | None, typer.Option(help="map name (default: the round's name)")]
    = None,
    new: Annotated[bool, typer.Option(help="fail if the map exists (If-None-Match: *)")]
    = False,
    token: Token = None,
    features: FeaturesOpt = DEFAULT_FEATURES,
    max_features: MaxFeaturesOpt = None,
    width: Annotated[int, typer.Option(help="the map's working width (keep the camera's "
                                            "aspect)")] = 320,
    height: Annotated[int, typer.Option(help="the map's working height")] = 240,
    positions: Annotated[str, typer.Option(
        help="'fused': the round's odometry.csv goes along and the service aligns it to "
             "poses.csv; 'recorded': it stays home and poses.csv is kept as it is")]
    = "fused",
) -> None:
    """Zip a round, build its map on the service, follow the job with a progress bar."""
    import tempfile

    from tqdm import tqdm

    from client.map_remote import follow_job, zip_round
    from client.transports import SwarmlocError
    from service.api.models import JobInfo

    rule = _positions_rule(positions)
    _read_round(round_dir)  # validation messages with file and line, before any upload
    client = _remote(to, token)
    with tempfile.TemporaryDirectory() as tmp:
        archive = zip_round(round_dir, Path(tmp) / "round.zip",
                            odometry=rule == "fused")
        try:
            job = client.build_map_remote(name or round_dir.name, archive, "*" if new else None,
                                          features, max_features, width, height)
            with tqdm(total=job.total, desc=f"build {job.map}", unit="img") as bar:
                def show(j: JobInfo) -> None:
                    bar.update(j.done - bar.n)
                    bar.set_postfix_str(j.state)

                job = follow_job(client, job, show)
        except SwarmlocError as exc:
            _remote_fail(exc)
        finally:
            client.close()
    if job.state == "failed":
        _fail(f"build job {job.id} failed ({job.status}): {job.error}")
    typer.echo(f"built map '{job.map}' on {to}: {job.total} images, version {job.checksum}")


# ---- benchmarks -------------------------------------------------------------------------
@bench_app.command("similarity")
def bench_similarity_cmd(k: int = 20, repeats: int = 7) -> None:
    """SIFT ms/frame; batched similarity vs OpenCV BFMatcher per comparison."""
    from client.lab.bench import bench_similarity

    b = bench_similarity(k=k, repeats=repeats)
    typer.echo(f"SIFT extraction (320x240):        {b.extract_ms:8.2f} ms/frame (median)")
    batched, bf = b.batched_ms_per_comparison, b.bfmatcher_ms_per_comparison
    typer.echo(f"batched similarity (K={b.k}):      {batched:8.3f} ms/comparison (median)")
    typer.echo(f"BFMatcher knnMatch x2 + recip.:   {bf:8.3f} ms/comparison (median)")
    typer.echo(f"speed-up:                         {b.speedup:8.1f} x")
    typer.echo(f"features: frame {b.frame_features:.0f}, map image {b.map_features:.0f} (pruned); "
               f"identical match counts: {b.counts_equal}")


@bench_app.command("startup")
def bench_startup_cmd(runs: int = 10) -> None:
    """Wall time of `swarmloc --help` in a fresh interpreter (median of RUNS), beside
    `python -c pass`."""
    import statistics
    import subprocess
    import sys
    import time

    def median_s(cmd: list[str]) -> float:
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            times.append(time.perf_counter() - t0)
        return statistics.median(times)

    help_s = median_s([sys.executable, "-m", "client.cli", "--help"])
    bare_s = median_s([sys.executable, "-c", "pass"])
    typer.echo(f"swarmloc --help: median {help_s:.3f} s over {runs} runs; "
               f"python -c pass: {bare_s:.3f} s")


@bench_app.command("ros2")
def bench_ros2_cmd(repeats: int = 200) -> None:
    """Per-frame cost of the ROS 2 layer: CDR in (rosbags) and the answer out (needs the
    'ros' extra)."""
    from client.lab.bench import bench_ros2

    b = bench_ros2(repeats=repeats)
    typer.echo(f"CompressedImage in (320x240 JPEG, {b.jpeg_bytes} B): {b.compressed_in_ms:7.3f} "
               "ms (median)")
    typer.echo(f"Image mono8 in:                 {b.image_in_ms:7.3f} ms")
    typer.echo(f"Image bgr8 in (to gray):        {b.bgr_in_ms:7.3f} ms")
    typer.echo(f"PoseWithCovarianceStamped out:  {b.pose_out_ms:7.3f} ms")
    typer.echo(f"DiagnosticStatus out:           {b.status_out_ms:7.3f} ms")
    typer.echo(f"SIFT on the same frame:         {b.extract_ms:7.3f} ms")


# ---- service (service/cli.py) ------------------------------------------------------------
app.command("serve")(serve)


# ---- replay -----------------------------------------------------------------------------
def _parse_params(items: list[str] | None) -> dict:
    out: dict = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            _fail(f"--param takes KEY=VALUE, got '{item}'")
        try:
            out[key] = int(value) if value.lstrip("-").isdigit() else float(value)
        except ValueError:
            _fail(f"--param {key}: '{value}' is not a number")
    return out


@app.command("replay")
def replay_cmd(
    round_dir: Annotated[Path, typer.Argument(
        help="round directory, or a rosbag2 (directory or .mcap / .db3 file)")],
    map_name: Annotated[str | None, typer.Option("--map", help="map name on the service")]
    = None,
    via: Annotated[str, typer.Option(help="http://HOST:PORT | zenoh[:ENDPOINT] | local[:DIR]")]
    = "local",
    estimator: Annotated[str, typer.Option(help="dpso | pf-g | pf-l")] = "dpso",
    param: Annotated[list[str] | None, typer.Option(help="estimator parameter KEY=VALUE")]
    = None,
    seed: int = 0,
    start: Annotated[int, typer.Option(help="first image (wraps around)")] = 0,
    speed: Annotated[float, typer.Option(help="k: every k-th image; 0.5: each image twice")]
    = 1.0,
    kidnap: Annotated[bool, typer.Option(help="jump n/2 images at the middle of the run")]
    = False,
    repeat: Annotated[int, typer.Option(help="runs from evenly spaced start images")] = 1,
    length: Annotated[int | None, typer.Option(help="iterations per run")] = None,
    odometry: Annotated[bool, typer.Option(help="send the round's odometry.csv with the "
                                                "frames, where it has one")] = True,
    out: Annotated[Path, typer.Option(help="report directory")] = Path("report"),
    baseline: Annotated[Path | None, typer.Option(help="earlier report.json to compare")]
    = None,
    tolerance: Annotated[float, typer.Option(help="allowed relative regression")] = 0.1,
    token: Annotated[str | None, typer.Option(help="bearer token for HTTP")] = None,
    robot_id: str = "replay",
    learn: Annotated[bool, typer.Option(
        help="teach the map: confident frames become an experience (written when a run ends)")]
    = False,
    condition: Annotated[str | None, typer.Option(
        help="the round's light (e.g. cloudy): the tag of what --learn teaches")] = None,
    image_topic: ImageTopic = None,
    gps_topic: GpsTopic = None,
    pose_topic: PoseTopic = None,
    min_distance: MinDistance = 0.0,
    odom_topic: OdomTopic = None,
) -> None:
    """Replay a round (or a rosbag2) against a map; write report.json, report.md and plots;
    compare with a baseline."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="swarmloc-bag-") as tmp:
        from client.bag import is_bag

        if is_bag(round_dir):  # converted on the fly to a round in a temporary directory
            if gps_topic:  # lat/lon must be projected in the map's frame
                from client.dataset import write_dataset_meta

                origin = _map_origin(via, token, map_name)
                if origin is None:
                    _fail(f"cannot read the geodetic origin of map '{map_name}' over "
                          f"'{via}'; convert the bag with 'swarmloc dataset from-bag' into "
                          "the dataset of the map's round, then replay that round")
                write_dataset_meta(tmp, {"origin": {"lat": origin[0], "lon": origin[1]}})
            bag_round = Path(tmp) / round_dir.stem
            _convert_bag(round_dir, image_topic, bag_round, gps_topic, pose_topic,
                         min_distance, odom_topic)
            round_dir = bag_round
        _replay(round_dir, map_name, via, estimator, param, seed, start, speed, kidnap,
                repeat, length, out, baseline, tolerance, token, robot_id, odometry, learn,
                condition)


def _replay(round_dir: Path, map_name: str | None, via: str, estimator: str,
            param: list[str] | None, seed: int, start: int, speed: float, kidnap: bool,
            repeat: int, length: int | None, out: Path, baseline: Path | None,
            tolerance: float, token: str | None, robot_id: str, odometry: bool = True,
            learn: bool = False, condition: str | None = None) -> None:
    from client.replay import ReplayConfig, replay
    from client.report import build_report, compare, write_report
    from client.transports import SwarmlocError, connect

    rnd = _read_round(round_dir)
    cfg = ReplayConfig(map_name, estimator, _parse_params(param), seed, start, speed, kidnap,
                       length, repeat, odometry, learn, condition)
    try:
        client = connect(via, token)
    except ValueError as exc:
        _fail(str(exc))
    if via.startswith(("http://", "https://")):
        typer.echo(f"watch it live: {via.rstrip('/')}/viewer"
                   + (f"?map={map_name}" if map_name else "")
                   + (" (add the token: &token=... or ?token=...)" if token else ""))
    try:
        runs = replay(client, rnd, cfg, robot_id=robot_id, progress=True,
                      on_end=_echo_learning if learn else None)
        route = _route_positions(client, map_name, rnd)
        if learn:
            _echo_experiences(client, map_name)
    except SwarmlocError as exc:
        _fail(f"service error {exc.status}: {exc.message}")
    finally:
        client.close()
    report = build_report(rnd, cfg, runs, via)
    files = write_report(report, runs, route, out)
    s = report["summary"]
    typer.echo(f"mean error {s['error_mean_m']:.2f} m (median {s['error_median_m']:.2f}, "
               f"p95 {s['error_p95_m']:.2f}), within 5 m {100 * s['within_5m']:.1f} %, "
               f"{s['comparisons_per_frame']:.1f} comparisons/frame, latency p50 "
               f"{s['latency_p50_ms']:.1f} ms p99 {s['latency_p99_ms']:.1f} ms")
    typer.echo("wrote " + ", ".join(str(f) for f in files))
    if baseline is not None:
        problems = compare(report, json.loads(baseline.read_text()), tolerance)
        for p in problems:
            typer.echo(f"REGRESSION: {p}", err=True)
        if problems:
            raise typer.Exit(1)
        typer.echo(f"no regression against {baseline} (tolerance {tolerance:g})")


def _map_origin(via: str, token: str | None, map_name: str | None
                ) -> tuple[float, float] | None:
    """(lat, lon) origin of the map, where the transport lists maps (HTTP, local)."""
    from client.transports import SwarmlocError, connect

    try:
        client = connect(via, token)
    except ValueError as exc:
        _fail(str(exc))
    try:
        maps = client.maps()
    except SwarmlocError:
        return None
    finally:
        client.close()
    name = map_name or _default_map(maps)
    match = [m for m in maps if m.name == name]
    o = match[0].meta.get("origin") if len(match) == 1 else None
    return (float(o["lat"]), float(o["lon"])) if o else None


def _echo_learning(info: SessionInfo) -> None:
    """What a learning run taught (where the service answers its session's progress)."""
    lr = info.learning
    if lr is None:
        typer.echo("learning: the service reported no progress for this run")
        return
    stopped = ", ".join(f"{g} {n}" for g, n in lr.stopped.items() if n)
    typer.echo(f"learning: {lr.taught} of {lr.frames} frames taught, {lr.bridged} bridged by "
               f"the wheels, into experience {lr.experience}"
               + (f"; stopped: {stopped}" if stopped else ""))


def _echo_experiences(client: Client, map_name: str | None) -> None:
    """What the map learned (where the transport lists maps: HTTP, local)."""
    from client.transports import SwarmlocError

    try:
        maps = client.maps()
    except SwarmlocError:
        return
    name = map_name or _default_map(maps)
    for m in maps:
        if m.name == name:
            typer.echo(f"map {name}: version {str(m.checksum)[:12]}, {len(m.experiences)} "
                       "experience(s)" + "".join(
                           f"\n  {e.id}: {e.images} images, condition {e.condition}, "
                           f"{e.bytes / 1e6:.1f} MB, {e.uses} uses" for e in m.experiences))


def _default_map(maps: list[MapSummary]) -> str:
    """The service's default map: the only one, else 'demo'."""
    return maps[0].name if len(maps) == 1 else "demo"


def _route_positions(client: Client, map_name: str | None, rnd: Round) -> np.ndarray:
    """The map's image positions for the route plot; the round's own when not available."""
    import numpy as np

    from client.transports import SwarmlocError

    try:
        name = map_name or _default_map(client.maps())
        return np.array(client.map_detail(name).positions)
    except SwarmlocError:
        return rnd.xy


@app.command("eval-split")
def eval_split(
    round_dir: Path,
    width: Annotated[int, typer.Option(help="working width (keep the camera's aspect)")] = 320,
    height: int = 240,
    estimator: str = "dpso",
    seed: int = 0,
    features: FeaturesOpt = LAB_FEATURES,
) -> None:
    """One traversal: map from the even frames, localize the odd frames (real-data check).

    Prints the share of odd frames whose best-matching map image is an adjacent even frame,
    the estimator's error when the odd frames are replayed in order, and the share of
    tracked frames within accuracy_m."""
    import numpy as np

    from client.lab.experiments import SimilarityTable, run
    from client.runs import run_metrics
    from service.maps.route_map import build_map_from_rounds
    from service.vision.features import extract

    rnd = _read_round(round_dir)
    params = feature_params(features, width, height)
    even = list(range(0, len(rnd), 2))
    odd = list(range(1, len(rnd), 2))
    m = build_map_from_rounds([rnd.subset(even, use_truth=True)], params=params,
                              positions="recorded")  # the truth: nothing to average out
    feats = [extract(rnd.load_image(i), params) for i in odd]
    adjacent = 0
    for k, f in enumerate(feats):
        best = int(np.argmax(m.similarity(f, range(m.n_images))))
        adjacent += abs(best - (k + 0.5)) <= 0.5 + 1e-9  # even neighbours of odd frame 2k+1
    query = rnd.subset(odd)
    res = run(m, SimilarityTable(m, feats), query, estimator, None, seed=seed)
    pr = m.meta["pruning"]
    typer.echo(f"{rnd.name}: map of {m.n_images} even frames ({features}, {width}x{height}, "
               f"pruning removed {100 * pr['removed_fraction']:.0f} %), {len(odd)} odd query "
               "frames")
    typer.echo(f"best match is an adjacent even frame for {adjacent}/{len(odd)} query frames")
    e = res.errors
    typer.echo(f"{estimator} replay of the odd frames: mean error {e.mean():.2f} m, median "
               f"{np.median(e):.2f} m, last half {e[len(e) // 2:].mean():.2f} m, "
               f"{res.comparisons.mean():.1f} comparisons/frame; final status {res.status[-1]}")
    cal = run_metrics(res)["calibration"]
    if cal is not None:
        typer.echo(f"tracked frames within accuracy_m (calibration): {100 * cal:.0f} %, median "
                   f"accuracy_m {np.median(res.accuracy_m):.2f} m")


@app.command("eval-pair")
def eval_pair_cmd(
    map_dir: Path,
    query_dir: Path,
    spacing: Annotated[float, typer.Option(help="metres between consecutive indices")] = 2.5,
    width: int = 640,
    height: int = 360,
    passes: Annotated[int, typer.Option(min=1, help="replays along the route and back")] = 4,
    estimator: str = "dpso",
    seeds: Annotated[int, typer.Option(min=1, help="replays (one seed each)")] = 3,
    features: FeaturesOpt = LAB_FEATURES,
    param: Annotated[list[str] | None, typer.Option(
        help="estimator parameter KEY=VALUE (repeatable), e.g. v0=0.05")] = None,
) -> None:
    """Two traversals known only by frame correspondence (poses.csv: filename,index), such as
    the Gardens Point day/night pair: how often the best match is the frame's own place
    (exactly, within +-1 frame), how often the estimator reports tracking within +-1 frame, and
    whether it admits (lost / recovering) the frames it gets wrong by > 10 m."""
    from client.dataset import DatasetError
    from client.lab.eval_pair import eval_pair

    params = feature_params(features, width, height)
    try:
        r = eval_pair(map_dir, query_dir, spacing=spacing, passes=passes, estimator=estimator,
                      seeds=seeds, params=params, estimator_params=_parse_params(param))
    except (DatasetError, ValueError) as exc:
        _fail(str(exc))
    typer.echo(f"{query_dir.name} against a map of {map_dir.name} ({features}, {width}x"
               f"{height}): the best match is the frame's own place for {r.best_is_true}/"
               f"{r.frames} frames, within +-1 frame for {r.best_within_one}/{r.frames} "
               f"(median similarity at the own place {r.true_similarity_median:.4f})")
    counts = ", ".join(f"{k} {v}" for k, v in sorted(r.status.items()))
    typer.echo(f"{estimator}, {r.replayed} frames replayed ({seeds} seeds): {counts}")
    typer.echo(f"reported tracking within +-1 frame: {r.tracking_within_one}/{r.replayed} "
               f"replayed frames ({100 * r.tracking_within_one / r.replayed:.0f} %); query "
               f"frames tracked within +-1 frame in at least half their visits: "
               f"{r.frames_tracked}/{r.frames}")
    honest = "n/a" if r.honest is None else f"{100 * r.honest:.0f} %"
    typer.echo(f"frames > 10 m off: {r.wrong}, reported lost or recovering: {honest}; "
               f"reported tracking while > 10 m off: {r.tracking_wrong}")


@bench_app.command("matcher")
def bench_matcher_cmd(
    photos: Annotated[Path | None, typer.Option(help="also measure on these photos")] = None,
    k: Annotated[int, typer.Option(help="map images per frame")] = 20,
    places: Annotated[int, typer.Option(help="query frames")] = 3,
    repeats: int = 5,
) -> None:
    """Exact uint8 matcher vs the float match_batch: ms/comparison, speed-up, identical counts."""
    from client.lab.bench import bench_matcher

    if photos is not None and not photos.is_dir():
        _fail(f"--photos {photos}: not a directory")
    for src in [None, str(photos)] if photos is not None else [None]:
        try:
            b = bench_matcher(src, k=k, places=places, repeats=repeats)
        except ValueError as exc:
            _fail(str(exc))
        typer.echo(f"{b.source}: {b.queries} frames x {b.k} map images, features: frame "
                   f"{b.frame_features:.0f}, map image {b.map_features:.0f}")
        typer.echo(f"  float match_batch (1 BLAS thread):    {b.float_ms:8.3f} ms/comparison")
        typer.echo(f"  float match_batch (default BLAS):     {b.float_default_blas_ms:8.3f} "
                   "ms/comparison")
        typer.echo(f"  uint8 match_batch_u8 (NumKong):       {b.fast_ms:8.3f} ms/comparison")
        typer.echo(f"  uint8 match_batch_u8 (BLAS float32):  {b.fast_blas_ms:8.3f} ms/comparison")
        typer.echo(f"  speed-up (NumKong vs float, 1 thread): {b.speedup:7.1f} x")
        typer.echo(f"  2 threads at once: float {b.float_2threads_ms:.3f}, uint8 "
                   f"{b.fast_2threads_ms:.3f} ms/comparison (wall / comparisons)")
        typer.echo(f"  identical counts, fast vs exact reference: {b.counts_identical} "
                   f"({b.comparisons} comparisons); float path vs reference: "
                   f"{b.float_counts_identical}")


@bench_app.command("features")
def bench_features_cmd(
    seed: int = 0,
    length: Annotated[float, typer.Option(help="loop length of the world, m")] = 120.0,
    map_step: Annotated[int, typer.Option(help="map image every N frames")] = 3,
    queries: Annotated[int, typer.Option(help="query frames per lighting")] = 10,
) -> None:
    """SIFT vs CLAHE + RootSIFT (uint8) vs ORB (AKAZE): CPU time per frame, place recognition."""
    from client.lab.bench import bench_features

    rows = bench_features(seed, length, map_step, queries)
    typer.echo(f"map: {rows[0].map_images} sunny images; {rows[0].queries} queries per lighting; "
               "top-1: most similar map image within 5 m of the truth")
    typer.echo(f"{'feature type':28s} {'feat/frame':>10s} {'extract ms':>10s} "
               f"{'match ms/cmp':>12s} {'top-1 cloudy':>12s} {'top-1 sunny':>11s}")
    for r in rows:
        typer.echo(f"{r.name:28s} {r.features:10.0f} {r.extract_ms:10.2f} {r.match_ms:12.3f} "
                   f"{100 * r.cross_light_top1:11.0f}% {100 * r.same_light_top1:10.0f}%")


@bench_app.command("latency")
def bench_latency_cmd(
    round_dir: Annotated[Path, typer.Argument(help="round whose frames are sent")],
    maps_dir: Annotated[Path, typer.Option(help="maps the server loads")] = Path("maps"),
    frames: int = 200,
) -> None:
    """p50/p99 per-frame latency in process, over HTTP and over Zenoh (real server)."""
    from client.lab.bench import bench_latency

    for b in bench_latency(str(maps_dir), str(round_dir), frames):
        typer.echo(f"{b.transport:10s} {b.frames} frames: p50 {b.p50_ms:6.1f} ms, "
                   f"p99 {b.p99_ms:6.1f} ms, mean {b.mean_ms:6.1f} ms")


@bench_app.command("scale")
def bench_scale_cmd(
    round_dir: Annotated[Path, typer.Argument(help="round whose frames are sent")],
    maps_dir: Annotated[Path, typer.Option(help="maps the replicas load")] = Path("maps"),
    frames: Annotated[int, typer.Option(help="frames per store in the overhead part")] = 200,
    robots: Annotated[int, typer.Option(help="robots sending at once to the replicas")] = 4,
    robot_frames: Annotated[int, typer.Option(help="frames each robot sends")] = 30,
    redis: Annotated[str | None, typer.Option(
        help="redis://host:port/db to use (default: a fresh redis-server on loopback)")] = None,
) -> None:
    """Redis session store overhead per frame (p50/p99 load and store) next to the in-process
    store, and frames/s of 1 and 2 replicas (real processes)."""
    import os

    from client.lab.bench_scale import bench_replicas, bench_store_overhead, with_redis

    url, srv = with_redis(redis)
    try:
        typer.echo(f"redis: {url}; load average {os.getloadavg()[0]:.1f} on "
                   f"{os.cpu_count()} CPUs")
        for o in bench_store_overhead(str(maps_dir), str(round_dir), url, frames):
            if not o.with_step and o.store == "in-process":
                typer.echo("the same, load and store back to back (no estimator step "
                           "between: the cost without the wake-up after a CPU burst):")
            typer.echo(f"{o.store:28s} load p50 {o.load_p50_ms:6.3f} ms p99 "
                       f"{o.load_p99_ms:6.3f} ms | store p50 {o.store_p50_ms:6.3f} ms p99 "
                       f"{o.store_p99_ms:6.3f} ms | step p50 {o.step_p50_ms:6.2f} ms | "
                       f"state {o.state_bytes} B")
        for t in bench_replicas(str(maps_dir), str(round_dir), url, robots, robot_frames):
            typer.echo(f"{t.replicas} replica(s), {t.setup:16s}: {t.frames} frames of "
                       f"{t.robots} robots in {t.seconds:5.1f} s = {t.fps:5.1f} frames/s")
    finally:
        if srv is not None:
            srv.stop()  # type: ignore[attr-defined]


@bench_app.command("store")
def bench_store_cmd(
    round_dir: Annotated[Path, typer.Argument(help="round whose frames are stepped")],
    maps_dir: Annotated[Path, typer.Option(help="maps to load")] = Path("maps"),
    frames: Annotated[int, typer.Option(help="frames per store")] = 200,
    estimator: Annotated[str, typer.Option(help="dpso | pf-g | pf-l | ...")] = "dpso",
) -> None:
    """Per-frame cost of the durable default session store (SQLite, WAL) next to the
    in-process memory store: medians of the same frames, round-robin in one run."""
    import os
    import statistics

    from client.lab.bench_store import bench_session_store

    typer.echo(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; "
               f"{frames} frames per store, {estimator}")
    rows = bench_session_store(str(maps_dir), str(round_dir), frames, estimator)
    base = rows[0]
    step = statistics.median(r.step_ms for r in rows)  # the same work in every store
    for r in rows:
        extra = r.store_ms - base.store_ms
        typer.echo(f"{r.store:24s} frame p50 {r.frame_ms:7.3f} ms, x{r.ratio:.3f} of "
                   f"{base.store} (paired) | store p50 {r.store_ms:6.3f} ms ({extra:+.3f} ms "
                   f"= {100 * extra / step:+.2f} % of the step p50) | step p50 "
                   f"{r.step_ms:7.3f} ms | state {r.state_bytes} B")


@bench_app.command("events")
def bench_events_cmd(
    round_dir: Annotated[Path, typer.Argument(help="round whose frames are sent")],
    maps_dir: Annotated[Path, typer.Option(help="maps the server loads")] = Path("maps"),
    frames: int = 150,
) -> None:
    """Cost of the event stream (GET /events) per frame with no viewer and with one."""
    from client.lab.bench import bench_events

    rows = bench_events(str(maps_dir), str(round_dir), frames)
    for b in rows:
        typer.echo(f"{b.condition:24s} {b.frames} frames: process_frame p50 "
                   f"{b.frame_ms_p50:6.2f} ms; stream hook p50 {b.hook_us_p50:6.1f} us, mean "
                   f"{b.hook_us_mean:6.1f} us; viewer got {b.messages} messages, "
                   f"{b.bytes_per_estimate:.0f} B/estimate")
    base = rows[0].frame_ms_p50
    for b in rows[1:]:
        typer.echo(f"{b.condition}: process_frame p50 {b.frame_ms_p50 - base:+.2f} ms "
                   f"({100 * (b.frame_ms_p50 / base - 1):+.1f} %) against no viewer")


@bench_app.command("viewer")
def bench_viewer_cmd(
    maps_dir: Annotated[Path, typer.Option(help="maps the server loads")] = Path("maps"),
    map_name: Annotated[str | None, typer.Option("--map", help="map shown")] = None,
    robots: int = 64,
    fps: Annotated[float, typer.Option(help="estimates per robot per second")] = 5.0,
    seconds: float = 10.0,
) -> None:
    """The viewer in headless Chromium under ROBOTS robots at FPS (synthetic estimates on the
    real stream): animation-frame intervals, draw time, long tasks; without and with all
    particles."""
    from client.lab.viewer_tools import bench_viewer

    for particles in (False, True):
        b = bench_viewer(maps_dir, map_name, robots, fps, seconds, particles)
        typer.echo(f"{b.robots} robots x {b.fps:g}/s for {b.seconds:g} s"
                   f"{' + all particles' if particles else ''}: published {b.published}, "
                   f"page received {b.received} messages ({b.dropped} replaced by newer); "
                   f"animation frame p50 {b.raf_ms_p50:.1f} ms p95 {b.raf_ms_p95:.1f} ms max "
                   f"{b.raf_ms_max:.0f} ms; canvas draw p50 {b.draw_ms_p50:.2f} ms p95 "
                   f"{b.draw_ms_p95:.2f} ms; long tasks (>50 ms) {b.long_tasks}")


@app.command("viewer-screenshot")
def viewer_screenshot_cmd(
    round_dir: Annotated[Path, typer.Argument(help="round whose frames the robots send")],
    out: Annotated[Path, typer.Option(help="PNG to write")] = Path("docs/viewer.png"),
    maps_dir: Annotated[Path, typer.Option(help="maps the server loads")] = Path("maps"),
    map_name: Annotated[str | None, typer.Option("--map", help="map shown")] = None,
    robots: int = 6,
) -> None:
    """Write a PNG of the fleet viewer (headless Chromium) with robots streaming real frames:
    the README's screenshot."""
    from client.lab.viewer_tools import screenshot

    path = screenshot(maps_dir, round_dir, out, map_name, robots)
    typer.echo(f"wrote {path} ({path.stat().st_size // 1024} KiB)")
@bench_app.command("build-latency")
def bench_build_latency_cmd(
    round_dir: Annotated[Path, typer.Argument(help="round: streamed as frames and built")],
    maps_dir: Annotated[Path, typer.Option(help="maps the server loads (copied)")]
    = Path("maps"),
    frames: Annotated[int, typer.Option(help="frames without a build")] = 150,
    fps: Annotated[float, typer.Option(help="robot frame rate (0: back to back)")] = 5.0,
    duty: Annotated[float, typer.Option(help="the build's duty cycle [SWARMLOC_BUILD_DUTY]")]
    = 0.5,
) -> None:
    """Frame latency p50/p99 of a streaming robot (HTTP) without and during a map build."""
    from client.lab.bench import bench_build_latency

    benches, build_s, state = bench_build_latency(str(maps_dir), str(round_dir), frames, fps,
                                                  duty=duty)
    for b in benches:
        typer.echo(f"{b.transport:16s} {b.frames:4d} frames: p50 {b.p50_ms:6.1f} ms, "
                   f"p99 {b.p99_ms:6.1f} ms, mean {b.mean_ms:6.1f} ms")
    typer.echo(f"map build of {round_dir.name}: {state} in {build_s:.1f} s "
               f"(duty {duty:g}; robot at {fps:g} frames/s over HTTP)")


# ---- experiments (client/lab/experiment_cli.py) -------------------------------------------
app.command("experiment")(experiment)
app.command("sweep")(sweep)


def _register_paper() -> None:
    from client.lab.paper_cli import paper

    app.command("paper")(paper)


_register_paper()


def main() -> None:
    run_cli(app)


if __name__ == "__main__":
    main()
