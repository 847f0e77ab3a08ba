"""One robot's localizer: a map, an estimator (DPSO | PF-g | PF-l) and its generator."""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from service.api.errors import InvalidParameters
from service.api.models import (
    MAX_ODOM_STEP_M,
    Estimate,
    EstimatorName,
    HeadingSource,
    Hypothesis,
    Odometry,
)
from service.api.params import DPSOParams
from service.engine.both_layers import BothLayers
from service.estimators.base import Status, StepResult
from service.estimators.fitness import ComparisonCache, LocateFn, TypeScores
from service.estimators.odometry import OdomStep, body_step
from service.estimators.registry import make_estimator, with_map_sigma
from service.maps.experiences import (
    SEED_SHARE,
    LayerChoice,
    base_images,
    experience_layers,
    same_light_level,
)
from service.maps.route_map import RouteMap
from service.vision.features import Features, extract
from service.vision.map_geometry import FramePairs, GeometryParams
from service.vision.metric_pose import Offset
from service.vision.place_index import PlaceSeeder, Verify

_UNKNOWN_VAR = 1e6
_FOUND = (Status.TRACKING.value, Status.RECOVERING.value)  # an estimate the gap rule may use


class Localizer:
    """Feeds frames to an estimator and turns its output into an ``Estimate``.

    Same map, frames, parameters and seed give identical estimates, bit for bit.
    """

    def __init__(self, route_map: RouteMap, estimator: str = "dpso",
                 params: dict[str, Any] | None = None, seed: int = 0) -> None:
        self.map = route_map
        self.estimator_name = estimator
        self.seed = seed
        self.estimator = make_estimator(route_map, estimator,
                                        with_map_sigma(estimator, params,
                                                       route_map.position_sigma_m),
                                        np.random.default_rng(seed))
        p = self.estimator.params  # the papers' estimators keep their random placements
        k = p.place_candidates if isinstance(p, DPSOParams) and p.variant == "swarmloc" else 0
        # a map with experiences ranks its own images and the learned ones apart, and a
        # searching swarm is given a learned image only where the frame clearly matches it
        # (``_verify``): a learned image of today's light looks more like any frame of that
        # light than the map's images at the true place
        own = base_images(route_map) if experience_layers(route_map) else None
        learned = None if own is None else \
            np.setdiff1d(np.arange(len(route_map.positions)), own)
        self.seeder = (PlaceSeeder(route_map.place_index, route_map.positions, k, among=own,
                                   learned=learned)
                       if route_map.place_index is not None and k > 0 else None)
        self._level: float | None = None  # the map's same-light level, once a search needs it
        self.seq = 0
        self.last: Estimate | None = None
        self.choice = LayerChoice()  # the layer frames are matched with (maps with experiences)
        # the previous frame's odometry pose (x, y, yaw); None: that frame had none
        self.odom_prev: tuple[float, float, float] | None = None

    @property
    def params(self) -> dict[str, Any]:
        return self.estimator.params.as_dict()

    def reset(self, near: tuple[float, float] | None = None, radius: float | None = None) -> None:
        self.estimator.reset(near, radius)
        self.odom_prev = None

    def extract(self, image: np.ndarray) -> Features:
        return extract(image, self.map.feature_params)

    def localize(self, image: np.ndarray, t: float | None = None,
                 prior: tuple[float, float, float] | None = None,
                 odom: Odometry | None = None) -> Estimate:
        return self.step(self.extract(image), t, prior, odom)

    def take_odometry(self, odom: Odometry | None) -> OdomStep | None:
        """The robot's motion since the previous frame from its odometry pose (None without
        one, or after a frame without one), and ``odom`` kept for the next frame;
        InvalidParameters for a step longer than MAX_ODOM_STEP_M, before anything changes."""
        step = self._odom_step(odom)
        self.odom_prev = None if odom is None else (odom.x, odom.y, odom.yaw)
        return step

    def _odom_step(self, odom: Odometry | None) -> OdomStep | None:
        if odom is None or self.odom_prev is None:
            return None
        p = self.estimator.params
        step = body_step(self.odom_prev, (odom.x, odom.y, odom.yaw),
                         p.odom_var_xy if odom.var_xy is None else odom.var_xy,
                         p.odom_var_yaw if odom.var_yaw is None else odom.var_yaw)
        if not step.distance <= MAX_ODOM_STEP_M:
            raise InvalidParameters(
                f"odometry moved {step.distance:.4g} m since the robot's previous frame, more "
                f"than {MAX_ODOM_STEP_M:g} m: a glitch or a reset odometry; send the frame "
                "without odometry (or reset the session) to start it again")
        return step

    def step(self, features: Features, t: float | None = None,
             prior: tuple[float, float, float] | None = None,
             odom: Odometry | None = None) -> Estimate:
        """One frame: optional pose prior (x, y, radius), optional odometry pose, estimator
        step, Estimate."""
        motion = self.take_odometry(odom)
        if prior is not None:
            self.estimator.constrain((prior[0], prior[1]), prior[2])
        codes = features.codes
        learned = bool(experience_layers(self.map))
        verified = ComparisonCache(lambda ids: self.map.similarity(features, ids)) \
            if learned else None
        self.seed_places(codes, None if verified is None else self._verify(verified))
        # the similarity keeps the frame's matches for the geometry (no second matching),
        # XFeat's too where its geometry may be tried (``locator``)
        kept = FramePairs(GeometryParams().delta) if self.map.geometry is not None else None
        kept2 = FramePairs(GeometryParams().delta) if self._second_geometry(features) \
            else None
        locate = self.locator(features, kept, kept2)
        both = None
        if learned and locate is not None:  # service/engine/both_layers.py
            locate = both = BothLayers(self.map, locate, self.estimator.spacing)
        # a map of two types: the first type's own m beside the fused one (its vouching)
        first = TypeScores() if self.map.fusion is not None and features.second is not None \
            else None
        record = None if first is None else first.record
        if not learned:
            res = self.estimator.step(
                lambda ids: self.map.similarity(features, ids, kept, kept2, first=record), t,
                locate, motion, first=first)
            comparisons = res.comparisons
        else:  # one layer per particle, then the layer probes (service/maps/experiences.py)
            similarity = ComparisonCache(
                lambda ids: self.map.similarity(features, ids, kept, kept2, first=record))
            res = self.estimator.step(self.choice.scaled(self.map, similarity), t, locate,
                                      motion,
                                      nearest=self.choice.nearest(self.map, self._at()),
                                      first=first)
            # the probes score the layers at the true place: where the swarm tracks (its
            # place reported or still to be confirmed by the geometry)
            if res.status is Status.TRACKING or res.unconfirmed:
                self.choice.probe(self.map, similarity, res.position)
            comparisons = similarity.comparisons
        if verified is not None:  # learned candidates compared for the search
            comparisons += verified.comparisons
        if both is not None:  # the map's own images located beside learned ones
            comparisons += both.extra
        self.seq += 1
        self.last = self._estimate(res, t, comparisons, learned)
        return self.last

    def _at(self) -> np.ndarray | None:
        """The previous estimate's position once the session has found its place (None: none
        yet, still initializing, or lost: the swarm searches)."""
        last = self.last
        return None if last is None or last.status not in _FOUND \
            else np.array([last.x, last.y])

    def _second_geometry(self, features: Features) -> bool:
        """Whether a frame RootSIFT's geometry cannot locate is tried with XFeat's: a map
        and a frame of two feature types with the camera, DPSO with ``metric_second``."""
        p = self.estimator.params
        return self.map.second_geometry is not None and features.second is not None \
            and isinstance(p, DPSOParams) and p.metric_second

    def locator(self, features: Features, kept: FramePairs | None = None,
                kept2: FramePairs | None = None) -> LocateFn | None:
        """The frame located at a map image by two-view geometry (service/vision/map_geometry.py),
        None for a map without the camera's intrinsics; ``kept``, ``kept2``: the frame's
        RootSIFT and XFeat matches its similarity kept."""
        geometry = self.map.geometry
        if geometry is None:
            return None
        params = GeometryParams()
        if not self._second_geometry(features):
            return lambda image_id: geometry.locate(features, image_id, params, kept)
        second, frame2 = self.map.second_geometry, features.second
        assert second is not None and frame2 is not None  # _second_geometry

        def locate(image_id: int) -> Offset | None:  # RootSIFT's, else XFeat's geometry
            off = geometry.locate(features, image_id, params, kept)
            return off if off is not None else second.locate(frame2, image_id, params, kept2)
        return locate

    def _verify(self, similarity: ComparisonCache) -> Verify:
        """Which learned images proposed to a searching swarm it is given: those the frame
        matches at ``SEED_SHARE`` of the map's same-light level or more (at a dusk start of a
        rendered world, 0.06-0.12 at the true place, 0.02-0.05 elsewhere, level 0.30)."""
        def verify(ids: np.ndarray) -> np.ndarray:
            if self._level is None:
                self._level = same_light_level(self.map)
            return np.asarray(similarity(ids) >= SEED_SHARE * self._level)
        return verify

    def seed_places(self, codes: np.ndarray, verify: Verify | None = None) -> None:
        """Candidate places of this frame for a searching estimator (service/vision/place_index.py);
        a no-op without a place index. ``verify``: the learned candidates it may be given."""
        if self.seeder is not None:
            last = self.last
            self.seeder.before_step(self.estimator, codes, None if last is None
                                    else np.array([last.x, last.y]), verify)

    def _estimate(self, res: StepResult, t: float | None, comparisons: int,
                  learned: bool) -> Estimate:
        x, y = (float(v) for v in res.position)
        lat = lon = None
        frame = self.map.frame
        if frame is not None:
            lat, lon = (float(v) for v in frame.to_geo(res.position)[0])
        ids, _ = self.map.nearest(res.position[None, :])
        nid = int(ids[0])
        cov = res.covariance
        pose_cov = np.diag([0.0, 0.0, _UNKNOWN_VAR, _UNKNOWN_VAR, _UNKNOWN_VAR, _UNKNOWN_VAR])
        pose_cov[:2, :2] = cov
        if res.heading_sigma is not None:
            pose_cov[5, 5] = res.heading_sigma ** 2
        return Estimate(
            seq=self.seq, stamp=t, frame_id=self.map.name,
            estimator=cast(EstimatorName, self.estimator_name),
            x=x, y=y, lat=lat, lon=lon, heading=float(res.heading),
            heading_source=cast(HeadingSource, res.heading_source), speed=float(res.speed_mps),
            status=res.status.value, lost=bool(res.lost), score=float(res.score),
            comparisons=comparisons, covariance=cov.tolist(),
            pose_covariance=pose_cov.ravel().tolist(), accuracy_m=res.accuracy_m,
            nearest_image=nid, nearest_image_name=self.map.image_names[nid],
            spread_m=res.spread_m,
            hypotheses=[Hypothesis(x=h.x, y=h.y, weight=h.weight)
                        for h in res.hypotheses],
            experience=self.choice.experience() if learned else None,
        )

