"""Exact, fast mutual nearest neighbours on int8 descriptor codes (XFeat).

XFeat's similarity (service/vision/xfeat.py) matches a frame's features with a map image's by
mutual nearest neighbours above a cosine gate and Lowe's ratio test. Both sides are int8 codes
(unit descriptors x 127), so the rule is defined on the codes, with the keys of the RootSIFT
matcher's scan (service/vision/matcher.py), in float32:

- ``d(a, b)`` is the exact integer dot product, ``s_a = float32(1 / sqrt(float64(sum a^2)))``;
- a's key of b is ``float32(d) * s_b`` and b's key of a is ``float32(d) * s_a`` (float32
  products); ``cos(a, b) = key_a(b) * s_a``;
- a's nearest neighbour in B is the first b of largest key, its second the largest key among
  the other rows (an exact tie makes both equal, so a tie never passes the ratio test);
- a and its nearest b match iff no a' of A has a larger key of b's (mutual; an exact tie keeps
  both), cos > ``min_cos`` and, when ``max_ratio`` < 1 and B has two rows or more,
  ``1 - cos1 < max_ratio^2 (1 - cos2)`` in float64 (for unit vectors ``|a - b|^2 = 2 - 2 cos``).

This is the float32 matching of unit descriptors that XFeat's upstream matcher does, with
each product rounded once instead of a GEMM's 64-term float sums: on 378 comparisons of a
rendered world's map images the matches were identical to that former float32 path.

Fast path: the dots of a tile of A's rows at a time (``matcher.scan_set``) come from an exact
GEMM, NumKong's packed int8 kernels or float32 BLAS (exact: every dot is an integer below
2^24), whichever this CPU runs faster (``matcher.fastest_gemm("int8")``), and the RootSIFT
matcher's fused scan keeps each row's two best keys and best column and each column's best
key; nothing else is materialised. The reference, ``mnn_pairs_reference``, computes the
same in NumPy; both agree bit for bit (tested).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.vision.matcher import check_codes, pack, row_state, scan_set, use_numkong

Pairs = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class PreparedCodes:
    """A set of int8 codes prepared once (per map image): s_b and the packed operand."""

    codes: np.ndarray  # (n, D) int8, no zero row
    inv_norms: np.ndarray  # (n,) float32, s_b
    packed: Any  # NumKong PackedMatrix, or None (float32 BLAS)

    def __len__(self) -> int:
        return len(self.codes)


def _check_i8(x: np.ndarray, name: str) -> np.ndarray:
    return check_codes(x, name, "int8")


def inv_norms_i8(x: np.ndarray) -> np.ndarray:
    """s_x = float32(1 / |x|) per row, |x| in float64 from the exact integer sum of squares;
    a zero row (no direction) is refused."""
    x = _check_i8(x, "codes")
    sq = np.einsum("ij,ij->i", x.astype(np.int64), x.astype(np.int64))
    if np.any(sq == 0):
        raise ValueError("code rows must be non-zero")
    return (1.0 / np.sqrt(sq.astype(np.float64))).astype(np.float32)


def prepare_codes(b: np.ndarray, backend: str = "auto") -> PreparedCodes:
    """Prepare a map image's int8 codes once: inverse norms and (NumKong) packed layout."""
    b = _check_i8(b, "set")
    inv = inv_norms_i8(b) if len(b) else np.zeros(0, np.float32)
    packed = pack(b, "int8") if use_numkong(backend, "int8") and len(b) else None
    return PreparedCodes(b, inv, packed)


def _decide(rm1: np.ndarray, rj1: np.ndarray, rm2: np.ndarray, col_key: np.ndarray,
            cm1: np.ndarray, inv_na: np.ndarray, nb: int, min_cos: float, max_ratio: float
            ) -> Pairs:
    """Rows of A matched (and their columns) from each row's best key ``rm1`` at column
    ``rj1``, its second key ``rm2``, b's key of that row ``col_key`` and each column's best key
    ``cm1``."""
    cos1 = rm1 * inv_na  # float32 products, as the rule defines cos
    ok = (col_key >= cm1[rj1]) & (cos1 > min_cos)
    if max_ratio < 1.0 and nb > 1:
        cos2 = rm2 * inv_na
        ok &= (1.0 - cos1.astype(np.float64)) < max_ratio ** 2 * (1.0 - cos2.astype(np.float64))
    rows = np.flatnonzero(ok)
    return rows, rj1[rows]


# ---- public API ---------------------------------------------------------------------------
def mnn_batch(a: np.ndarray, sets: Sequence[np.ndarray | PreparedCodes], min_cos: float,
              max_ratio: float = 1.0, backend: str = "auto") -> tuple[np.ndarray, list[Pairs]]:
    """m(A, B) for each set B (matches over min(|A|, |B|)) and each set's matches (rows of
    A, rows of B), by the rule in this module's docstring."""
    a = _check_i8(a, "a")
    prepared = [s if isinstance(s, PreparedCodes) else prepare_codes(s, backend) for s in sets]
    scores = np.zeros(len(prepared))
    none = np.zeros(0, np.int64)
    out: list[Pairs] = [(none, none)] * len(prepared)
    na_rows = len(a)
    if na_rows == 0:
        return scores, out
    inv_na = inv_norms_i8(a)
    use_nk = use_numkong(backend, "int8")
    a_f32 = None if use_nk else a.astype(np.float32)
    rows = rm1, rj1, rm2, rd1 = row_state(na_rows)
    for k, s in enumerate(prepared):
        nb = len(s)
        if nb == 0:
            continue
        if s.codes.shape[1] != a.shape[1]:
            raise ValueError(f"code length differs: {a.shape[1]} vs {s.codes.shape[1]}")
        cm1, _ = scan_set(a, a_f32, inv_na, s.codes, s.packed, s.inv_norms, "int8", rows,
                          column_second=False)
        col_key = rd1.astype(np.float32) * inv_na
        out[k] = _decide(rm1, rj1, rm2, col_key, cm1, inv_na, nb, min_cos, max_ratio)
        scores[k] = len(out[k][0]) / min(na_rows, nb)
    return scores, out


def mnn_pairs(a: np.ndarray, b: np.ndarray | PreparedCodes, min_cos: float,
              max_ratio: float = 1.0, backend: str = "auto") -> Pairs:
    """Indices (ia, ib) of the matches of int8 codes ``a`` and ``b``: mutual nearest
    neighbours whose cosine exceeds ``min_cos`` and, when ``max_ratio`` < 1, whose distance is
    below ``max_ratio`` times the distance to a's second nearest neighbour in ``b`` (Lowe's
    ratio: a match not clearly better than the next candidate is chance)."""
    return mnn_batch(a, [b], min_cos, max_ratio, backend)[1][0]


def mnn_scores(a: np.ndarray, sets: Sequence[np.ndarray | PreparedCodes], min_cos: float,
               max_ratio: float = 1.0) -> np.ndarray:
    """m(A, B) for each set B: matches over min(|A|, |B|)."""
    return mnn_batch(a, sets, min_cos, max_ratio)[0]


def mnn_pairs_reference(a: np.ndarray, b: np.ndarray, min_cos: float, max_ratio: float = 1.0
                        ) -> Pairs:
    """The rule in this module's docstring in plain NumPy."""
    a, b = _check_i8(a, "a"), _check_i8(b, "b")
    if len(a) == 0 or len(b) == 0:
        none = np.zeros(0, np.int64)
        return none, none
    dots = (a.astype(np.int64) @ b.astype(np.int64).T).astype(np.float32)
    inv_na, inv_nb = inv_norms_i8(a), inv_norms_i8(b)
    row_keys = dots * inv_nb[None, :]
    col_keys = dots * inv_na[:, None]
    ia = np.arange(len(a))
    j1 = row_keys.argmax(axis=1)
    k1 = row_keys[ia, j1]
    others = row_keys.copy()
    others[ia, j1] = -np.inf
    k2 = others.max(axis=1)
    return _decide(k1, j1, k2, col_keys[ia, j1], col_keys.max(axis=0), inv_na, len(b),
                   min_cos, max_ratio)


def warm_up() -> None:
    """Compile (or load from the cache) the scan for the dot types a frame meets: NumKong's
    int32 and BLAS's float32, on writable and read-only (memory-mapped) codes."""
    rng = np.random.default_rng(0)
    x = rng.integers(-127, 128, (20, 64), dtype=np.int8)
    x[:, 0] = 1  # no zero row
    ro = x.copy()
    ro.flags.writeable = False
    for backend in ("auto", "blas"):
        for a in (x, ro):
            mnn_batch(a, [x[:19], prepare_codes(ro[1:], backend)], 0.8, 0.9, backend)
