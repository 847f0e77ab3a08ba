"""The lab's method names (the papers' tables: DPSO-80, PF-l-300, ...), each listed once with
the estimator and parameters it stands for. The estimator names themselves are the service's
(``service.estimators.registry``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Method:
    estimator: str  # a name of service.api.models.EstimatorName
    params: dict[str, Any] = field(default_factory=dict)
    papers_map: bool = False  # SIFT + pruning as in the papers, else the service's features


METHODS: dict[str, Method] = {
    "DPSO-80": Method("dpso"),
    "DPSO-80-paper": Method("dpso", {"variant": "paper"}, papers_map=True),
    # DPSO without the place index: global placements around random map images (as before)
    "DPSO-80-random": Method("dpso", {"place_candidates": 0}),
    "PF-l-100": Method("pf-l", {"n_particles": 100}),
    "PF-l-300": Method("pf-l", {"n_particles": 300}),
    "PF-g-300": Method("pf-g", {"n_particles": 300}),
}
