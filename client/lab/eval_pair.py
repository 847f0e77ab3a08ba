"""Two traversals known only by frame correspondence (Gardens Point day/night): does the
service admit that it cannot match, instead of tracking a wrong place?

Such pairs carry no metric poses: ``poses.csv`` lists ``filename,index``, frame i of one
folder showing the place of frame i of the other. The frames are placed ``spacing`` metres
apart along a straight line (index * spacing), the map is built from one folder and the
other folder's frames are replayed along the route and back, ``passes`` times.

Judged per frame: whether the best-matching map image is the frame's own place (exactly, or
within one frame: +-1), and, over the replays, whether the estimator reports ``tracking`` at a
map image within one frame of the truth (the map image nearest to the estimate).
"""

from __future__ import annotations

import csv
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from client.dataset import DatasetError, Round, check_image
from client.lab.experiments import SimilarityTable, run
from client.runs import BAD_STATUS, WRONG_M
from service.maps.route_map import build_map_from_rounds
from service.vision.features import SiftParams, extract

if TYPE_CHECKING:
    from service.vision.features import FeatureParams


def read_indexed_frames(folder: Path, spacing: float) -> Round:
    """The frames of ``folder/poses.csv`` (``filename,index``) at x = index * spacing."""
    poses = folder / "poses.csv"
    if not poses.is_file():
        raise DatasetError(f"{folder}: no poses.csv (filename,index)")
    names: list[str] = []
    index: list[int] = []
    with poses.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None or not {"filename", "index"} <= set(reader.fieldnames):
            raise DatasetError(f"{poses}: the header must name the columns filename,index")
        for line, row in enumerate(reader, start=2):
            name = (row.get("filename") or "").strip()
            try:
                i = int(row.get("index") or "")
            except ValueError:
                raise DatasetError(f"{poses}, line {line}: index {row.get('index')!r} is not "
                                   "an integer") from None
            check_image(folder, name, f"{poses}, line {line}")
            names.append(name)
            index.append(i)
    if len(names) < 2:
        raise DatasetError(f"{poses}: needs at least 2 frames")
    if len(set(index)) != len(index):
        raise DatasetError(f"{poses}: an index appears twice")
    order = np.argsort(index, kind="stable")
    xy = np.column_stack([np.asarray(index, float)[order] * spacing, np.zeros(len(names))])
    return Round(folder.name, folder, tuple(names[k] for k in order), xy, None, xy.copy(), None)


@dataclass(frozen=True)
class PairResult:
    frames: int  # query frames (distinct)
    best_is_true: int  # query frames whose best-matching map image is their own place
    best_within_one: int  # ... is their own place or one of its neighbours (+-1 frame)
    true_similarity_median: float  # m of each frame's own place
    replayed: int  # frames replayed, over all seeds
    status: dict[str, int]  # status counts over all replayed frames
    wrong: int  # replayed frames with error > WRONG_M
    honest: float | None  # share of those reported lost or recovering
    tracking_wrong: int  # replayed frames reported tracking with error > WRONG_M
    tracking_within_one: int  # replayed frames reported tracking within +-1 frame
    frames_tracked: int  # query frames tracking within +-1 frame in at least half their visits


def eval_pair(map_dir: Path, query_dir: Path, *, spacing: float = 2.5, width: int = 640,
              height: int = 360, passes: int = 4, estimator: str = "dpso",
              seeds: int = 3, params: FeatureParams | None = None,
              estimator_params: dict[str, Any] | None = None) -> PairResult:
    """Map from ``map_dir``, ``query_dir`` replayed there and back ``passes`` times, once per
    seed. ``params``: the map's feature type (default CLAHE + RootSIFT at ``width`` x
    ``height``; when given, its own working size counts); ``estimator_params``: the
    estimator's parameters beyond its defaults."""
    params = params or SiftParams(width=width, height=height)
    map_round = read_indexed_frames(map_dir, spacing)
    query = read_indexed_frames(query_dir, spacing)
    m = build_map_from_rounds([map_round], params=params)
    table = SimilarityTable(m, [extract(query.load_image(i), params) for i in range(len(query))])
    n = len(query)
    ids = np.arange(m.n_images)
    rows = np.array([table.scores(q, ids) for q in range(n)])  # every frame x every image
    own = m.nearest(query.xy)[0]  # each frame's own place
    best = np.argmax(rows, axis=1)
    best_is_true = int(np.sum(best == own))
    best_within_one = int(np.sum(np.abs(best - own) <= 1))
    true_m = float(np.median(rows[np.arange(n), own]))
    there_and_back = np.concatenate([np.arange(n), np.arange(n - 2, 0, -1)])
    order = np.tile(there_and_back, passes)
    replay = query.subset(order.tolist())
    sub = SimilarityTable(m, [table.queries[int(q)] for q in order])
    sub.table = table.table[order]
    sub.first = None if table.first is None else table.first[order]
    status: Counter[str] = Counter()
    wrong = tracking_wrong = 0
    admitted = 0
    near_visits = np.zeros(n, np.int64)  # per query frame: visits tracked within +-1 frame
    for seed in range(seeds):
        res = run(m, sub, replay, estimator, estimator_params, seed=seed)
        st = np.asarray(res.status)
        big = res.errors > WRONG_M
        status.update(st.tolist())
        wrong += int(big.sum())
        admitted += int(np.isin(st[big], list(BAD_STATUS)).sum())
        tracking_wrong += int(((st == "tracking") & big).sum())
        at = m.nearest(res.est_xy)[0]
        truth = m.nearest(res.true_xy)[0]
        near = (st == "tracking") & (np.abs(at - truth) <= 1)
        near_visits += np.bincount(order[res.frames][near], minlength=n)
    visits = np.bincount(order, minlength=n) * seeds
    return PairResult(n, best_is_true, best_within_one, true_m, len(order) * seeds,
                      dict(status), wrong, admitted / wrong if wrong else None, tracking_wrong,
                      int(near_visits.sum()), int(np.sum(2 * near_visits >= visits)))
