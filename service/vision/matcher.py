"""Exact, fast m(A, B) on uint8 descriptors (quantised RootSIFT).

The similarity is the papers' symmetric ratio test (see ``service.vision.features``), defined here
precisely for integer descriptors, so that the fast path and the reference agree bit for bit:

- ``d(a, b)`` is the exact integer dot product, ``|a| = sqrt(float64(sum a^2))``;
- ``cos(a, b) = min(d / (|a| * |b|), 1)`` in float64, the angle is ``math.acos(cos)``;
- the nearest neighbour of ``a`` in B is the first ``b`` of largest cos; the second-nearest
  angle comes from the largest cos among the other rows (an exact tie makes both angles equal,
  so a tie never passes);
- ``a`` passes iff ``acos(cos1) < delta * acos(cos2)``; a pair counts when ``a`` and ``b`` are
  each other's nearest neighbour and both pass; m = count / min(|A|, |B|); a set with fewer
  than two features matches nothing.

Fast path: the integer dot products come from an exact GEMM, NumKong's packed uint8 kernels
(AMX / VNNI where the CPU has them) or float32 BLAS (exact because every dot is an integer
below 2^24), whichever this CPU runs faster (``fastest_gemm``, timed once). A fused numba
kernel keeps the two best float32 keys per row
(``d * 1/|b|``) and per column (``d * 1/|a|``) without materialising anything else. The float32
keys are within 2.5e-7 (relative) of the exact ratio; wherever the two best keys are closer than
``_TOL`` or the decision could flip within that error, the row or column is rescanned exactly in
integers and float64, so the result equals the reference's.
"""

from __future__ import annotations

import functools
import math
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np

from service.vision.features import DEFAULT_DELTA, BatchMatch

_TOL = 1e-6  # relative; the float32 key error is at most ~2.5e-7
_TILE = 256  # rows of A per GEMM tile at most (``tile_rows``)
_TILE_BYTES = 512 * 1024  # a tile of 4-byte dots this large at most: it stays in L2


def _jit(fn: Callable) -> Any:
    """numba ``njit(nogil=True)``, compiled on first use; ``cache_kernels_in`` gives it an
    on-disk cache (this module gives every kernel the default one at import)."""
    import numba

    return numba.njit(nogil=True)(fn)


def default_cache_dir() -> Path:
    """Where the kernels are cached by default: ``$XDG_CACHE_HOME/swarmloc/numba`` (else
    ``~/.cache/swarmloc/numba``), never the installed package (site-packages may be
    read-only, and a cache written there on the first frame made it take seconds)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "swarmloc" / "numba"


def _writable_dir(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return False
    return True


def cache_kernels_in(path: Path | None, kernels: Sequence[Any] | None = None) -> Path | None:
    """Keep the compiled numba kernels (``kernels``, default this module's) in ``path``;
    returns the directory used, or None where ``path`` is None or cannot be written: the
    kernels then compile in each process (a few seconds, in ``warm_up``)."""
    import numba
    from numba.core.caching import NullCache

    config: Any = numba.config
    used = path if path is not None and _writable_dir(path) else None
    saved = config.CACHE_DIR
    config.CACHE_DIR = str(used) if used is not None else ""
    try:  # numba reads CACHE_DIR when a kernel's cache is made, not later
        for kernel in _KERNELS if kernels is None else kernels:
            try:
                if used is not None:
                    kernel.enable_caching()
                    continue
            except RuntimeError:  # "cannot cache function ...: no locator available"
                used = None
            kernel._cache = NullCache()  # numba's own "no cache" (njit without cache=True)
    finally:
        config.CACHE_DIR = saved
    return used


try:  # NumKong: exact packed uint8 GEMM (AMX / AVX-512 VNNI); optional, BLAS otherwise
    import numkong as _nk
except ImportError:  # pragma: no cover - numkong is a main dependency
    _nk = None  # type: ignore[assignment]


@dataclass(frozen=True)
class PreparedSet:
    """A descriptor set prepared once (per map image): its rows, norms and packed GEMM operand."""

    desc: np.ndarray  # (n, D) uint8
    norms: np.ndarray  # (n,) float64, |b|
    inv_norms: np.ndarray  # (n,) float32, 1 / |b|
    packed: Any  # numkong PackedMatrix, or None (BLAS path)

    def __len__(self) -> int:
        return len(self.desc)


def check_codes(x: np.ndarray, name: str, dtype: Literal["uint8", "int8"] = "uint8"
                ) -> np.ndarray:
    """``x`` as a contiguous 2-D array of ``dtype`` codes short enough for exact float32 dot
    products (every dot below 2^24: 258 uint8 or 1,040 int8 values), else a ValueError that
    says which."""
    x = np.asarray(x)
    if x.dtype != np.dtype(dtype) or x.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D {dtype} code array, got {x.dtype} {x.shape}")
    most = (2**24 - 1) // (255 * 255 if dtype == "uint8" else 127 * 127)
    if x.shape[1] > most:
        raise ValueError(f"{name}: codes of length {x.shape[1]} are too long for exact "
                         f"float32 dot products (at most {most})")
    return np.ascontiguousarray(x)


def _check_u8(x: np.ndarray, name: str) -> np.ndarray:
    return check_codes(x, name, "uint8")


def norms_u8(x: np.ndarray) -> np.ndarray:
    """|x| per row in float64 from the exact integer sum of squares; zero rows are refused."""
    x = _check_u8(x, "descriptors")
    f = x.astype(np.float32)
    sq = np.einsum("ij,ij->i", f, f)  # integer partial sums below 2^24: exact in float32
    if np.any(sq == 0):
        raise ValueError("descriptor rows must be non-zero")
    return np.sqrt(sq.astype(np.float64))


def prepare(b: np.ndarray, backend: str = "auto") -> PreparedSet:
    """Prepare a map image's uint8 descriptors once: norms and (NumKong) packed layout."""
    b = _check_u8(b, "set")
    norms = norms_u8(b)
    inv = (1.0 / norms).astype(np.float32) if len(b) else np.zeros(0, np.float32)
    packed = None
    if use_numkong(backend) and len(b):
        packed = pack(b, "uint8")
    return PreparedSet(b, norms, inv, packed)


def gemm_width(n: int) -> int:
    """The width NumKong's packed GEMM runs at for a set of ``n`` rows: ``n``, or up to 28
    more (zero rows packed after the set) where ``n`` lies within 12 of a multiple of 512.
    There the output tile's rows lie a multiple of 2 KiB apart, its stores alias in the cache,
    and the GEMM ran 2-2.5x slower: 0.29 against 0.12 ns per dot for 1,024 x 1,024 int8 codes
    of 64, 1,040 columns as fast as 1,000 (docs/research/performance.md). XFeat keeps 1,024
    features per image and SIFT 2,048 on rich frames, so most comparisons fell there."""
    r = n % 512
    if n < 500 or 12 < r < 500:
        return n
    return n - r + (512 if r >= 500 else 0) + 16


def tile_rows(width: int) -> int:
    """Rows of A per NumKong GEMM tile against a set this wide: at most 256, at least 32, a
    tile of at most 512 KiB of 4-byte dots. NumKong writes the tile and the two scans read
    it: 256 rows of 1,300 columns (1.3 MiB) took 10 % longer per comparison than 96 rows, 256
    of 4,000 columns 45 % longer than 32 (docs/research/performance.md). The float32 BLAS
    path keeps 256 rows: smaller tiles made it slower (4,000 columns: 35 %)."""
    return max(32, min(_TILE, _TILE_BYTES // (4 * max(width, 1)) // 16 * 16))


def pack(codes: np.ndarray, dtype: Literal["uint8", "int8"]) -> Any:
    """NumKong's packed operand of ``codes`` (rows), with zero rows up to ``gemm_width``: the
    GEMM's extra columns are zero dots, which no scan reads."""
    extra = gemm_width(len(codes)) - len(codes)
    if extra:
        codes = np.concatenate([codes, np.zeros((extra, codes.shape[1]), codes.dtype)])
    return _nk.dots_pack(codes, dtype=dtype)


def top_columns(a: np.ndarray, s: PreparedSet, w: int) -> np.ndarray:
    """(nA, w) int64: per row of uint8 ``a``, the ``w`` rows of the prepared set with the
    largest cosine (exact integer dot products x 1 / |b|; NumKong's packed GEMM, else float32
    BLAS), best first, in tiles of 256 rows."""
    a = _check_u8(a, "a")
    w = min(w, len(s))
    out = np.empty((len(a), w), np.int64)
    for r0 in range(0, len(a), _TILE):
        r1 = min(r0 + _TILE, len(a))
        if s.packed is not None:
            nk_out = _nk.empty((r1 - r0, gemm_width(len(s))), dtype="uint32")
            _nk.dots_packed(a[r0:r1], s.packed, out=nk_out)
            dots = np.asarray(nk_out)
        else:
            dots = a[r0:r1].astype(np.float32) @ s.desc.astype(np.float32).T
        _top_w(dots, s.inv_norms, out[r0:r1])
    return out


def use_numkong(backend: str, dtype: Literal["uint8", "int8"] = "uint8") -> bool:
    """Whether ``backend`` (auto, numkong or blas) runs NumKong's packed GEMM on codes of
    ``dtype`` (auto: whichever of the two this CPU runs faster, ``fastest_gemm``)."""
    if backend not in ("auto", "numkong", "blas"):
        raise ValueError(f"unknown matcher backend {backend!r}: use auto, numkong or blas")
    if backend == "numkong" and _nk is None:
        raise ValueError("matcher backend 'numkong' needs the numkong package")
    return backend == "numkong" or (backend == "auto" and _nk is not None
                                    and fastest_gemm(dtype).backend == "numkong")


@dataclass(frozen=True)
class GemmChoice:
    """Which exact GEMM ``backend="auto"`` uses on this CPU, and the timings that chose it."""

    backend: str  # "numkong" or "blas"
    numkong_ms: float  # three 256-row tiles, best of 7 each; nan without NumKong
    blas_ms: float

    def describe(self) -> str:
        if math.isnan(self.numkong_ms):
            return "float32 BLAS (NumKong not installed)"
        name = "NumKong" if self.backend == "numkong" else "float32 BLAS"
        return (f"{name} (three tiles: NumKong {self.numkong_ms:.2f} ms, BLAS "
                f"{self.blas_ms:.2f} ms on this CPU)")


@functools.lru_cache(maxsize=2)
def fastest_gemm(dtype: Literal["uint8", "int8"] = "uint8") -> GemmChoice:
    """Time NumKong's packed GEMM against float32 BLAS once per process and code type
    (``uint8``: RootSIFT's 128-byte codes; ``int8``: XFeat's 64, service/vision/mnn_matcher.py),
    on a tile of the matcher's shape, and take the faster: both give the same exact dot
    products, so the choice changes speed only. For uint8 NumKong wins by 3-7x where the CPU
    has AMX or AVX-512 VNNI; on AVX2 alone BLAS was 1.45x faster
    (docs/research/performance.md)."""
    from threadpoolctl import threadpool_limits

    if dtype not in ("uint8", "int8"):
        raise ValueError(f"unknown code type {dtype!r}: use uint8 or int8")
    rng = np.random.default_rng(0)
    dims, low = (128, 0) if dtype == "uint8" else (64, -127)
    acc: Literal["uint32", "int32"] = "uint32" if dtype == "uint8" else "int32"
    # the full code range and map images' uneven sizes: NumKong's packed kernels slow down
    # for some widths (535 columns took 1.8x the time of 512)
    a = rng.integers(low, 128 if low else 256, (_TILE, dims)).astype(dtype)
    sets = [rng.integers(low, 128 if low else 256, (n, dims)).astype(dtype)
            for n in (487, 535, 600)]
    blas = np.zeros(len(sets))
    kong = np.zeros(len(sets))
    with threadpool_limits(1):  # as frames run: one BLAS thread each
        a32 = a.astype(np.float32)
        for k, b in enumerate(sets):
            b32, out32 = b.astype(np.float32).T, np.empty((_TILE, len(b)), np.float32)
            packed = _nk.dots_pack(b, dtype=dtype) if _nk is not None else None
            out_nk = _nk.empty((_TILE, len(b)), dtype=acc) if _nk is not None else None
            t_blas, t_kong = [], []
            for _ in range(7):  # interleaved, best of each: robust to a busy neighbour
                t0 = time.perf_counter()
                np.matmul(a32, b32, out=out32)
                t_blas.append(time.perf_counter() - t0)
                if packed is not None:
                    t0 = time.perf_counter()
                    _nk.dots_packed(a, packed, out=out_nk)
                    t_kong.append(time.perf_counter() - t0)
            blas[k] = min(t_blas)
            kong[k] = min(t_kong) if t_kong else math.nan
    blas_ms, kong_ms = 1e3 * float(blas.sum()), 1e3 * float(kong.sum())
    return GemmChoice("numkong" if kong_ms < blas_ms else "blas", kong_ms, blas_ms)


# ---- numba kernels ------------------------------------------------------------------------
def _four_rows(dots, r, r0, inv_na):
    """Rows r.. r + 3 of a tile and their scales (rows r0 + r.. of A): a column sweep's four."""
    return (inv_na[r0 + r], inv_na[r0 + r + 1], inv_na[r0 + r + 2], inv_na[r0 + r + 3],
            dots[r], dots[r + 1], dots[r + 2], dots[r + 3])


def _scan_columns(dots, r0, inv_na, cm1, cm2):
    """Update the two best float32 keys d * (1/|a|) of every column with rows r0.. of a tile
    (the columns of ``cm1``: the tile may be wider, ``gemm_width``).

    Four rows per sweep: the column state is loaded and stored once for four updates.
    """
    nr = dots.shape[0]
    nb = cm1.shape[0]
    r = 0
    while r + 4 <= nr:
        sa, sb, sc, sd, ra, rb, rc, rd = _four_rows(dots, r, r0, inv_na)
        for j in range(nb):
            c1 = cm1[j]
            c2 = cm2[j]
            k = np.float32(ra[j]) * sa
            c2 = max(c2, min(c1, k))
            c1 = max(c1, k)
            k = np.float32(rb[j]) * sb
            c2 = max(c2, min(c1, k))
            c1 = max(c1, k)
            k = np.float32(rc[j]) * sc
            c2 = max(c2, min(c1, k))
            c1 = max(c1, k)
            k = np.float32(rd[j]) * sd
            c2 = max(c2, min(c1, k))
            c1 = max(c1, k)
            cm1[j] = c1
            cm2[j] = c2
        r += 4
    while r < nr:
        sa = inv_na[r0 + r]
        ra = dots[r]
        for j in range(nb):
            k = np.float32(ra[j]) * sa
            c1 = cm1[j]
            cm2[j] = max(cm2[j], min(c1, k))
            cm1[j] = max(c1, k)
        r += 1


def _scan_columns_best(dots, r0, inv_na, cm1):
    """``_scan_columns`` for the best key of every column only (XFeat's mutual check needs no
    second): one max per element instead of three operations."""
    nr = dots.shape[0]
    nb = cm1.shape[0]
    r = 0
    while r + 4 <= nr:
        sa, sb, sc, sd, ra, rb, rc, rd = _four_rows(dots, r, r0, inv_na)
        for j in range(nb):
            c1 = max(cm1[j], np.float32(ra[j]) * sa)
            c1 = max(c1, np.float32(rb[j]) * sb)
            c1 = max(c1, np.float32(rc[j]) * sc)
            cm1[j] = max(c1, np.float32(rd[j]) * sd)
        r += 4
    while r < nr:
        sa = inv_na[r0 + r]
        ra = dots[r]
        for j in range(nb):
            cm1[j] = max(cm1[j], np.float32(ra[j]) * sa)
        r += 1


def _finish_row(row, inv_nb, nfull, lm1, lm2, lj1):
    """Best key, its column and the second key of a row from its lanes plus the tail."""
    m1 = np.float32(-np.inf)  # below any key (int8 codes' keys may be negative)
    m2 = np.float32(-np.inf)
    j1 = -1
    for j in range(nfull, inv_nb.shape[0]):
        k = np.float32(row[j]) * inv_nb[j]
        if k > m1:
            m2 = m1
            m1 = k
            j1 = j
        elif k > m2:
            m2 = k
    for q in range(lm1.shape[0]):  # merge the lanes (an equal value goes to m2: a tie is kept)
        v = lm1[q]
        if v > m1 or (v == m1 and lj1[q] < j1):
            m2 = m1
            m1 = v
            j1 = lj1[q]
        elif v > m2:
            m2 = v
        m2 = max(m2, lm2[q])
    return m1, j1, m2


def _scan_rows(dots, r0, inv_nb, rm1, rj1, rm2, rd1):
    """Best key d * (1/|b|), its column and dot, and the second key of rows r0.. of a tile
    (the columns of ``inv_nb``: the tile may be wider, ``gemm_width``).

    Each row over 16 lanes (lane q: the columns q, q + 16, ...), four blocks of 16 columns per
    sweep: a lane's state stays in registers for four updates, the loop vectorises, and a lane
    keeps the block of its best column (an int32 counter, not the column: no 64-bit index
    vector in the loop). Then the lanes merge with the tail.
    """
    nr = dots.shape[0]
    nb = inv_nb.shape[0]
    nl = 16
    nblk = 4
    a1 = np.empty(nl, np.float32)
    a2 = np.empty(nl, np.float32)
    aj = np.empty(nl, np.int32)
    nfull = nb - nb % nl
    nsweep = nfull - nfull % (nblk * nl)
    for r in range(nr):
        ra = dots[r]
        for q in range(nl):
            a1[q] = -np.inf
            a2[q] = -np.inf
            aj[q] = -1
        blk = np.int32(0)
        for jb in range(0, nsweep, nblk * nl):
            for q in range(nl):
                l1 = a1[q]
                l2 = a2[q]
                lj = aj[q]
                for t in range(nblk):
                    j = jb + t * nl + q
                    k = np.float32(ra[j]) * inv_nb[j]
                    lj = blk + np.int32(t) if k > l1 else lj
                    l2 = max(l2, min(l1, k))
                    l1 = max(l1, k)
                a1[q] = l1
                a2[q] = l2
                aj[q] = lj
            blk += np.int32(nblk)
        for jb in range(nsweep, nfull, nl):
            for q in range(nl):
                j = jb + q
                k = np.float32(ra[j]) * inv_nb[j]
                l1 = a1[q]
                aj[q] = blk if k > l1 else aj[q]
                a2[q] = max(a2[q], min(l1, k))
                a1[q] = max(l1, k)
            blk += np.int32(1)
        for q in range(nl):  # block -> column
            aj[q] = aj[q] * nl + q if aj[q] >= 0 else -1
        m1, j1, m2 = _finish_row(ra, inv_nb, nfull, a1, a2, aj)
        rm1[r0 + r] = m1
        rj1[r0 + r] = j1
        rm2[r0 + r] = m2
        rd1[r0 + r] = ra[j1]


def _scan_tile(dots, r0, inv_na, inv_nb, rm1, rj1, rm2, rd1, cm1, cm2):
    """The float32 top-2 keys of rows r0.. (best column and its dot kept) and of every column
    (values; the best only where ``cm2`` is empty)."""
    if cm2.shape[0] == 0:
        _scan_columns_best(dots, r0, inv_na, cm1)
    else:
        _scan_columns(dots, r0, inv_na, cm1, cm2)
    _scan_rows(dots, r0, inv_nb, rm1, rj1, rm2, rd1)


def _dot(x, y):  # numba kernel
    d = np.int64(0)
    for t in range(x.shape[0]):
        d += np.int64(x[t]) * np.int64(y[t])
    return d


def _cos(x, y, nx, ny):
    return min(_dot(x, y) / (nx * ny), 1.0)


def _exact_scan(x, nx, ys, nys):
    """Exact best index, best cos and second cos of x over the rows of ys."""
    c1 = -1.0
    c2 = -1.0
    j1 = -1
    for j in range(ys.shape[0]):
        c = _cos(x, ys[j], nx, nys[j])
        if c > c1:
            c2 = c1
            c1 = c
            j1 = j
        elif c > c2:
            c2 = c
    return j1, c1, c2


def _passes(c1, c2, delta):
    return math.acos(c1) < delta * math.acos(c2)


def _ratio(c1, m2, n, delta, tol):
    """Ratio test with the exact best cos c1 and the second from its float32 key m2 (cos =
    m2 / n within tol): 1 pass, 0 fail, -1 undecided (needs the exact scan)."""
    c2 = m2 / n
    if _passes(c1, min(c2 * (1.0 + tol), 1.0), delta):
        return 1
    if not _passes(c1, min(c2 * (1.0 - tol), 1.0), delta):
        return 0
    return -1


def _decide(a, na, b, nb, inv_na, rm1, rj1, rm2, rd1, cm1, cm2, delta, tol, matched, partner):
    """Mark rows of A in a symmetric ratio-test match with B (``partner``: the matched row of
    B); return the count. The scan's keys do not depend on ``delta``: one scan serves any.

    Cheap checks first: a row whose float32 best is clear and whose column's clear best is
    another row is no match (no angle is computed); exact rescans only where keys are close.
    """
    count = 0
    for i in range(a.shape[0]):
        c2 = 0.0
        row_clear = rm1[i] > rm2[i] * (1.0 + tol)  # a clear float32 winner is the exact one
        if row_clear:
            j = rj1[i]
            d = rd1[i]
            c1 = min(d / (na[i] * nb[j]), 1.0)
        else:
            j, c1, c2 = _exact_scan(a[i], na[i], b, nb)
            d = _dot(a[i], b[j])
        col_clear = cm1[j] > cm2[j] * (1.0 + tol)
        if col_clear and np.float32(d) * inv_na[i] != cm1[j]:
            continue  # column j's nearest neighbour is another row
        if row_clear:
            ok = _ratio(c1, rm2[i], na[i], delta, tol)
            if ok < 0:
                _, c1, c2 = _exact_scan(a[i], na[i], b, nb)
                ok = _passes(c1, c2, delta)
        else:
            ok = _passes(c1, c2, delta)
        if not ok:
            continue
        if col_clear:
            okb = _ratio(c1, cm2[j], nb[j], delta, tol)
            if okb < 0:
                ib, c1b, c2b = _exact_scan(b[j], nb[j], a, na)
                okb = ib == i and _passes(c1b, c2b, delta)
        else:
            ib, c1b, c2b = _exact_scan(b[j], nb[j], a, na)
            okb = ib == i and _passes(c1b, c2b, delta)
        if okb:
            matched[i] = True
            partner[i] = j
            count += 1
    return count


def _ivf_scan(a, na, words, b, nb, starts, rc1, rc2, rj, cc1, cc2, ci):
    """Exact cosines of the candidate pairs (b's word among a's words): the two best of
    every row (best column kept) and of every column (best row kept)."""
    dims = a.shape[1]
    for i in range(a.shape[0]):
        for q in range(words.shape[1]):
            w = words[i, q]
            for j in range(starts[w], starts[w + 1]):
                d = np.int64(0)
                for t in range(dims):
                    d += np.int32(a[i, t]) * np.int32(b[j, t])
                c = min(d / (na[i] * nb[j]), 1.0)
                if c > rc1[i]:
                    rc2[i] = rc1[i]
                    rc1[i] = c
                    rj[i] = j
                elif c > rc2[i]:
                    rc2[i] = c
                if c > cc1[j]:
                    cc2[j] = cc1[j]
                    cc1[j] = c
                    ci[j] = i
                elif c > cc2[j]:
                    cc2[j] = c


def _top_w(dots, inv_nb, out):
    """Each row's ``out.shape[1]`` columns of the largest dots x inv_nb, best first (the
    columns of ``inv_nb``: ``dots`` may be wider, ``gemm_width``)."""
    w = out.shape[1]
    best = np.empty(w, np.float32)
    for i in range(dots.shape[0]):
        for q in range(w):
            best[q] = -np.inf
            out[i, q] = -1
        for j in range(inv_nb.shape[0]):
            v = np.float32(dots[i, j]) * inv_nb[j]
            if v > best[w - 1]:
                q = w - 1
                while q > 0 and v > best[q - 1]:
                    best[q] = best[q - 1]
                    out[i, q] = out[i, q - 1]
                    q -= 1
                best[q] = v
                out[i, q] = j


def _ivf_decide(rc1, rc2, rj, cc1, cc2, ci, delta, matched):
    """Rows in a symmetric ratio-test match among their candidates (a side with fewer than
    two candidates never passes); returns the count and marks ``matched``."""
    count = 0
    for i in range(rc1.shape[0]):
        j = rj[i]
        if j < 0 or ci[j] != i or rc2[i] < -1.5 or cc2[j] < -1.5:
            continue
        if _passes(rc1[i], rc2[i], delta) and _passes(cc1[j], cc2[j], delta):
            matched[i] = True
            count += 1
    return count


_four_rows = _jit(_four_rows)
_scan_columns = _jit(_scan_columns)
_scan_columns_best = _jit(_scan_columns_best)
_finish_row = _jit(_finish_row)
_scan_rows = _jit(_scan_rows)
_scan_tile = _jit(_scan_tile)
_dot = _jit(_dot)
_cos = _jit(_cos)
_exact_scan = _jit(_exact_scan)
_passes = _jit(_passes)
_ratio = _jit(_ratio)
_decide = _jit(_decide)
_ivf_scan = _jit(_ivf_scan)
_ivf_decide = _jit(_ivf_decide)
_top_w = _jit(_top_w)
_KERNELS: tuple[Any, ...] = (_four_rows, _scan_columns, _scan_columns_best, _finish_row,
                             _scan_rows, _scan_tile, _dot, _cos, _exact_scan, _passes, _ratio,
                             _decide, _ivf_scan, _ivf_decide, _top_w)
cache_kernels_in(default_cache_dir())


# ---- public API -----------------------------------------------------------------------------
Pairs = tuple[np.ndarray, np.ndarray]  # (rows of a, rows of a set): matched features


def match_batch_u8(a: np.ndarray, sets: Sequence[np.ndarray | PreparedSet],
                   delta: float = DEFAULT_DELTA, backend: str = "auto") -> BatchMatch:
    """Exact symmetric ratio-test matches of uint8 descriptors ``a`` (nA, D) against each set.

    ``sets`` holds uint8 arrays (nB, D) or, better, ``PreparedSet``s from ``prepare`` (a map
    prepares each image once). ``backend``: ``auto`` (the faster on this CPU:
    ``fastest_gemm``), ``numkong`` or ``blas`` (float32 GEMM). Equal to
    ``match_batch_u8_reference`` on every input.
    """
    return _match(a, sets, delta, backend, None)[0]


def match_batch_u8_pairs(a: np.ndarray, sets: Sequence[np.ndarray | PreparedSet],
                         delta: float, pairs_delta: float, backend: str = "auto"
                         ) -> tuple[BatchMatch, list[Pairs]]:
    """``match_batch_u8(a, sets, delta)`` and, per set, the matched index pairs (rows of
    ``a``, rows of the set) of the symmetric ratio test at ``pairs_delta``, from the same
    GEMM and scans (only the decisions run again): the matches the two-view geometry uses
    (service/vision/metric_pose.py), at no second matching."""
    r, pairs = _match(a, sets, delta, backend, float(pairs_delta))
    assert pairs is not None
    return r, pairs


def row_state(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The per-row outputs of the scan for ``n`` rows of A (best key, its column, second key,
    best dot), filled by ``scan_set`` for each set in turn."""
    return (np.empty(n, np.float32), np.empty(n, np.int64), np.empty(n, np.float32),
            np.empty(n, np.int64))


def scan_set(a: np.ndarray, a_f32: np.ndarray | None, inv_na: np.ndarray, codes: np.ndarray,
             packed: Any, inv_nb: np.ndarray, dtype: Literal["uint8", "int8"],
             rows: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
             column_second: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A's rows against one prepared set, a tile at a time: the exact GEMM (NumKong's packed
    ``dtype`` kernels where ``a_f32`` is None, else float32 BLAS on ``a_f32``) and the fused
    scan, which fills ``rows`` (each row's best key, its column, its second key and its best
    dot, ``row_state``); returns each column's two best keys (the second an empty array
    where ``column_second`` is False: the scan then keeps each column's best alone)."""
    rm1, rj1, rm2, rd1 = rows
    nb, na_rows = len(codes), len(a)
    cm1 = np.full(nb, -np.inf, np.float32)  # below any key (int8 keys may be negative)
    cm2 = np.full(nb if column_second else 0, -np.inf, np.float32)
    width = gemm_width(nb)
    tile = min(tile_rows(width) if a_f32 is None else _TILE, na_rows)
    acc: Literal["uint32", "int32"] = "uint32" if dtype == "uint8" else "int32"
    if a_f32 is None:
        packed = packed if packed is not None else pack(codes, dtype)
        out = _nk.empty((tile, width), dtype=acc)
        buf = np.asarray(out)
    else:  # the transposed set, as wide as the packed GEMM's (its rows alias there too)
        b_t = np.zeros((codes.shape[1], width), np.float32)
        b_t[:, :nb] = codes.T
        buf = np.empty((tile, b_t.shape[1]), np.float32)
    for r0 in range(0, na_rows, tile):
        r1 = min(r0 + tile, na_rows)
        if a_f32 is None:
            if r1 - r0 != tile:
                out = _nk.empty((r1 - r0, width), dtype=acc)
                buf = np.asarray(out)
            _nk.dots_packed(a[r0:r1], packed, out=out)
            dots = buf
        else:
            dots = np.matmul(a_f32[r0:r1], b_t, out=buf[: r1 - r0])
        _scan_tile(dots, r0, inv_na, inv_nb, rm1, rj1, rm2, rd1, cm1, cm2)
    return cm1, cm2


def _match(a: np.ndarray, sets: Sequence[np.ndarray | PreparedSet], delta: float,
           backend: str, pairs_delta: float | None) -> tuple[BatchMatch, list[Pairs] | None]:
    a = _check_u8(a, "a")
    k = len(sets)
    na_rows = len(a)
    counts = np.zeros(k, np.int64)
    matched = np.zeros((k, na_rows), bool)
    none = np.zeros(0, np.int64)
    pairs: list[Pairs] | None = None if pairs_delta is None else [(none, none)] * k
    use_nk = use_numkong(backend)
    prepared = [s if isinstance(s, PreparedSet) else prepare(s, backend) for s in sets]
    for s in prepared:
        if s.desc.shape[1] != a.shape[1] and len(s) and na_rows:
            raise ValueError(f"descriptor length differs: {a.shape[1]} vs {s.desc.shape[1]}")
    nb_all = np.array([len(s) for s in prepared], np.int64)
    if k == 0 or na_rows < 2:
        return BatchMatch(counts, np.zeros(k), matched), pairs
    na = norms_u8(a)
    inv_na = (1.0 / na).astype(np.float32)
    a_f32 = None if use_nk else a.astype(np.float32)
    state = rm1, rj1, rm2, rd1 = row_state(na_rows)
    partner = np.empty(na_rows, np.int64)
    for idx, s in enumerate(prepared):
        nb = len(s)
        if nb < 2:
            continue
        cm1, cm2 = scan_set(a, a_f32, inv_na, s.desc, s.packed, s.inv_norms, "uint8", state)
        counts[idx] = _decide(a, na, s.desc, s.norms, inv_na, rm1, rj1, rm2, rd1, cm1, cm2,
                              float(delta), _TOL, matched[idx], partner)
        if pairs is not None and pairs_delta is not None:
            hit = matched[idx]
            if pairs_delta != delta:
                hit = np.zeros(na_rows, bool)
                _decide(a, na, s.desc, s.norms, inv_na, rm1, rj1, rm2, rd1, cm1, cm2,
                        float(pairs_delta), _TOL, hit, partner)
            rows = np.flatnonzero(hit)
            pairs[idx] = (rows, partner[rows])
    denom = np.minimum(na_rows, nb_all)
    scores = np.where(denom > 0, counts / np.maximum(denom, 1), 0.0)
    return BatchMatch(counts, scores, matched), pairs


class WordSorted(Protocol):
    """A map image's uint8 descriptors sorted by visual word (service/vision/vocabulary.py):
    ``desc`` (n, D) uint8 word by word, ``norms`` (n,) float64, ``starts`` (k + 1,) int64
    (word q's rows are starts[q]:starts[q + 1])."""

    @property
    def desc(self) -> np.ndarray: ...
    @property
    def norms(self) -> np.ndarray: ...
    @property
    def starts(self) -> np.ndarray: ...


@dataclass(frozen=True)
class _Sorted:  # one word, for the warm-up
    desc: np.ndarray
    norms: np.ndarray
    starts: np.ndarray


def _ivf_one(a: np.ndarray, norms_a: np.ndarray, words_a: np.ndarray, s: WordSorted,
             delta: float, matched: np.ndarray, pairs_delta: float | None = None
             ) -> tuple[int, np.ndarray, np.ndarray | None]:
    """(count, each row's best candidate row of ``s``, the rows matched at ``pairs_delta``
    or None), marking ``matched``; one scan serves both deltas."""
    na_rows, nb = len(a), len(s.desc)
    rj = np.full(na_rows, -1, np.int64)
    if nb < 2 or na_rows < 2:
        return 0, rj, None if pairs_delta is None else np.zeros(na_rows, bool)
    rc1 = np.full(na_rows, -2.0)
    rc2 = np.full(na_rows, -2.0)
    cc1 = np.full(nb, -2.0)
    cc2 = np.full(nb, -2.0)
    ci = np.full(nb, -1, np.int64)
    _ivf_scan(a, norms_a, words_a, s.desc, s.norms, s.starts, rc1, rc2, rj, cc1, cc2, ci)
    count = _ivf_decide(rc1, rc2, rj, cc1, cc2, ci, float(delta), matched)
    if pairs_delta is None:
        return count, rj, None
    hit = matched
    if pairs_delta != delta:
        hit = np.zeros(na_rows, bool)
        _ivf_decide(rc1, rc2, rj, cc1, cc2, ci, float(pairs_delta), hit)
    return count, rj, hit


def pairs_ivf(a: np.ndarray, norms_a: np.ndarray, words_a: np.ndarray, s: WordSorted,
              delta: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (rows of ``a``, rows of ``s.desc``) of ``match_batch_ivf``'s matches."""
    matched = np.zeros(len(a), bool)
    _, rj, _ = _ivf_one(a, norms_a, words_a, s, delta, matched)
    rows = np.flatnonzero(matched)
    return rows, rj[rows]


def match_batch_ivf(a: np.ndarray, norms_a: np.ndarray, words_a: np.ndarray,
                    sets: Sequence[WordSorted], delta: float = DEFAULT_DELTA,
                    pairs_delta: float | None = None
                    ) -> tuple[BatchMatch, list[Pairs] | None]:
    """The symmetric ratio test of ``a`` (nA, D) uint8 against each word-sorted set, among
    the candidate pairs only: b's word is one of ``words_a``'s (nA, w) words of a. Exact
    cosines; with every word probed it equals ``match_batch_u8``. ``pairs_delta``: also,
    per set, the matched index pairs (rows of ``a``, rows of ``s.desc``) of the ratio test
    at that delta, from the same scan (``match_batch_u8_pairs``'s; else None)."""
    k = len(sets)
    na_rows = len(a)
    counts = np.zeros(k, np.int64)
    matched = np.zeros((k, na_rows), bool)
    nb_all = np.array([len(s.desc) for s in sets], np.int64)
    pairs: list[Pairs] | None = None if pairs_delta is None else []
    for idx, s in enumerate(sets):
        counts[idx], rj, hit = _ivf_one(a, norms_a, words_a, s, delta, matched[idx],
                                        pairs_delta)
        if pairs is not None and hit is not None:
            rows = np.flatnonzero(hit)
            pairs.append((rows, rj[rows]))
    denom = np.minimum(na_rows, nb_all)
    scores = np.where(denom > 0, counts / np.maximum(denom, 1), 0.0)
    return BatchMatch(counts, scores, matched), pairs


def match_batch_u8_reference(a: np.ndarray, sets: Sequence[np.ndarray],
                             delta: float = DEFAULT_DELTA) -> BatchMatch:
    """The definition above, written plainly: float64 dot products (exact for uint8),
    cos = min(d / (|a| |b|), 1), angles with ``math.acos``, full argmax both ways."""
    a = _check_u8(a, "a")
    k = len(sets)
    counts = np.zeros(k, np.int64)
    matched = np.zeros((k, len(a)), bool)
    nb_all = np.array([len(b) for b in sets], np.int64)
    if len(a) >= 2:
        na = norms_u8(a)
        for idx, b in enumerate(sets):
            b = _check_u8(b, "set")
            if len(b) < 2:
                continue
            nb = norms_u8(b)
            cos = np.minimum((a.astype(np.float64) @ b.astype(np.float64).T)
                             / (na[:, None] * nb[None, :]), 1.0)
            row_best, row_pass = _reference_side(cos, delta)
            col_best, col_pass = _reference_side(cos.T, delta)
            rows = np.arange(len(a))
            ok = row_pass & col_pass[row_best] & (col_best[row_best] == rows)
            matched[idx] = ok
            counts[idx] = int(ok.sum())
    denom = np.minimum(len(a), nb_all)
    scores = np.where(denom > 0, counts / np.maximum(denom, 1), 0.0)
    return BatchMatch(counts, scores, matched)


def _reference_side(cos: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray]:
    best = cos.argmax(axis=1)
    rows = np.arange(len(cos))
    c1 = cos[rows, best]
    rest = cos.copy()
    rest[rows, best] = -np.inf
    c2 = rest.max(axis=1)
    ok = np.array([math.acos(x) < delta * math.acos(y) for x, y in zip(c1, c2, strict=True)],
                  bool)
    return best, ok


def compiled_signatures() -> int:
    """How many type signatures the kernels have compiled (or loaded) in this process."""
    return sum(len(k.signatures) for k in _KERNELS)


def warm_up() -> None:
    """Compile (or load from the cache) the numba kernels for every argument type a frame
    meets, outside any timed section: writable and read-only descriptors on either side (a
    loaded map's codes are read-only memory maps; a map image is the frame of the two-view
    geometry's structure), NumKong's uint32 and BLAS's float32 dot products."""
    rng = np.random.default_rng(0)
    x = rng.integers(1, 255, (20, 128), dtype=np.uint8)
    ro = x.copy()
    ro.flags.writeable = False
    for backend in ("auto", "blas"):
        for a in (x, ro):
            match_batch_u8(a, [x[:19], prepare(ro[1:], backend), prepare(x[2:], backend)],
                           backend=backend)
    one_word = _Sorted(x.copy(), norms_u8(x), np.array([0, len(x)], np.int64))
    for a in (x, ro):
        match_batch_ivf(a, norms_u8(a), np.zeros((len(a), 1), np.int64), [one_word], 0.6,
                        0.9)
        for backend in ("auto", "blas"):
            top_columns(a, prepare(x[:5], backend), 2)
