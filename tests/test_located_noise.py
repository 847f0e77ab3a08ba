"""The located positions' jitter (service/estimators/located_noise.py), on positions with known
noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.estimators.located_noise import LocatedNoise


def _track(n: int, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """A robot driving 0.6 m per frame around a 25 m circle, located with N(0, sigma^2)."""
    a = np.arange(n) * 0.6 / 25.0
    return 25.0 * np.c_[np.cos(a), np.sin(a)] + rng.normal(0.0, sigma, (n, 2))


@pytest.mark.parametrize("sigma", [0.05, 0.15, 0.4])
def test_the_jitter_is_the_located_positions_noise(sigma: float) -> None:
    est = []
    for seed in range(20):
        noise = LocatedNoise(window=64)
        for t, xy in enumerate(_track(80, sigma, np.random.default_rng(seed))):
            noise.add(t, xy)
        est.append(noise.jitter(prior=9.0))
    assert abs(np.median(est) / sigma - 1.0) < 0.15


def test_the_prior_holds_until_enough_consecutive_triples() -> None:
    noise = LocatedNoise()
    xy = _track(40, 0.2, np.random.default_rng(0))
    for t in range(0, 40, 2):  # every other frame: no three consecutive frames
        noise.add(t, xy[t])
    assert noise.jitter(prior=0.7) == 0.7 and noise.diffs == []
    for t in range(10):  # ten consecutive frames: eight triples
        noise.add(100 + t, xy[t])
    assert len(noise.diffs) == 8 and noise.jitter(prior=0.7) != 0.7
    noise.reset()
    assert noise.jitter(prior=0.7) == 0.7


def test_the_radius_has_the_maps_floor_and_one_wrong_image_barely_moves_it() -> None:
    noise = LocatedNoise()
    assert noise.sigma(0.3, 2.0, prior=0.0) == pytest.approx(0.3)
    assert noise.sigma(0.3, 2.0, prior=0.2) == pytest.approx(math.hypot(0.3, 0.4))
    xy = _track(60, 0.1, np.random.default_rng(1))
    for t in range(60):
        noise.add(t, xy[t])
    calm = noise.jitter(prior=0.0)
    noise.add(60, xy[59] + np.array([8.0, 0.0]))  # one frame located at a wrong image
    assert noise.jitter(prior=0.0) < 1.2 * calm
