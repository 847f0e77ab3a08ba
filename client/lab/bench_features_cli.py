"""CLI registration of ``swarmloc bench webcam-night`` (client/lab/bench_webcam.py) and
``swarmloc bench extract`` (client/lab/bench_extract.py); kept apart so that the CLI's start-up
imports none of the benchmarks' modules."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def _kinds(features: str, known: tuple[str, ...] = ("clahe-rootsift", "xfeat")) -> list[str]:
    kinds = [k.strip() for k in features.split(",") if k.strip()]
    unknown = [k for k in kinds if k not in known]
    if unknown or not kinds:
        raise typer.BadParameter(f"unknown feature type(s) {unknown}: use "
                                 f"{', '.join(known)}")
    return kinds


def _sizes(text: str, option: str) -> list[tuple[int, int]]:
    """``WxH,WxH...`` as (width, height) pairs of at least 32x32."""
    try:
        wh = [tuple(int(v) for v in s.lower().split("x")) for s in text.split(",") if s]
    except ValueError:
        raise typer.BadParameter(f"{option} takes WxH,WxH..., got {text!r}") from None
    if not wh or any(len(s) != 2 or min(s) < 32 for s in wh):
        raise typer.BadParameter(f"{option} takes WxH,WxH... of at least 32x32, got {text!r}")
    return [(s[0], s[1]) for s in wh]


def register(bench_app: typer.Typer) -> None:
    """``bench webcam-night`` and ``bench extract`` on the CLI's bench group."""

    @bench_app.command("webcam-night")
    def webcam_night_cmd(
        scenes: Annotated[Path, typer.Argument(help="folder of scene folders, each the "
                                                    "photos of one fixed camera, e.g. "
                                                    "../shared/textures/tilde_webcam")],
        features: Annotated[str, typer.Option(help="feature types compared (the ratio is "
                                                   "the second over the first)")]
        = "clahe-rootsift,xfeat",
        area: Annotated[int, typer.Option(min=1024, help="pixels of the working size (the "
                                                         "photo's aspect kept)")]
        = 640 * 360,
        night_max: Annotated[float, typer.Option(help="a photo darker than this mean grey "
                                                      "is night")] = 80.0,
        tolerance: Annotated[float, typer.Option(help="a match is correct within this "
                                                      "many pixels of the identity")] = 3.0,
    ) -> None:
        """Day-night pairs of fixed cameras: the share of pairs with at least 10, 20 and 50
        correct matches (the feature type's own matches, keypoints within TOLERANCE px under
        the identity), per feature type, and their ratio."""
        from client.lab.bench_webcam import bench_webcam, report

        try:
            b = bench_webcam(scenes, _kinds(features), area, night_max, tolerance)
        except ValueError as exc:
            raise typer.BadParameter(str(exc)) from None
        report(b, typer.echo)

    @bench_app.command("approx")
    def approx_cmd(
        dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
        map_round: Annotated[str, typer.Option("--map", help="round used as the map")]
        = "sunny1",
        query: Annotated[str, typer.Option(help="comma-separated query rounds (the map "
                                                "round: its odd frames on a map of its even "
                                                "frames)")] = "cloudy1",
        size: Annotated[str, typer.Option(help="working size WxH")] = "320x240",
        words: Annotated[int, typer.Option(min=0, help="visual words of the map (k; 0: the "
                                                       "map's own, from its features per "
                                                       "image)")] = 0,
        probes: Annotated[int, typer.Option(min=1, help="words a frame feature is compared "
                                                        "in (w)")] = 3,
        frames: Annotated[int, typer.Option(min=1, help="frames after the warm-up")] = 60,
        warmup: Annotated[int, typer.Option(min=0, help="frames of global convergence not "
                                                        "scored")] = 20,
        seed: int = 0,
        max_features: Annotated[str, typer.Option(
            help="features per frame capped at N with a low detector threshold (rich "
                 "frames); 0: the default features; N,N,...: a sweep (a map per N), with "
                 "each step's growth")] = "0",
        exact_geometry: Annotated[bool, typer.Option(
            help="the two-view geometry on the exact matcher's pairs")] = False,
        exact_top: Annotated[int, typer.Option(
            min=0, help="the best N images of each comparison matched again exactly")] = 0,
    ) -> None:
        """The inverted-file matcher (the service's ``words`` matcher) against the exact one
        on the same frames: localizer step, step / extraction, mean error, match counts and
        the best image per frame; per feature cap of a sweep."""
        from client.dataset import DatasetError
        from client.lab.bench_approx import bench_approx, report, report_growth
        from client.lab.bench_extract import split_rounds

        try:
            pairs = [(q, *split_rounds(dataset, map_round, q)) for q in query.split(",") if q]
        except DatasetError as exc:
            raise typer.BadParameter(str(exc)) from None
        wh = _sizes(size, "--size")[0]
        try:
            caps = [int(v) for v in max_features.split(",") if v.strip()]
        except ValueError:
            raise typer.BadParameter(f"--max-features takes N,N,..., got {max_features!r}"
                                     ) from None
        if not caps or min(caps) < 0:
            raise typer.BadParameter("--max-features takes counts >= 0 (0: the default)")
        typer.echo(f"{dataset} map {map_round} at {wh[0]}x{wh[1]}"
                   + f"; inverted file k={words or 'auto'}, w={probes}"
                   + (" (similarity only, exact geometry)" if exact_geometry else "")
                   + (f", the best {exact_top} images again exactly" if exact_top else "")
                   + f"; DPSO seed {seed}; one thread")
        rows = [r for cap in caps for r in bench_approx(
            [(f"{q} ({cap or 'default'} features)", m, r) for q, m, r in pairs], wh, frames,
            warmup, seed, words, probes, cap, exact_geometry, exact_top)]
        report(rows, typer.echo)
        if len(caps) > 1:
            report_growth(rows, len(pairs), typer.echo)

    @bench_app.command("reuse")
    def reuse_cmd(
        dataset: Annotated[Path, typer.Argument(help="dataset with the rounds (with the "
                                                     "camera's intrinsics)")],
        map_round: Annotated[str, typer.Option("--map", help="round used as the map")]
        = "sunny1",
        query: Annotated[str, typer.Option(help="comma-separated query rounds (the map "
                                                "round: its odd frames on a map of its even "
                                                "frames)")] = "cloudy1",
        size: Annotated[str, typer.Option(help="working size WxH")] = "320x240",
        frames: Annotated[int, typer.Option(min=1, help="frames after the warm-up")] = 60,
        warmup: Annotated[int, typer.Option(min=0, help="frames not scored")] = 20,
        seed: int = 0,
    ) -> None:
        """The two-view geometry on the matches the similarity kept against matching the
        frame again, and with every structure computed beforehand: step, step / extraction,
        error, and whether the estimates are identical."""
        from client.dataset import DatasetError
        from client.lab.bench_extract import split_rounds
        from client.lab.bench_reuse import bench_reuse, report

        try:
            pairs = [(q, *split_rounds(dataset, map_round, q)) for q in query.split(",") if q]
        except DatasetError as exc:
            raise typer.BadParameter(str(exc)) from None
        if not pairs:
            raise typer.BadParameter("--query names no round")
        if len(pairs) > 1 and any(q == map_round for q, _, _ in pairs):
            raise typer.BadParameter("the map round as a query (even / odd frames) cannot be "
                                     "combined with other query rounds")
        wh = _sizes(size, "--size")[0]
        typer.echo(f"{dataset} map {map_round} at {wh[0]}x{wh[1]}; DPSO seed {seed}; one "
                   "thread")
        try:
            rows = bench_reuse(pairs[0][1], [(q, r) for q, _, r in pairs], wh, frames, warmup,
                               seed)
        except ValueError as exc:
            raise typer.BadParameter(str(exc)) from None
        report(rows, typer.echo)

    @bench_app.command("extract")
    def extract_cmd(
        dataset: Annotated[Path | None, typer.Argument(
            help="dataset with the rounds for the localizer step (none: extraction only)")]
        = None,
        map_round: Annotated[str, typer.Option("--map", help="round used as the map")]
        = "sunny1",
        query: Annotated[str, typer.Option(help="round whose frames are localized (the map "
                                                "round: its odd frames on a map of its even "
                                                "frames)")] = "cloudy1",
        image: Annotated[Path | None, typer.Option(
            help="image timed for extraction, resized to each size (default: the query's "
                 "first frame), e.g. a KITTI frame")] = None,
        sizes: Annotated[str, typer.Option(help="working sizes WxH, comma-separated")]
        = "320x240,640x480,1226x370",
        features: Annotated[str, typer.Option(help="feature types (clahe-rootsift, xfeat, "
                                                    "clahe-rootsift+xfeat)")]
        = "clahe-rootsift,xfeat,clahe-rootsift+xfeat",
        repeats: Annotated[int, typer.Option(min=1, help="extractions timed per size")] = 15,
        frames: Annotated[int, typer.Option(min=1, help="frames stepped after the warm-up")]
        = 60,
        warmup: Annotated[int, typer.Option(min=0, help="frames of global convergence not "
                                                        "timed")] = 20,
        seed: int = 0,
        sweep: Annotated[str, typer.Option(
            help="features-per-frame caps, e.g. 500,1000,2000,4000: the step's growth with "
                 "the features (needs DATASET), at --sweep-size")] = "",
        sweep_size: Annotated[str, typer.Option(help="working size WxH of the sweep")]
        = "1226x370",
        skip_sizes: Annotated[bool, typer.Option(
            help="only the sweep (not the table per size)")] = False,
    ) -> None:
        """Extraction ms per frame (median, OpenCV and ONNX Runtime on one thread) of each
        feature type at each size, the localizer step (median ms while tracking) on a map of
        that type beside it, and the ratio XFeat / RootSIFT, measured in one run."""
        from client.dataset import DatasetError, imread_gray
        from client.lab.bench_extract import (
            KINDS,
            bench_extract,
            report,
            report_sweep,
            split_rounds,
        )

        wh = _sizes(sizes, "--sizes")
        try:
            caps = [int(c) for c in sweep.split(",") if c.strip()]
        except ValueError:
            raise typer.BadParameter(f"--sweep takes N,N,..., got {sweep!r}") from None
        if any(c < 2 for c in caps) or (caps and dataset is None):
            raise typer.BadParameter("--sweep takes counts of at least 2 and needs a DATASET")
        if dataset is None and image is None:
            raise typer.BadParameter("give a DATASET (and rounds) or an --image to time")
        try:
            rounds = split_rounds(dataset, map_round, query) if dataset is not None else None
        except DatasetError as exc:
            raise typer.BadParameter(str(exc)) from None
        path = image if image is not None else rounds[1].image_path(0)  # type: ignore[index]
        img = imread_gray(path)
        if img is None:
            raise typer.BadParameter(f"{path} does not decode as an image")
        typer.echo(f"extraction timed on {path} resized to each size; step: "
                   + (f"{dataset} map {map_round}, query {query}" if rounds else "not measured"))
        if not skip_sizes:
            rows = bench_extract(img, wh, _kinds(features, KINDS), repeats, rounds, frames,
                                 warmup, seed)
            report(rows, typer.echo)
        if caps:
            size = _sizes(sweep_size, "--sweep-size")[0]
            typer.echo(f"sweep at {size[0]}x{size[1]}: features per frame capped at {caps} "
                       "(map and frames); features/frame counted on the timed image")
            swept = bench_extract(img, [size], _kinds(features, KINDS), repeats, rounds,
                                  frames, warmup, seed, caps)
            report_sweep(swept, caps, typer.echo)
