from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.vision.features import (
    SiftParams,
    extract,
    match_batch,
    similarity,
    similarity_bfmatcher,
    to_working_size,
)


def _unit(rng: np.random.Generator, n: int, d: int = 128) -> np.ndarray:
    a = rng.random((n, d)).astype(np.float32) ** 3  # non-negative and fairly distinct, as SIFT
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def test_self_similarity_is_one_for_distinct_features() -> None:
    a = _unit(np.random.default_rng(0), 200)
    assert similarity(a, a) == pytest.approx(1.0)


def test_symmetric_and_bounded(sunny1, cloudy1) -> None:
    fa = extract(sunny1.load_image(3)).descriptors
    for img in (sunny1.load_image(5), cloudy1.load_image(4), sunny1.load_image(60)):
        fb = extract(img).descriptors
        ab, ba = similarity(fa, fb), similarity(fb, fa)
        assert ab == pytest.approx(ba)
        assert 0.0 <= ab <= 1.0


def test_empty_and_single_feature_sets() -> None:
    a = _unit(np.random.default_rng(1), 10)
    empty = np.zeros((0, 128), np.float32)
    assert similarity(a, empty) == 0.0
    assert similarity(empty, a) == 0.0
    assert similarity(a, a[:1]) == 0.0  # no second neighbour: no ratio test can pass
    bm = match_batch(a, [a, empty, a[:3]])
    assert bm.scores[0] == pytest.approx(1.0) and bm.scores[1] == 0.0
    assert bm.matched.shape == (3, 10)


def test_batched_equals_bfmatcher_reference(sunny1, cloudy1) -> None:
    frames = [sunny1.load_image(i) for i in range(0, 40, 4)] + [cloudy1.load_image(2)]
    feats = [extract(f).descriptors for f in frames]
    for a in feats[:4]:
        counts = match_batch(a, feats).counts.tolist()
        ref = [similarity_bfmatcher(a, b)[0] for b in feats]
        assert counts == ref
        assert max(ref) > 0  # not a vacuous comparison


def test_exact_duplicate_partner_never_matches() -> None:
    a = _unit(np.random.default_rng(2), 30)
    b = np.vstack([a[:10], a[:1]])  # a[0] has two identical partners: angle ratio 1
    bm = match_batch(a, [b])
    assert not bm.matched[0, 0]
    assert bm.counts[0] == similarity_bfmatcher(a, b)[0] == 9


def test_frames_of_other_sizes_are_resized() -> None:
    params = SiftParams(width=320, height=240)
    big = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    assert to_working_size(big, params).shape == (240, 320)
    f = extract(big, params)
    assert f.keypoints[:, 0].max() < 320 and f.keypoints[:, 1].max() < 240
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)


def test_rootsift_codes_are_the_square_root_of_the_l1_histogram(sunny1) -> None:
    img = sunny1.load_image(4)
    plain = extract(img, SiftParams(clahe=False, root=False))
    root = extract(img, SiftParams(clahe=False, root=True))
    assert plain.codes.dtype == root.codes.dtype == np.uint8
    np.testing.assert_array_equal(plain.keypoints, root.keypoints)
    d = plain.codes.astype(np.float64)  # OpenCV's SIFT is integer-valued: codes are exact
    expect = np.sqrt(d / d.sum(axis=1, keepdims=True))
    got = root.descriptors.astype(np.float64)
    assert np.abs(got - expect).max() < 0.02  # quantisation of the codes only
    # the angle between RootSIFT vectors is the Hellinger distance of the histograms
    np.testing.assert_allclose(np.linalg.norm(root.descriptors, axis=1), 1.0, atol=1e-5)


def test_clahe_finds_more_features_in_flat_light(cloudy1) -> None:
    img = cloudy1.load_image(10)
    assert len(extract(img, SiftParams())) > 1.2 * len(extract(img, SiftParams.papers()))


def test_default_features_match_across_lighting_better(sunny1, cloudy1) -> None:
    """The true place stands out more with CLAHE + RootSIFT than with the papers' SIFT."""
    ratios = {}
    for name, params in (("papers", SiftParams.papers()), ("default", SiftParams())):
        r = []
        for i in range(5, len(cloudy1), 15):
            q = extract(cloudy1.load_image(i), params).descriptors
            d = np.linalg.norm(sunny1.xy - cloudy1.truth_xy[i], axis=1)
            near, far = int(np.argmin(d)), np.flatnonzero(d > 15)[::6]
            sets = [extract(sunny1.load_image(j), params).descriptors
                    for j in [near, *far.tolist()]]
            s = match_batch(q, sets).scores
            r.append(s[0] / max(float(np.median(s[1:])), 1e-3))
        ratios[name] = float(np.median(r))
    assert ratios["default"] > ratios["papers"]


def test_a_rich_frame_keeps_its_strongest_features_up_to_the_cap() -> None:
    """A full-width frame of fine texture gives SIFT thousands of keypoints; the default keeps
    the 2,048 strongest (a comparison's exact matching stays bounded), ``n_features=0`` all of
    them, and a frame below the cap keeps every feature either way."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (370, 1226)).astype(np.uint8), (3, 3), 0)
    capped = extract(texture, SiftParams(width=1226, height=370))
    every = extract(texture, SiftParams(width=1226, height=370, n_features=0))
    assert len(every) > 2 * 2048
    assert 2048 <= len(capped) <= 2048 + 8  # OpenCV keeps ties at the cut
    small = cv2.resize(texture, (160, 120), interpolation=cv2.INTER_AREA)
    few = extract(small, SiftParams(width=160, height=120))
    assert 0 < len(few) < 2048
    np.testing.assert_array_equal(
        few.codes, extract(small, SiftParams(width=160, height=120, n_features=0)).codes)
