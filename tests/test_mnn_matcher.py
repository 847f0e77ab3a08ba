"""XFeat's exact int8 mutual-nearest-neighbour matcher (service/vision/mnn_matcher.py): the
fast path equals its NumPy reference bit for bit on either GEMM, at the edges too, and gives
upstream's float32 matching of unit descriptors on real XFeat features."""

from __future__ import annotations

import numpy as np
import pytest

from client.dataset import Round
from service.maps.route_map import RouteMap, build_map_from_rounds
from service.vision.features import extract, unit_descriptors
from service.vision.mnn_matcher import (
    inv_norms_i8,
    mnn_batch,
    mnn_pairs_reference,
    prepare_codes,
)
from service.vision.xfeat import XFeatParams

BACKENDS = ("auto", "blas")


def _codes(rng: np.random.Generator, n: int, dims: int = 64) -> np.ndarray:
    x = rng.normal(size=(n, dims))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    c = np.clip(np.rint(x * 127), -127, 127).astype(np.int8)
    c[~c.any(axis=1), 0] = 1
    return c


def _same(got: tuple[np.ndarray, np.ndarray], want: tuple[np.ndarray, np.ndarray]) -> bool:
    return bool(np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]))


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_fast_path_equals_the_reference(backend: str) -> None:
    """Sizes around the row scan's 16 lanes and 64-column sweeps, several NumKong tiles
    (``tile_rows``) of the frame's 601 rows, sets the GEMM runs wider (512, 1,024:
    ``gemm_width``), a near copy of the frame among the sets (many matches; once padded to
    1,024 rows), gates on and off."""
    rng = np.random.default_rng(0)
    a = _codes(rng, 601)
    near = np.clip(a.astype(int) + rng.integers(-6, 7, a.shape), -127, 127).astype(np.int8)
    sets = [_codes(rng, n) for n in (1, 2, 15, 17, 31, 33, 63, 65, 256, 512, 700)] + \
        [near[::-1].copy()] + \
        [np.vstack([_codes(rng, 423), near])]
    total = 0
    for min_cos, ratio in ((0.82, 0.93), (0.0, 1.0), (0.3, 0.8)):
        scores, pairs = mnn_batch(a, [prepare_codes(b, backend) for b in sets], min_cos,
                                     ratio, backend)
        for k, b in enumerate(sets):
            want = mnn_pairs_reference(a, b, min_cos, ratio)
            assert _same(pairs[k], want), (backend, min_cos, ratio, len(b))
            assert scores[k] == len(want[0]) / min(len(a), len(b))
            total += len(want[0])
    assert total > 1200  # the near copies match: the comparison is not of empty sets


@pytest.mark.parametrize("backend", BACKENDS)
def test_negative_keys_and_ties(backend: str) -> None:
    """Rows whose every cosine is negative still find their nearest neighbour (the scan starts
    below any key), and a duplicated map row makes a tie: both rows of A that pick it stay
    mutual, and the ratio test refuses the tie."""
    rng = np.random.default_rng(1)
    a = -np.abs(_codes(rng, 5))  # every dot of A with B is negative
    for b in (np.abs(_codes(rng, 40)), np.abs(_codes(rng, 1024))):  # 1,024: a wider GEMM,
        for ratio in (1.0, 0.999):  # whose zero dots beyond the set no scan may read
            got = mnn_batch(a, [b], -1.0, ratio, backend)[1][0]
            assert _same(got, mnn_pairs_reference(a, b, -1.0, ratio))
            assert len(got[0]) >= 1
    b = _codes(rng, 3)
    twin = np.stack([b[0], b[0], b[1]])
    plain = mnn_batch(b[:1], [twin], 0.5, 1.0, backend)[1][0]
    assert plain[0].tolist() == [0] and plain[1].tolist() == [0]  # the first of the tie
    assert len(mnn_batch(b[:1], [twin], 0.5, 0.99, backend)[1][0][0]) == 0
    both = np.stack([b[0], b[0]])
    ia, ib = mnn_batch(both, [b], 0.5, 1.0, backend)[1][0]
    assert ia.tolist() == [0, 1] and ib.tolist() == [0, 0]


def test_bad_codes_are_refused_with_the_reason() -> None:
    with pytest.raises(ValueError, match="int8"):
        prepare_codes(np.zeros((3, 64), np.uint8))
    with pytest.raises(ValueError, match="non-zero"):
        inv_norms_i8(np.zeros((2, 64), np.int8))
    with pytest.raises(ValueError, match="too long"):
        prepare_codes(np.ones((2, 2000), np.int8))
    with pytest.raises(ValueError, match="length differs"):
        mnn_batch(np.ones((2, 64), np.int8), [np.ones((2, 32), np.int8)], 0.8)
    with pytest.raises(ValueError, match="backend"):
        mnn_batch(np.ones((2, 64), np.int8), [np.ones((2, 64), np.int8)], 0.8, 1.0, "gpu")


def _upstream(a: np.ndarray, b: np.ndarray, min_cos: float, ratio: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """Upstream XFeat's matching of unit float32 descriptors (one float GEMM), with the
    ratio test: what the similarity computed before this matcher."""
    ua, ub = unit_descriptors(a), unit_descriptors(b)
    sim = ua @ ub.T
    ia = np.arange(len(a))
    j1 = sim.argmax(axis=1)
    c1 = sim[ia, j1]
    ok = (c1 >= sim.max(axis=0)[j1]) & (c1 > min_cos)
    sim[ia, j1] = -2.0
    ok &= (1.0 - c1) < ratio ** 2 * (1.0 - sim.max(axis=1))
    return ia[ok], j1[ok]


def test_real_xfeat_features_match_as_upstream_does(sunny1: Round, cloudy1: Round) -> None:
    """On the small world's XFeat features (frames of another light against map images), the
    int8 matcher keeps exactly the pairs upstream's float32 matching keeps."""
    params = XFeatParams()
    m: RouteMap = build_map_from_rounds([sunny1.subset(list(range(0, len(sunny1), 6)))],
                                        params=params)
    frames = [extract(cloudy1.load_image(i), params).codes for i in range(0, len(cloudy1), 9)]
    compared = matched = 0
    for codes in frames:
        ids = list(range(m.n_images))
        _, pairs = mnn_batch(codes, [m.features_of(i) for i in ids], params.min_cos,
                                params.max_ratio)
        for i, got in zip(ids, pairs, strict=True):
            b = np.asarray(m.codes[m.offsets[i]:m.offsets[i + 1]])
            assert _same(got, _upstream(codes, b, params.min_cos, params.max_ratio))
            compared += 1
            matched += len(got[0])
    assert compared >= 50 and matched > 100
