"""The journal's published numbers (Kronfeld, Weiss, Zell, "Swarm-supported outdoor
localization with sparse visual data", Sec. 7), copied from its tables.

Fig. 4 (error against simulated speed) and Fig. 6 (error over the kidnapped run) are plots
without tabulated values; only Tab. 1-4 give numbers.
"""

from __future__ import annotations

# Tab. 1: sunny (round 1) vs cloudy (round 1): (mean error m, avg. comparisons per image)
TAB1: dict[str, tuple[float, float]] = {
    "DPSO-40": (2.84, 17.9),
    "DPSO-60": (2.60, 22.3),
    "DPSO-80": (2.54, 25.9),
    "DPSO-100": (2.50, 29.1),
    "DPSO-120": (2.46, 32.0),
    "PF-g-100": (3.95, 40.8),
    "PF-g-300": (3.39, 62.4),
    "PF-l-100": (2.80, 42.2),
    "PF-l-300": (2.38, 69.6),
}

# Tab. 2: DPSO-80, sunny1 vs cloudy1: (mean error, std) in the standard and kidnapped case
TAB2: dict[tuple[str, str], tuple[float, float]] = {
    ("non-adaptive", "standard"): (2.56, 0.71),
    ("non-adaptive", "kidnapped"): (10.54, 22.1),
    ("adaptive", "standard"): (2.50, 0.35),
    ("adaptive", "kidnapped"): (5.58, 14.2),
}

# Tab. 3: PF-l-300 grid search, sunny1 vs cloudy1, mean error (m) averaged over 365 runs.
# Rows sigma_acc; per sigma_rot the three initial speeds v_R, 2 v_R, 3 v_R.
TAB3_SIGMA_ROT = (20, 30, 40, 50, 60)
TAB3_SIGMA_ACC = (1e-2, 1e-3, 1e-4, 1e-5)
TAB3_V_INIT = (1, 2, 3)  # multiples of the driven speed v_R
_TAB3_ROWS = {
    1e-2: (5.43, 4.22, 4.31, 4.79, 3.55, 3.60, 4.49, 3.34, 3.42, 4.37, 3.22, 3.21, 4.23, 3.12,
           3.11),
    1e-3: (5.70, 3.56, 3.22, 5.16, 2.81, 2.61, 4.77, 2.65, 2.56, 4.54, 2.59, 2.53, 4.51, 2.58,
           2.51),
    1e-4: (5.62, 3.45, 3.13, 5.18, 2.72, 2.61, 4.70, 2.60, 2.55, 4.55, 2.54, 2.54, 4.44, 2.54,
           2.52),
    1e-5: (5.63, 3.43, 3.14, 5.14, 2.72, 2.61, 4.68, 2.60, 2.56, 4.50, 2.56, 2.54, 4.36, 2.54,
           2.53),
}
TAB3: dict[tuple[int, float, int], float] = {
    (rot, acc, v): row[3 * i + j]
    for acc, row in _TAB3_ROWS.items()
    for i, rot in enumerate(TAB3_SIGMA_ROT)
    for j, v in enumerate(TAB3_V_INIT)
}
TAB3_COMPARISONS_BEST = 72.15  # "72.15 for the best configuration tested" (Sec. 7.2)

# Tab. 4: (mean error, std, avg. comparisons per image) per scenario and method
TAB4: dict[str, dict[str, tuple[float, float, float]]] = {
    "sunny vs sunny": {
        "PF-g-300": (2.15, 0.29, 60.8), "PF-l-100": (2.24, 0.29, 44.72),
        "PF-l-300": (1.79, 0.30, 66.6), "DPSO-80": (1.99, 0.36, 21.4)},
    "cloudy vs cloudy": {
        "PF-g-300": (2.06, 0.56, 55.3), "PF-l-100": (1.92, 0.27, 38.31),
        "PF-l-300": (1.43, 0.33, 62.2), "DPSO-80": (1.47, 0.35, 20.5)},
    "sunny vs cloudy": {
        "PF-g-300": (3.28, 0.27, 60.9), "PF-l-100": (3.11, 0.42, 41.62),
        "PF-l-300": (2.52, 0.32, 69.1), "DPSO-80": (2.77, 0.40, 22.3)},
}

# Sec. 6: one round is 260 m with about 360-400 images, one image per second at ~0.6 m/s
PAPER_IMAGES_PER_ROUND = 365
PAPER_SPEED_MPS = 0.6
