"""The estimator registry: every estimator name (and DPSO variant) is listed here once and
dispatched here once, to its parameter class and its constructor.

Names: ``service.api.models.EstimatorName`` (the API's schema) and
``service.api.params.DPSOVariant``; this module maps each to its class. Adding an estimator:
its name to ``EstimatorName``, its parameter class to ``service/api/params.py``, one
``EstimatorSpec`` below (CONTRIBUTING.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, get_args

import numpy as np

from service.api.models import EstimatorName
from service.api.params import CommonParams, DPSOParams, DPSOVariant, ParamError, PFParams
from service.estimators.base import Estimator
from service.estimators.fitness import MapIndex
from service.estimators.multi_swarm_dpso import MultiSwarmDPSO
from service.estimators.paper_dpso import DPSO
from service.estimators.particle_filter import ParticleFilter

ESTIMATORS: tuple[str, ...] = get_args(EstimatorName)

Build = Callable[[MapIndex, Any, np.random.Generator], Estimator]


@dataclass(frozen=True)
class EstimatorSpec:
    params: type[CommonParams]  # parameter class with the papers' defaults
    build: Build  # (map, parameters, generator) -> estimator


DPSO_VARIANT_CLASSES: dict[str, Build] = {
    "swarmloc": MultiSwarmDPSO,  # the service's default (docs/reference/estimators.md)
    "paper": DPSO,  # the journal's DPSO as published
}


def _dpso(index: MapIndex, p: DPSOParams, rng: np.random.Generator) -> Estimator:
    return DPSO_VARIANT_CLASSES[p.variant](index, p, rng)


REGISTRY: dict[str, EstimatorSpec] = {
    "dpso": EstimatorSpec(DPSOParams, _dpso),
    "pf-g": EstimatorSpec(PFParams, lambda m, p, rng: ParticleFilter(m, p, rng, "gauss")),
    "pf-l": EstimatorSpec(PFParams, lambda m, p, rng: ParticleFilter(m, p, rng, "linear")),
}
assert tuple(REGISTRY) == ESTIMATORS, "REGISTRY must cover service.api.models.EstimatorName"
assert tuple(DPSO_VARIANT_CLASSES) == get_args(DPSOVariant), "cover every DPSOVariant"


def spec_of(estimator: str) -> EstimatorSpec:
    try:
        return REGISTRY[estimator]
    except KeyError:
        raise ParamError(f"unknown estimator '{estimator}'; choose one of "
                         f"{list(ESTIMATORS)}") from None


def params_for(estimator: str, overrides: dict[str, Any] | None = None) -> CommonParams:
    """The estimator's parameters: its defaults with ``overrides`` (validated)."""
    return spec_of(estimator).params().with_overrides(overrides)


def make_estimator(index: MapIndex, estimator: str, params: dict[str, Any] | None,
                   rng: np.random.Generator) -> Estimator:
    """A new estimator of that name on the map, with its parameters and generator."""
    return spec_of(estimator).build(index, params_for(estimator, params), rng)


def with_map_sigma(estimator: str, overrides: dict[str, Any] | None,
                   position_sigma_m: float | None) -> dict[str, Any] | None:
    """``overrides`` with the map's own position error as the floor of a located frame's
    radius (``metric_map_sigma_m``) where the map knows it (positions fused with odometry,
    service/maps/positions.py) and the session did not set it."""
    fields = getattr(spec_of(estimator).params, "model_fields", {})
    if (position_sigma_m is None or "metric_map_sigma_m" not in fields
            or "metric_map_sigma_m" in (overrides or {})):
        return overrides
    return {**(overrides or {}), "metric_map_sigma_m": position_sigma_m}
