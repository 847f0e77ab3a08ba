"""How to combine CLAHE + RootSIFT and XFeat similarities (issue 28): a measurement, no DPSO.

For a rendered world (``/work/data/wN``: a map round and query rounds with ``truth.csv``),
both feature types are extracted for every map image and every ``step``-th query frame, and
m(frame, image) is computed for every pair with the map's own similarity of each type. Then
each fusion rule turns the two score tables into one and is judged per query round on:

- ``within5``: the share of frames whose best map image lies within 5 m of the truth;
- ``ratio``: the best score within 2 m of the truth over the best score more than 10 m away
  (median and 10th percentile over frames; > 1 where the true place wins);
- ``distinct``: the best score within 2 m over the median of the images more than 10 m away,
  floored as DPSO's lost detection floors it (``distinct_ratio`` judges this; the share
  of frames at >= 3 is printed).

The rules need no labels: each type's score is divided by a normaliser computed from the
map's own images at build time: ``chance`` (the median m of map images more than 20 m
apart), ``typical`` (the median m of consecutive map images) or ``span`` ((m - chance) /
(typical - chance)). The fused score is then put back on RootSIFT's scale (times RootSIFT's
normaliser), so that the estimator's absolute floors keep their meaning.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from client.dataset import read_round
from service.maps.route_map import build_map
from service.vision.features import extract, named_params

TYPES = ("clahe-rootsift", "xfeat")
NEAR_M, FAR_M, WITHIN_M, CHANCE_M = 2.0, 10.0, 5.0, 20.0


@dataclass
class Tables:
    """Score tables of one world: per type, queries x map images and map-image statistics."""

    map_xy: np.ndarray  # (n, 2)
    queries: dict[str, np.ndarray]  # round -> (q, 2) true positions
    scores: dict[str, dict[str, np.ndarray]]  # type -> round -> (q, n)
    consecutive: dict[str, np.ndarray]  # type -> (n - 1,) m(i, i + 1)
    far: dict[str, np.ndarray]  # type -> sampled m(i, j), |xi - xj| > CHANCE_M


def score_tables(world: Path, map_round: str, rounds: list[str], step: int = 8,
                 far_images: int = 64, far_pairs: int = 16, seed: int = 0) -> Tables:
    mr = read_round(world / map_round)
    qrs = {r: read_round(world / r) for r in rounds}
    xy = np.asarray(mr.reference_xy, float)
    rng = np.random.default_rng(seed)
    scores: dict[str, dict[str, np.ndarray]] = {}
    consecutive, far = {}, {}
    images = [mr.load_image(i) for i in range(len(mr))]
    for kind in TYPES:
        t0 = time.perf_counter()
        m = build_map("study", images, xy, list(mr.images), params=named_params(kind),
                      place_index=False)
        ids = range(m.n_images)
        consecutive[kind] = np.array([m.similarity(np.asarray(m.codes_of(i)), [i + 1])[0]
                                      for i in range(m.n_images - 1)])
        vals = []
        rng_k = np.random.default_rng(seed)
        for i in rng_k.choice(m.n_images, min(far_images, m.n_images), replace=False):
            d = np.linalg.norm(xy - xy[i], axis=1)
            cand = np.flatnonzero(d > CHANCE_M)
            pick = rng_k.choice(cand, min(far_pairs, len(cand)), replace=False)
            vals.append(m.similarity(np.asarray(m.codes_of(int(i))), pick))
        far[kind] = np.concatenate(vals)
        scores[kind] = {}
        for r, qr in qrs.items():
            rows = []
            for i in range(0, len(qr), step):
                f = extract(qr.load_image(i), m.feature_params)
                rows.append(m.similarity(f.codes, ids))
            scores[kind][r] = np.array(rows)
        print(f"  {world.name} {kind}: {time.perf_counter() - t0:.0f} s", flush=True)
    del rng
    queries = {r: np.asarray(qr.reference_xy, float)[::step] for r, qr in qrs.items()}
    return Tables(xy, queries, scores, consecutive, far)


def normalisers(t: Tables, kind: str) -> dict[str, float]:
    return {"chance": float(np.median(t.far[kind])), "chance_mean": float(np.mean(t.far[kind])),
            "typical": float(np.median(t.consecutive[kind]))}


def fuse(t: Tables, rnd: str, rule: str) -> np.ndarray:
    """The fused (q, n) table of one rule: ``rootsift``, ``xfeat``, ``COMBINE/NORM`` with
    COMBINE in max, sum, geo and NORM in chance, typical, span, or ``max/affine`` and
    ``mean/affine``: RootSIFT's score and XFeat's mapped affinely onto RootSIFT's scale
    (chance level to chance level, typical to typical), the larger or the mean."""
    r, x = t.scores["clahe-rootsift"][rnd], t.scores["xfeat"][rnd]
    if rule == "rootsift":
        return r
    if rule == "xfeat":
        return x
    combine, norm = rule.split("/")
    nr, nx = normalisers(t, "clahe-rootsift"), normalisers(t, "xfeat")
    if norm == "affine":  # XFeat mapped onto RootSIFT's scale: chance -> chance, typical ->
        cr, cx = nr["chance_mean"], nx["chance_mean"]  # typical; RootSIFT as it is
        x2 = cr + (x - cx) * (nr["typical"] - cr) / (nx["typical"] - cx)
        both = np.stack([r, x2])
        out = both.mean(axis=0) if combine == "mean" else both.max(axis=0)
        return np.maximum(out, 0.0)
    if norm == "span":
        a = np.maximum(r - nr["chance_mean"], 0) / (nr["typical"] - nr["chance_mean"])
        b = np.maximum(x - nx["chance_mean"], 0) / (nx["typical"] - nx["chance_mean"])
        scale = nr["typical"] - nr["chance_mean"]
    else:
        key = "chance_mean" if norm == "chance" else norm  # a median chance may be 0
        a, b, scale = r / nr[key], x / nx[key], nr[key]
    if combine == "max":
        out = np.maximum(a, b)
    elif combine == "sum":
        out = (a + b) / 2
    elif combine == "geo":
        out = np.sqrt(a * b)
    else:
        raise ValueError(rule)
    return out * scale


RULES = ("rootsift", "xfeat", *(f"{c}/{n}" for n in ("chance", "typical", "span")
                                 for c in ("max", "sum", "geo")), "max/affine", "mean/affine")


def judge(t: Tables, rnd: str, table: np.ndarray, floor: float = 0.004) -> dict[str, float]:
    q = t.queries[rnd]
    d = np.linalg.norm(q[:, None, :] - t.map_xy[None, :, :], axis=2)
    best = table.argmax(axis=1)
    within = float(np.mean(d[np.arange(len(q)), best] <= WITHIN_M))
    near = np.where(d <= NEAR_M, table, -np.inf).max(axis=1)
    far_best = np.where(d > FAR_M, table, -np.inf).max(axis=1)
    far_med = np.array([np.median(row[dd > FAR_M]) for row, dd in zip(table, d, strict=True)])
    ratio = near / np.maximum(far_best, 1e-9)
    distinct = near / np.maximum(far_med, 0.25 * floor)
    return {"within5": within, "ratio_med": float(np.median(ratio)),
            "ratio_p10": float(np.percentile(ratio, 10)),
            "wins": float(np.mean(ratio > 1)), "distinct3": float(np.mean(distinct >= 3))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("worlds", nargs="+")
    ap.add_argument("--map", default="sunny1")
    ap.add_argument("--query", default="cloudy1,dusk1")
    ap.add_argument("--step", type=int, default=8)
    ap.add_argument("--cache", default="/tmp/fusion-study")
    args = ap.parse_args(argv)
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    rounds = args.query.split(",")
    results = {}
    for w in args.worlds:
        world = Path(w)
        f = cache / f"{world.name}-{args.map}-{'_'.join(rounds)}-{args.step}.npz"
        if f.is_file():
            z = np.load(f)
            t = Tables(z["map_xy"], {r: z[f"q_{r}"] for r in rounds},
                       {k: {r: z[f"s_{k}_{r}"] for r in rounds} for k in TYPES},
                       {k: z[f"c_{k}"] for k in TYPES}, {k: z[f"f_{k}"] for k in TYPES})
        else:
            t = score_tables(world, args.map, rounds, args.step)
            arrays: dict[str, np.ndarray] = {
                "map_xy": t.map_xy, **{f"q_{r}": t.queries[r] for r in rounds},
                **{f"s_{k}_{r}": t.scores[k][r] for k in TYPES for r in rounds},
                **{f"c_{k}": t.consecutive[k] for k in TYPES},
                **{f"f_{k}": t.far[k] for k in TYPES}}
            np.savez(f, **arrays)  # type: ignore[arg-type]
        for k in TYPES:
            print(f"{world.name} {k} normalisers: " + ", ".join(
                f"{a} {b:.4f}" for a, b in normalisers(t, k).items()))
        for r in rounds:
            for rule in RULES:
                results[(world.name, r, rule)] = judge(t, r, fuse(t, r, rule))
    cols = ("within5", "ratio_med", "ratio_p10", "wins", "distinct3")
    print(f"\n{'world':6} {'round':8} {'rule':12} " + " ".join(f"{c:>9}" for c in cols))
    for (w, r, rule), v in results.items():
        print(f"{w:6} {r:8} {rule:12} " + " ".join(f"{v[c]:9.3f}" for c in cols))
    print(f"\nmean over worlds and rounds ({len(args.worlds)} x {len(rounds)}):")
    for rule in RULES:
        vs = [v for (w, r, ru), v in results.items() if ru == rule]
        worst = min(v["within5"] for v in vs)
        print(f"  {rule:12} " + " ".join(f"{c} {np.mean([v[c] for v in vs]):.3f}"
                                          for c in cols) + f"  worst within5 {worst:.3f}")
    (cache / "results.json").write_text(json.dumps(
        {"/".join(k): v for k, v in results.items()}, indent=1))


if __name__ == "__main__":
    main()
