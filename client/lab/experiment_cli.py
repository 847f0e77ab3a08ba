"""``swarmloc experiment`` / ``sweep``: DPSO (product and papers' variant) against the filters.

Each estimator runs from evenly spaced start images of a query round against a map round and
is scored after a warm-up of global convergence (``run_metrics``): error, share within 5 m,
comparisons per frame, share of frames in recovery, accuracy-radius calibration, honesty (how
many badly wrong frames admit it) and, with ``--kidnap``, the frames to recover from a
kidnapping. The product's DPSO and the filters use CLAHE + RootSIFT (unpruned) unless
``--features`` names another type; the papers' DPSO runs on a map built as in the papers
(SIFT, pruned).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from client.lab.methods import METHODS, Method

if TYPE_CHECKING:
    from collections.abc import Sequence

    from client.dataset import Round
    from client.lab.experiments import SimilarityTable
    from client.runs import Run
    from service.maps.positions import PositionsRule
    from service.maps.route_map import RouteMap
    from service.vision.features import Features


def map_for(dataset: Path, rounds: str, papers: bool, features: str = "clahe-rootsift",
            size: tuple[int, int] = (320, 240), max_features: int | None = None,
            positions: PositionsRule | None = None) -> RouteMap:
    """The map of one round (or rounds joined by '+'), built once and kept in DATASET/.maps;
    ``features``: the feature type of our maps (the papers' maps are always the papers' SIFT),
    built at the working size ``size`` with SIFT's cap ``max_features`` (None: the type's);
    ``positions``: our maps' (None: the default, fused with a round's odometry; the papers'
    maps always keep the recorded ones)."""
    from client.dataset import read_round
    from service.maps.positions import round_positions
    from service.maps.route_map import build_map_from_rounds, load_map, save_map
    from service.vision.features import SiftParams, named_params

    names = [r for r in rounds.split("+") if r]
    kind = "-papers" if papers else ("" if features == "clahe-rootsift" else f"-{features}")
    if not papers and size != (320, 240):
        kind += f"-{size[0]}x{size[1]}"
    if not papers and max_features is not None:
        kind += f"-cap{max_features}"
    rule: PositionsRule = "recorded" if papers else (positions or "fused")
    if not papers and rule == "recorded":
        kind += "-recorded"
    path = dataset / ".maps" / f"{'+'.join(names)}{kind}.swmap"
    rnds = [read_round(dataset / r) for r in names]
    if path.is_file():
        kept = load_map(path)
        placed = [round_positions(r, rule)[1] for r in rnds]
        # else built before the camera was known, or with other positions
        if (kept.meta.get("camera") == rnds[0].camera
                and kept.meta.get("source", {}).get("positions") == placed):
            return kept
    params = SiftParams.papers() if papers else named_params(features, *size, max_features)
    m = build_map_from_rounds(rnds, params=params, prune_features=papers, positions=rule)
    return load_map(save_map(m, path))  # loaded: with its checksum, memory-mapped


def table_path(dataset: Path, m: RouteMap, query: str) -> Path:
    """Where ``cached_table`` keeps the table of map ``m`` and query round ``query`` (keyed by
    the map's checksum: a rebuilt map starts a new table; the words matcher's similarities,
    and those with its exact pass on the best images, apart from the exact ones)."""
    kind = (f"-words{m.exact_top or ''}" if m.uses_words else "")
    return dataset / ".maps" / f"{m.meta['checksum'][:16]}{kind}-{query}.table.npy"


def cached_table(dataset: Path, m: RouteMap, rnd: Round,
                 queries: Sequence[Features] | None = None) -> SimilarityTable:
    """The similarity table of a map and a query round, kept in DATASET/.maps between runs
    (``table_path``); ``queries``: the round's features when already extracted."""
    from client.lab.experiments import round_features

    return stored_table(dataset, m, rnd.name,
                        round_features(m, rnd) if queries is None else queries)


def stored_table(dataset: Path, m: RouteMap, query: str, queries: Sequence[Features]
                 ) -> SimilarityTable:
    """The table of map ``m`` and the features ``queries`` of round ``query``, with the
    values kept at ``table_path`` (where ``save_table`` writes them back)."""
    import numpy as np

    from client.lab.experiments import SimilarityTable

    table = SimilarityTable(m, queries)
    path = table_path(dataset, m, query)
    if path.is_file():
        saved = np.load(path)
        if saved.shape == table.table.shape:
            table.table = saved
    first = _first_path(path)
    if table.first is not None and first.is_file():
        saved = np.load(first)
        if saved.shape == table.first.shape:
            table.first = saved
    table.cache_path = path
    return table


def _first_path(path: Path) -> Path:
    """Where a table of a map of two types keeps the first type's own m."""
    return path.with_name(path.name.replace(".table.npy", ".first.npy"))


def save_table(table: SimilarityTable) -> None:
    import numpy as np

    path = table.cache_path
    if path is None:
        return
    for target, values in ((path, table.table), (_first_path(path), table.first)):
        if values is not None:
            tmp = target.with_suffix(".tmp.npy")
            np.save(tmp, values)
            tmp.replace(target)


def metrics(runs: list[Run], warmup: int) -> dict[str, Any]:
    """``client.runs.run_metrics`` of every run after ``warmup``, averaged over the runs."""
    from client.runs import run_metrics, summarize

    return summarize([run_metrics(r, warmup) for r in runs])


def param_value(raw: str) -> Any:
    """A parameter value given on the command line: true or false (any case), an int, a
    float, else the string."""
    if raw.lower() in ("true", "false"):
        return raw.lower() == "true"
    for cast in (int, float):
        try:
            return cast(raw)
        except ValueError:
            pass
    return raw


def parse_params(pairs: list[str] | None) -> dict[str, Any]:
    """``NAME=VALUE`` pairs as a parameter dict (``param_value``)."""
    out = {}
    for pair in pairs or []:
        name, sep, raw = pair.partition("=")
        if not sep or not name:
            raise typer.BadParameter(f"{pair!r}: give a parameter as NAME=VALUE")
        out[name] = param_value(raw)
    return out


def check_feature_type(features: str) -> None:
    """A lab command's ``--features``: one of the feature types, else one line that lists
    them."""
    from service.vision.features import FEATURE_TYPES

    if features not in FEATURE_TYPES:
        raise typer.BadParameter(f"unknown feature type {features!r}; choose one of "
                                 f"{', '.join(FEATURE_TYPES)}")


def parse_seeds(seeds: str) -> list[int]:
    """A lab command's ``--seeds`` (comma-separated integers), else one line that says so."""
    try:
        return [int(x) for x in seeds.split(",") if x.strip()]
    except ValueError:
        raise typer.BadParameter(f"--seeds {seeds!r}: comma-separated integers, e.g. 0,7,11"
                                 ) from None


def world_with(data: Path, seed: int, rounds: list[str], render: str) -> Path:
    """DATA/wSEED, a world of a lab command, if it holds every one of ``rounds``; else one
    line that names the missing round and the command that renders the world's ``render``
    rounds."""
    world = data / f"w{seed}"
    for r in rounds:
        if not (world / r).is_dir():
            raise typer.BadParameter(f"{world} has no round {r}; render it with swarmloc "
                                     f"world render {world} --seed {seed} --rounds {render}")
    return world


def _starts(n: int, count: int) -> list[int]:
    return [k * n // count for k in range(count)]


def _runs(m: RouteMap, table: SimilarityTable, rnd: Round, method: Method,
          starts: list[int], seed: int, kidnap: bool = False,
          odometry: bool = False) -> list[Run]:
    from client.lab.experiments import run

    return [run(m, table.fresh() if m.exact_top else table, rnd, method.estimator,
                method.params, seed=seed + k, start=s, kidnap=kidnap, odometry=odometry)
            for k, s in enumerate(starts)]


def _kidnap(m: RouteMap, table: SimilarityTable, rnd: Round, method: Method,
            starts: list[int], seed: int, odometry: bool = False) -> list[int | None]:
    from client.runs import frames_to_recover

    return [frames_to_recover(r)
            for r in _runs(m, table, rnd, method, starts, seed, True, odometry)]


def _median(values: list[int]) -> float:
    import numpy as np

    return float(np.median(values)) if values else float("nan")


def _fmt(x: float | None, pct: bool = False) -> str:
    if x is None or x != x:  # undefined (None) or NaN
        return "–"
    return f"{100 * x:.1f}%" if pct else f"{x:.2f}"


def experiment(
    dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
    map_round: Annotated[str, typer.Option(
        "--map", help="round used as the map; rounds joined by '+' make a multi-condition map")]
    = "sunny1",
    query: Annotated[str, typer.Option(help="comma-separated rounds replayed against it")]
    = "sunny2,cloudy1",
    methods: Annotated[str, typer.Option(help=f"comma-separated, of {list(METHODS)}")]
    = ",".join(METHODS),
    starts: Annotated[int, typer.Option(help="runs from evenly spaced start images")] = 8,
    warmup: Annotated[int, typer.Option(help="frames of global convergence not scored")] = 20,
    kidnap: Annotated[bool, typer.Option(help="also run the kidnapping experiment")] = True,
    seed: int = 0,
    features: Annotated[str, typer.Option(
        help="feature type of the map for our estimators: clahe-rootsift, xfeat or "
             "clahe-rootsift+xfeat (the papers' variants always use the papers' SIFT)")]
    = "clahe-rootsift",
    matcher: Annotated[str, typer.Option(
        help="matcher of our maps: auto (the service's default), exact, or words (the "
             "inverted file), as SWARMLOC_MATCHER")]
    = "auto",
    exact_top: Annotated[int, typer.Option(
        help="with --matcher words: the best N images of each comparison matched again "
             "exactly")] = 0,
    param: Annotated[list[str] | None, typer.Option(
        help="NAME=VALUE: an estimator parameter for every chosen method, beside its own "
             "(repeatable), e.g. --param metric_disagree_m=0")] = None,
    size: Annotated[str, typer.Option(
        help="working size WxH of our maps and frames (the papers' keep theirs)")] = "320x240",
    max_features: Annotated[int | None, typer.Option(
        help="SIFT's features per map image and frame of our maps (0: all; default: the "
             "type's), as swarmloc map build --max-features")] = None,
    odometry: Annotated[bool, typer.Option(
        help="every frame carries its round's wheel odometry (odometry.csv), as swarmloc "
             "replay sends it by default; at the kidnap the wheels see an ordinary step")]
    = False,
) -> None:
    """Every estimator's error (mean, median, within 5 m), comparisons, share of frames in
    recovery, accuracy_m calibration (tracked frames within it), honesty (frames with error
    > 10 m reported lost or recovering), speed error and kidnap recovery (back within 5 m
    for 5 frames)."""
    from client.dataset import ODOMETRY_FILE, read_round
    from service.api.models import MATCHERS
    from service.vision.features import named_params

    chosen = [x for x in methods.split(",") if x]
    extra = parse_params(param)
    unknown = [x for x in chosen if x not in METHODS]
    if unknown:
        raise typer.BadParameter(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
    check_feature_type(features)
    if matcher not in MATCHERS:
        raise typer.BadParameter(f"unknown matcher {matcher!r}; choose from {list(MATCHERS)}")
    if exact_top and matcher != "words":
        raise typer.BadParameter("--exact-top goes with --matcher words")
    try:
        w, h = (int(v) for v in size.lower().split("x"))
        named_params(features, w, h, max_features)  # checks the size and the cap
    except ValueError as exc:
        raise typer.BadParameter(f"--size / --max-features: {exc}") from None
    queries = [x for x in query.split(",") if x]
    if odometry:  # before any map is built
        for q in queries:
            if not (dataset / q / ODOMETRY_FILE).is_file():
                raise typer.BadParameter(f"round {q} has no odometry.csv: run without "
                                         "--odometry")
    maps = {papers: map_for(dataset, map_round, papers, features, (w, h), max_features)
            for papers in {METHODS[c].papers_map for c in chosen}}
    if matcher == "words" and False in maps:
        maps[False] = maps[False].with_words(exact_top=exact_top)
    elif matcher != "auto" and False in maps:
        maps[False] = maps[False].with_matcher(matcher)
    for q in queries:
        rnd = read_round(dataset / q)
        tables = {papers: cached_table(dataset, m, rnd) for papers, m in maps.items()}
        start_list = _starts(len(rnd), starts)
        typer.echo(f"\n{map_round} (map) vs {q}: {starts} runs x {len(rnd)} frames, errors "
                   f"after {warmup} frames{', with odometry' if odometry else ''}")
        typer.echo(f"{'method':14s} {'mean err (m)':>13s} {'median':>7s} {'<=5 m':>7s} "
                   f"{'comp/frame':>10s} {'recov':>6s} {'calib':>6s} {'honest':>7s} "
                   f"{'speed':>6s} {'kidnap: back/runs, median':>26s}")
        rows = {}
        for name in chosen:
            method = METHODS[name]
            if extra:
                method = Method(method.estimator, {**method.params, **extra}, method.papers_map)
            m, table = maps[method.papers_map], tables[method.papers_map]
            r = metrics(_runs(m, table, rnd, method, start_list, seed, odometry=odometry),
                        warmup)
            rows[name] = r
            kid = ""
            if kidnap:
                rec = _kidnap(m, table, rnd, method, start_list, seed, odometry)
                done = [f for f in rec if f is not None]
                kid = f"{len(done)}/{len(rec)}, {_fmt(_median(done))} {rec}"
            typer.echo(f"{name:14s} {r['error_mean_m']:6.2f} ± {r['error_mean_std_m']:4.2f} "
                       f"{r['error_median_m']:7.2f} {_fmt(r['within_5m'], True):>7s} "
                       f"{r['comparisons_per_frame']:10.1f} "
                       f"{_fmt(r['bad_status_share'], True):>6s} "
                       f"{_fmt(r['calibration'], True):>6s} {_fmt(r['honesty'], True):>7s} "
                       f"{_fmt(r['speed_error_rel'], True):>6s} {kid}")
        for table in tables.values():
            save_table(table)
        if "DPSO-80" in rows and "PF-l-300" in rows:
            d, pf = rows["DPSO-80"], rows["PF-l-300"]
            ratio = d["comparisons_per_frame"] / pf["comparisons_per_frame"]
            typer.echo(f"DPSO-80 / PF-l-300: error x{d['error_mean_m'] / pf['error_mean_m']:.2f}"
                       f", comparisons x{ratio:.2f}")


def sweep(
    dataset: Annotated[Path, typer.Argument(help="dataset with the rounds")],
    param: Annotated[str, typer.Option(help="DPSO parameter to vary, e.g. distinct_ratio")],
    values: Annotated[str, typer.Option(help="comma-separated values, e.g. 2,3,4")],
    map_round: Annotated[str, typer.Option("--map", help="round used as the map")] = "sunny1",
    query: Annotated[str, typer.Option(help="comma-separated query rounds")] = "sunny2,cloudy1",
    variant: Annotated[str, typer.Option(help="DPSO variant: swarmloc or paper")] = "swarmloc",
    starts: int = 9,
    warmup: int = 20,
) -> None:
    """DPSO mean error, comparisons, share of frames in recovery and kidnap recovery for each
    value of one parameter (how the choices in docs/research/papers.md were made)."""
    from client.dataset import read_round

    papers = variant == "paper"
    m = map_for(dataset, map_round, papers)
    tables = {}
    for q in [x for x in query.split(",") if x]:
        rnd = read_round(dataset / q)
        tables[q] = (rnd, cached_table(dataset, m, rnd))
    for raw in values.split(","):
        value: Any = float(raw) if "." in raw or "e" in raw else int(raw)
        method = Method("dpso", {"variant": variant, param: value}, papers)
        for q, (rnd, table) in tables.items():
            start_list = _starts(len(rnd), starts)
            r = metrics(_runs(m, table, rnd, method, start_list, 0), warmup)
            kid = _kidnap(m, table, rnd, method, start_list, 0)
            done = [f for f in kid if f is not None]
            typer.echo(f"{param}={value} {map_round} vs {q}: mean error {r['error_mean_m']:.2f} m"
                       f", {r['comparisons_per_frame']:.1f} comparisons, recovering "
                       f"{100 * r['bad_status_share']:.1f} % of frames, kidnap recovery median "
                       f"{_median(done):.0f} frames, never recovered "
                       f"{len(kid) - len(done)}/{len(kid)}")
