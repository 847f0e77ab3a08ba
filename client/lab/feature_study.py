"""``swarmloc bench feature-types``: ORB and AKAZE (binary descriptors, Hamming distance)
against the map's default CLAHE + RootSIFT, on accuracy (the papers' protocol: DPSO-80 and
PF-l-300 through ``client.lab.experiments``) and time per frame, in the same lighting and
across lighting.

Every type sees the same frames after the same CLAHE. The binary similarity is the papers'
m(A, B) with Hamming distances in place of angles: reciprocal nearest neighbours whose best
distance is below ``ratio`` x the second best both ways (an exact tie never passes), over
min(|A|, |B|). Distances come from NumKong's packed Hamming kernel, the two best per row and
column from one numba pass: the fair fast version of ``BFMatcher.knnMatch`` both ways.

The estimators keep their default parameters (tuned on RootSIFT similarities). Positions,
frames and protocol come from the map of the dataset's map round; only the similarity table
differs between types.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

TYPES = ("rootsift", "orb", "akaze")  # "orbN": ORB keeping the N best features
ORB_FEATURES = 500  # OpenCV's default
HAMMING_RATIO = 0.8  # Lowe's ratio on Hamming distances (ORB's usual setting)


def _clahe(image: np.ndarray) -> np.ndarray:
    import cv2

    from service.vision.features import SiftParams, to_working_size

    p = SiftParams()
    gray = to_working_size(image, p)
    tiles = (p.clahe_tile, p.clahe_tile)
    return cv2.createCLAHE(clipLimit=p.clahe_clip, tileGridSize=tiles).apply(gray)


def akaze_available() -> bool:
    import cv2

    return hasattr(cv2, "AKAZE_create") or hasattr(getattr(cv2, "xfeatures2d", None),
                                                   "AKAZE_create")


def extractor(kind: str) -> Callable[[np.ndarray], np.ndarray]:
    """image -> descriptors: uint8 codes (RootSIFT, (n, 128)) or packed bits (ORB (n, 32),
    AKAZE's MLDB (n, 61)). ``orb`` keeps OpenCV's default 500 features, ``orbN`` N."""
    import cv2

    from service.vision.features import extract

    if kind == "rootsift":
        return lambda image: extract(image).codes
    if kind.startswith("orb") and (kind[3:].isdigit() or kind == "orb"):
        n = int(kind[3:] or ORB_FEATURES)

        def make() -> Any:
            return cv2.ORB_create(nfeatures=n)
    elif kind == "akaze":
        if not akaze_available():
            raise ValueError("this OpenCV has no AKAZE (OpenCV 5 moved it to the contrib "
                             "build: opencv-contrib-python-headless)")
        make = getattr(cv2, "AKAZE_create", None) or cv2.xfeatures2d.AKAZE_create
    else:
        raise ValueError(f"unknown feature type {kind!r}; use one of {TYPES}")

    def run(image: np.ndarray) -> np.ndarray:
        _, d = make().detectAndCompute(_clahe(image), None)
        return np.ascontiguousarray(d) if d is not None else np.zeros((0, 32), np.uint8)
    return run


def _top2_kernel() -> Callable[..., int]:
    import numba

    @numba.njit(cache=True, nogil=True)
    def mutual_ratio(d: np.ndarray, ratio: float) -> int:  # pragma: no cover - compiled
        na, nb = d.shape
        big = np.int64(1) << 40
        r1 = np.full(na, big)
        r2 = np.full(na, big)
        ri = np.zeros(na, np.int64)
        c1 = np.full(nb, big)
        c2 = np.full(nb, big)
        ci = np.zeros(nb, np.int64)
        for i in range(na):
            for j in range(nb):
                v = np.int64(d[i, j])
                if v < r1[i]:
                    r2[i] = r1[i]
                    r1[i] = v
                    ri[i] = j
                elif v < r2[i]:
                    r2[i] = v
                if v < c1[j]:
                    c2[j] = c1[j]
                    c1[j] = v
                    ci[j] = i
                elif v < c2[j]:
                    c2[j] = v
        count = 0
        for i in range(na):
            j = ri[i]
            if ci[j] == i and r1[i] < ratio * r2[i] and c1[j] < ratio * c2[j]:
                count += 1
        return count

    return mutual_ratio


class HammingMatcher:
    """m(A, B) on binary descriptors (see the module docstring); map sets packed once."""

    def __init__(self, ratio: float = HAMMING_RATIO) -> None:
        self.ratio = ratio
        self._kernel = _top2_kernel()

    @staticmethod
    def prepare(bits: np.ndarray) -> tuple[Any, int]:
        import numkong

        return numkong.hammings_pack(np.ascontiguousarray(bits, np.uint8)), len(bits)

    def counts(self, a: np.ndarray, prepared: Sequence[tuple[Any, int]]) -> np.ndarray:
        import numkong

        out = np.zeros(len(prepared), np.int64)
        if len(a) < 2:
            return out
        a = np.ascontiguousarray(a, np.uint8)
        for k, (packed, nb) in enumerate(prepared):
            if nb >= 2:
                d = np.asarray(numkong.hammings_packed(a, packed))
                out[k] = self._kernel(d, self.ratio)
        return out

    def scores(self, a: np.ndarray, prepared: Sequence[tuple[Any, int]]) -> np.ndarray:
        nb = np.array([n for _, n in prepared], np.int64)
        denom = np.maximum(np.minimum(len(a), nb), 1)
        return self.counts(a, prepared) / denom


def hamming_reference(a: np.ndarray, b: np.ndarray, ratio: float = HAMMING_RATIO) -> int:
    """The same count written plainly (NumPy popcounts, argsort): for the tests."""
    if len(a) < 2 or len(b) < 2:
        return 0
    x = np.bitwise_xor(a[:, None, :], b[None, :, :])
    d = np.unpackbits(x, axis=2).sum(axis=2).astype(np.int64)
    rows = np.sort(d, axis=1)
    cols = np.sort(d, axis=0)
    count = 0
    for i in range(len(a)):
        j = int(np.argmin(d[i]))
        if int(np.argmin(d[:, j])) != i:
            continue
        if rows[i, 0] < ratio * rows[i, 1] and cols[0, j] < ratio * cols[1, j]:
            count += 1
    return count


class FeatureTable:
    """m(query frame q, map image i) of one feature type, computed on first use and kept;
    the interface of ``client.lab.experiments.SimilarityTable`` (``scores(q, ids)``)."""

    def __init__(self, kind: str, queries: list[np.ndarray], map_sets: list[np.ndarray],
                 route_map: Any) -> None:
        from service.vision.matcher import prepare

        self.kind = kind
        self.queries = queries
        self.table = np.full((len(queries), len(map_sets)), np.nan)
        self.seconds = 0.0  # thread CPU time spent computing similarities
        self.computed = 0
        self._prep: Callable[[np.ndarray], Any]
        if kind == "rootsift":
            self._prepared: list[Any] = [None] * len(map_sets)
            self._prep = lambda codes: prepare(codes)
            self._map = route_map
        else:
            self._hamming = HammingMatcher()
            self._prepared = [None] * len(map_sets)
            self._prep = self._hamming.prepare
        self._sets = map_sets

    def _prepared_set(self, i: int) -> Any:
        p = self._prepared[i]
        if p is None:
            p = self._prepared[i] = self._prep(self._sets[i])
        return p

    def compute(self, q: int, ids: np.ndarray) -> np.ndarray:
        from service.vision.matcher import match_batch_u8

        sets = [self._prepared_set(int(i)) for i in ids]
        t0 = time.thread_time()
        if self.kind == "rootsift":
            s = match_batch_u8(self.queries[q], sets, self._map.delta).scores
        else:
            s = self._hamming.scores(self.queries[q], sets)
        self.seconds += time.thread_time() - t0
        self.computed += len(ids)
        return np.asarray(s, float)

    def scores(self, q: int, ids: np.ndarray) -> np.ndarray:
        row = self.table[q]
        missing = ids[np.isnan(row[ids])]
        if len(missing):
            row[missing] = self.compute(q, missing)
        return row[ids]


@dataclass
class TypeResult:
    kind: str
    query: str
    features: float  # per query frame (mean)
    extract_ms: float  # per frame, thread CPU, median
    match_ms: float  # per comparison, thread CPU, median over sample frames
    errors: dict[str, float]  # method -> mean error after the warm-up (m)
    within_5m: dict[str, float]
    comparisons: dict[str, float]  # method -> comparisons per frame

    def frame_ms(self, method: str) -> float:
        """Extraction + the method's comparisons per frame x time per comparison."""
        return self.extract_ms + self.comparisons[method] * self.match_ms


def _descriptors(kind: str, rnd: Any, cache: Path | None) -> list[np.ndarray]:
    """Every frame's descriptors (kept in ``cache`` as .npz between runs)."""
    path = cache / f"{rnd.path.parent.name}-{rnd.name}-{kind}.npz" if cache else None
    if path is not None and path.is_file():
        z = np.load(path)
        return [z[f"f{i}"] for i in range(len(rnd))]
    fn = extractor(kind)
    out = [fn(rnd.load_image(i)) for i in range(len(rnd))]
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **{f"f{i}": d for i, d in enumerate(out)})  # type: ignore[arg-type]
        tmp.replace(path)
    return out


def _timing(kind: str, rnd: Any, table: FeatureTable, route_map: Any, frames: int = 12,
            k: int = 20) -> tuple[float, float]:
    """(extraction ms per frame, matching ms per comparison): thread CPU, medians over
    ``frames`` frames spread over the round, each against its ``k`` nearest map images."""
    fn = extractor(kind)
    idx = [int(len(rnd) * (j + 0.5) / frames) for j in range(frames)]
    ext, match = [], []
    fn(rnd.load_image(idx[0]))  # first-call set-up outside the timing
    for q in idx:
        image = rnd.load_image(q)
        t0 = time.thread_time()
        fn(image)
        ext.append(time.thread_time() - t0)
        _, ids = route_map._tree.query(rnd.reference_xy[q], k=k)
        ids = np.asarray(ids, np.int64)
        table.compute(q, ids)  # prepares the sets: the timed call below runs on warm ones
        t0 = time.thread_time()
        table.compute(q, ids)
        match.append((time.thread_time() - t0) / k)
    return 1e3 * float(np.median(ext)), 1e3 * float(np.median(match))


def study(dataset: Path, map_round: str, queries: list[str], kinds: list[str],
          methods: list[str], starts: int, warmup: int, cache: Path | None,
          emit: Callable[[str], None] = print) -> list[TypeResult]:
    """For each query round and feature type: accuracy of ``methods`` and time per frame."""
    from threadpoolctl import threadpool_limits

    from client.dataset import read_round
    from client.lab.experiment_cli import _runs, _starts, map_for, metrics
    from client.lab.methods import METHODS
    from service.vision.matcher import warm_up

    warm_up()
    route_map = map_for(dataset, map_round, False) if cache is None else _map(dataset,
                                                                              map_round, cache)
    map_rnd = read_round(dataset / map_round)
    out = []
    with threadpool_limits(1, "blas"):
        map_desc = {k: _descriptors(k, map_rnd, cache) for k in kinds}
        for qname in queries:
            rnd = read_round(dataset / qname)
            for kind in kinds:
                t0 = time.perf_counter()
                qdesc = _descriptors(kind, rnd, cache)
                table = FeatureTable(kind, qdesc, map_desc[kind], route_map)
                _load_table(table, cache, dataset, qname)
                errs, within, comps = {}, {}, {}
                for name in methods:
                    m = metrics(_runs(route_map, table, rnd, METHODS[name],  # type: ignore[arg-type]
                                      _starts(len(rnd), starts), 0), warmup)
                    errs[name], within[name] = m["error_mean_m"], m["within_5m"]
                    comps[name] = m["comparisons_per_frame"]
                _save_table(table, cache, dataset, qname)
                ext_ms, match_ms = _timing(kind, rnd, table, route_map)
                r = TypeResult(kind, qname, float(np.mean([len(d) for d in qdesc])), ext_ms,
                               match_ms, errs, within, comps)
                out.append(r)
                emit(line(r, methods) + f"   ({time.perf_counter() - t0:.0f} s)")
    return out


def _map(dataset: Path, map_round: str, cache: Path) -> Any:
    """The map round's default map, built into ``cache`` (never into the dataset)."""
    from client.dataset import read_round
    from service.maps.route_map import build_map_from_rounds, load_map, save_map

    path = cache / f"{dataset.name}-{map_round}.swmap"
    if path.is_file():
        return load_map(path)
    cache.mkdir(parents=True, exist_ok=True)
    return load_map(save_map(build_map_from_rounds([read_round(dataset / map_round)]), path))


def _table_path(table: FeatureTable, cache: Path | None, dataset: Path, query: str
                ) -> Path | None:
    if cache is None:
        return None
    return cache / f"{dataset.name}-{query}-{table.kind}-{HAMMING_RATIO}.table.npy"


def _load_table(table: FeatureTable, cache: Path | None, dataset: Path, query: str) -> None:
    path = _table_path(table, cache, dataset, query)
    if path is not None and path.is_file():
        saved = np.load(path)
        if saved.shape == table.table.shape:
            table.table = saved


def _save_table(table: FeatureTable, cache: Path | None, dataset: Path, query: str) -> None:
    path = _table_path(table, cache, dataset, query)
    if path is not None:
        tmp = path.with_name(path.name + ".tmp.npy")
        np.save(tmp, table.table)
        tmp.replace(path)


def header(methods: list[str]) -> str:
    cols = "".join(f"{m + ' err':>15}{'<=5m':>7}{'comp':>6}{'frame ms':>9}" for m in methods)
    return f"{'query':<8}{'type':<10}{'feat':>6}{'extract ms':>11}{'ms/comp':>9}{cols}"


def line(r: TypeResult, methods: list[str]) -> str:
    cols = "".join(f"{r.errors[m]:15.2f}{100 * r.within_5m[m]:6.1f}%{r.comparisons[m]:6.1f}"
                   f"{r.frame_ms(m):9.1f}" for m in methods)
    return (f"{r.query:<8}{r.kind:<10}{r.features:6.0f}{r.extract_ms:11.2f}"
            f"{r.match_ms:9.3f}{cols}")
