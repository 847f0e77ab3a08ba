"""The fast uint8 matcher equals its exact reference (and the float path) on real frames."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.vision.features import ROOT_SCALE, extract, match_batch, unit_descriptors
from service.vision.matcher import (
    _jit,
    match_batch_u8,
    match_batch_u8_pairs,
    match_batch_u8_reference,
    norms_u8,
    prepare,
    warm_up,
)

BACKENDS = ("auto", "numkong", "blas")  # auto: the faster of the two here (fastest_gemm)


@pytest.fixture(scope="module")
def frames(sunny1, sunny2, cloudy1) -> dict[str, np.ndarray]:
    """CLAHE + RootSIFT uint8 features: neighbouring, same and far places, two lightings."""
    out = {}
    for name, rnd in (("sunny1", sunny1), ("sunny2", sunny2), ("cloudy1", cloudy1)):
        for i in (3, 5, 40, 100):
            out[f"{name}/{i}"] = extract(rnd.load_image(i)).codes
    return out


@pytest.fixture(scope="module")
def references(frames) -> dict:
    sets = [frames[n] for n in sorted(frames)]
    return {n: match_batch_u8_reference(frames[n], sets) for n in sorted(frames)}


def _same(x, y) -> None:
    np.testing.assert_array_equal(x.counts, y.counts)
    np.testing.assert_array_equal(x.matched, y.matched)
    np.testing.assert_array_equal(x.scores, y.scores)


def test_features_are_quantised_rootsift(frames) -> None:
    for q in frames.values():
        assert q.dtype == np.uint8 and q.shape[1] == 128 and len(q) > 100
        n = norms_u8(q)
        # unit vectors scaled by ROOT_SCALE, rounded (a component rarely clips at 255)
        assert np.all(np.abs(n - ROOT_SCALE) < ROOT_SCALE * 0.05)


@pytest.mark.parametrize("backend", BACKENDS)
def test_fast_path_equals_reference_on_rendered_frames(frames, references, backend) -> None:
    warm_up()
    names = sorted(frames)
    sets = [frames[n] for n in names]
    prepared = [prepare(s, backend) for s in sets]
    counts = []
    for name in names:
        ref = references[name]
        _same(match_batch_u8(frames[name], prepared, backend=backend), ref)
        _same(match_batch_u8(frames[name], sets, backend=backend), ref)  # unprepared sets
        counts.append(ref.counts)
    counts = np.array(counts)
    # the comparison is not trivial: self-matches, neighbours that match, far places that don't
    assert np.all(np.diag(counts) > 0.5 * np.array([len(s) for s in sets]))
    assert (counts[np.eye(len(names)) == 0] > 0).sum() >= len(names)
    assert (counts == 0).sum() > 0 or counts.min() < counts.max() / 20


def test_reference_agrees_with_float_path_on_rendered_frames(frames, references) -> None:
    """The float32 path on the normalised vectors gives the reference's counts on these frames
    up to a borderline ratio that float32 rounding flips: at most one match per comparison and
    a few in all (the exact matcher, which the service uses, equals the reference exactly)."""
    names = sorted(frames)
    sets = [frames[n] for n in names]
    unit = [unit_descriptors(s) for s in sets]
    diffs, total = [], 0
    for name in names:
        flt = match_batch(unit_descriptors(frames[name]), unit)
        diffs.append(np.abs(references[name].counts - flt.counts))
        total += int(references[name].counts.sum())
    assert max(int(d.max()) for d in diffs) <= 1
    assert sum(int(d.sum()) for d in diffs) <= max(2, total // 200)


@pytest.mark.parametrize("backend", BACKENDS)
def test_ties_and_near_ties_follow_the_reference(backend) -> None:
    """Tiny integer vectors give many exact ties and near ties: the exact fallbacks decide."""
    rng = np.random.default_rng(7)
    for _ in range(150):
        n1, n2 = rng.integers(0, 70, 2)
        dim = int(rng.integers(2, 8))
        a = rng.integers(0, 3, (n1, dim)).astype(np.uint8)
        b = rng.integers(0, 3, (n2, dim)).astype(np.uint8)
        a[a.sum(axis=1) == 0, 0] = 1
        b[b.sum(axis=1) == 0, 0] = 1
        sets = [b, a, np.vstack([b, b[:1]])]
        _same(match_batch_u8(a, sets, backend=backend), match_batch_u8_reference(a, sets))


def test_gemm_width_moves_only_widths_near_a_multiple_of_512() -> None:
    """The packed GEMM runs some columns wider (zero rows) where its output rows would lie a
    multiple of 2 KiB apart; every other width is the set's own."""
    from service.vision.matcher import gemm_width

    moved = {n: gemm_width(n) for n in range(0, 4200) if gemm_width(n) != n}
    assert all(0 < w - n <= 28 and min(w % 512, 512 - w % 512) >= 16 for n, w in moved.items())
    assert {512, 1024, 1016, 1036, 2048} <= set(moved) and not {499, 600, 1000, 1300} & set(moved)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sets_the_gemm_runs_wider_match_as_the_reference(backend) -> None:
    """Sets of 505, 512 and 1,030 rows (their GEMM is wider than the set, with zero rows) and
    one of a frame's near copy padded to 1,024 rows: the same matches as the reference."""
    rng = np.random.default_rng(3)
    a = rng.integers(0, 40, (300, 128)).astype(np.uint8)
    near = np.clip(a.astype(int) + rng.integers(-2, 3, a.shape), 0, 255).astype(np.uint8)
    sets = [rng.integers(0, 40, (n, 128)).astype(np.uint8) for n in (505, 512, 1030)]
    sets.append(np.vstack([rng.integers(0, 40, (724, 128)).astype(np.uint8), near]))
    got = match_batch_u8(a, sets, backend=backend)
    _same(got, match_batch_u8_reference(a, sets))
    assert got.counts[-1] > 100  # the near copy matches


def test_tiles_hold_at_most_512_kib_of_dots() -> None:
    """NumKong's tile against a set: 32-256 rows, a multiple of 16, at most 512 KiB of 4-byte
    dots where 32 rows allow it, fewer rows for wider sets."""
    from service.vision.matcher import tile_rows

    widths = [1, 300, 610, 1040, 1300, 2064, 4000, 20000]
    rows = [tile_rows(w) for w in widths]
    assert all(32 <= r <= 256 and r % 16 == 0 for r in rows)
    assert all(r * 4 * w <= 512 * 1024 for r, w in zip(rows, widths, strict=True) if r > 32)
    assert rows == sorted(rows, reverse=True) and rows[0] == 256 and rows[-1] == 32


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_wide_set_in_many_small_tiles_matches_as_the_reference(backend) -> None:
    """A set of 4,000 rows: NumKong runs 130 frame rows in tiles of 32 (the last one of 2);
    the same matches as the reference."""
    rng = np.random.default_rng(4)
    a = rng.integers(0, 40, (130, 128)).astype(np.uint8)
    b = rng.integers(0, 40, (4000, 128)).astype(np.uint8)
    b[1000:1130] = np.clip(a.astype(int) + rng.integers(-2, 3, a.shape), 0, 255)
    got = match_batch_u8(a, [b], backend=backend)
    _same(got, match_batch_u8_reference(a, [b]))
    assert got.counts[0] > 60


def _reference_pairs(a: np.ndarray, b: np.ndarray, delta: float) -> tuple[np.ndarray, ...]:
    """The reference's matches at ``delta`` and each one's exact nearest neighbour in b."""
    rows = np.flatnonzero(match_batch_u8_reference(a, [b], delta).matched[0])
    cos = (a[rows].astype(np.float64) @ b.astype(np.float64).T) \
        / (norms_u8(a)[rows, None] * norms_u8(b)[None, :])
    return rows, cos.argmax(axis=1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_pairs_at_a_second_ratio_come_from_the_same_pass(frames, references, backend) -> None:
    """The geometry's matches (ratio 0.9) kept by the similarity's pass (ratio 0.6) are the
    reference's at 0.9, each with its exact nearest neighbour; the similarity is unchanged."""
    names = sorted(frames)
    sets = [prepare(frames[n], backend) for n in names]
    looser = 0
    for name in names[::3]:
        r, pairs = match_batch_u8_pairs(frames[name], sets, 0.6, 0.9, backend=backend)
        _same(r, references[name])
        for n, (rows, cols), m in zip(names, pairs, r.matched, strict=True):
            want = _reference_pairs(frames[name], frames[n], 0.9)
            np.testing.assert_array_equal(rows, want[0])
            np.testing.assert_array_equal(cols, want[1])
            assert set(np.flatnonzero(m)) <= set(rows.tolist())  # 0.6's matches pass 0.9
            looser += len(rows) - int(m.sum())
        same, kept = match_batch_u8_pairs(frames[name], sets, 0.6, 0.6, backend=backend)
        assert all(np.array_equal(k[0], np.flatnonzero(m)) for k, m in zip(kept, same.matched,
                                                                          strict=True))
    assert looser > 0  # the second ratio decides differently


def test_exact_tie_never_passes_and_identical_descriptor_does() -> None:
    rng = np.random.default_rng(0)
    x = rng.integers(1, 255, (3, 128)).astype(np.uint8)
    a = x[:2]
    tie = np.stack([x[0], x[0], x[2]])  # a0 has two equal nearest neighbours
    clean = np.stack([x[0], x[2]])  # a0 == b0: angle 0 passes any ratio test
    for backend in BACKENDS:
        r = match_batch_u8(a, [tie, clean], backend=backend)
        assert not r.matched[0, 0]
        assert r.matched[1, 0]
        _same(r, match_batch_u8_reference(a, [tie, clean]))


def test_small_sets_match_nothing() -> None:
    x = np.random.default_rng(1).integers(1, 255, (10, 128)).astype(np.uint8)
    r = match_batch_u8(x, [x[:0], x[:1], x])
    assert r.counts.tolist() == [0, 0, 10]
    assert r.scores.tolist() == [0.0, 0.0, 1.0]
    assert match_batch_u8(x[:1], [x]).counts.tolist() == [0]
    assert match_batch_u8(x, []).counts.shape == (0,)
    _, pairs = match_batch_u8_pairs(x[:1], [x, x[:1]], 0.6, 0.9)
    assert [len(p[0]) for p in pairs] == [0, 0]


def test_bad_input_is_refused() -> None:
    x = np.ones((4, 128), np.uint8)
    with pytest.raises(ValueError, match="uint8"):
        match_batch_u8(x.astype(np.float32), [x])
    with pytest.raises(ValueError, match="non-zero"):
        match_batch_u8(np.vstack([x, np.zeros((1, 128), np.uint8)]), [x])
    with pytest.raises(ValueError, match="backend"):
        match_batch_u8(x, [x], backend="gpu")
    with pytest.raises(ValueError, match="too long"):
        match_batch_u8(np.ones((4, 300), np.uint8), [np.ones((4, 300), np.uint8)])


def test_jit_falls_back_without_a_cache_location() -> None:
    """A function numba cannot cache (no source file) still compiles, uncached."""
    scope: dict = {}
    exec("def f(x):\n    return x + 1\n", scope)  # no source file: no cache locator
    assert _jit(scope["f"])(41) == 42


def test_module_works_where_numba_can_write_no_cache() -> None:
    """Read-only install and no writable user cache: every kernel compiles uncached, results
    unchanged (a fresh interpreter, numba's cache locators all refusing)."""
    code = (
        "import numba.core.caching as c\n"
        "impl = getattr(c, 'CacheImpl', None) or getattr(c, '_CacheImpl')\n"
        "impl._locator_classes = []\n"  # no location accepts a cache
        "import numpy as np\n"
        "from service.vision.matcher import match_batch_u8, match_batch_u8_reference\n"
        "x = np.random.default_rng(0).integers(1, 255, (40, 128)).astype(np.uint8)\n"
        "r = match_batch_u8(x, [x[5:], x[:30]])\n"
        "assert (r.counts == match_batch_u8_reference(x, [x[5:], x[:30]]).counts).all()\n"
        "print(r.counts.tolist())\n"
    )
    root = Path(__file__).resolve().parent.parent
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=False, cwd=root)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[35, 30]"
