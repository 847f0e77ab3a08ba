"""Multi-swarm DPSO: the papers' future work (journal Sec. 8), built for changing light.

The swarm moves as in the papers (Eqs. 4-6, self-adaptive v0, recovery boost), with these
changes, each measured in docs/research/lighting.md:

- **A start speed in map spacings.** v0 starts at least ``v0_spacings`` map image spacings
  per frame (over the longer axis range): the papers' v0 is a fraction of the map's extent,
  which on a short map with images far apart is slower than a robot moving an image per
  frame (routes of ~100 m with images ~0.6 m apart keep the papers' v0).

- **Coasting.** A frame whose best match falls below ``coast_ratio`` of the level seen while
  tracking is weak: its estimate does not feed the tracked velocity, and the next frame's
  swarm is carried by the velocity tracked before (at most ``coast_max_frames`` frames), as a
  particle filter's motion model carries its particles through frames that say little.
- **Evidence along paths.** Each particle accumulates its fitness with a decay
  (A <- lambda A + f, in the spirit of sequence matching); redrawn particles start from zero.
  A sub-swarm's support is the most evidence one of its particles carries, so one spurious
  match cannot move the estimate to another sub-swarm unless the evidence persists.
- **Sub-swarms (speciation).** Particles are grouped each frame around seeds taken in order of
  this frame's fitness (species PSO, Li 2004; Parrott & Li 2006 for moving optima): a particle
  within ``species_radius_m`` of a seed belongs to its species and is attracted to it. Each
  species is a hypothesis, supported by the most evidence one of its particles carries. The
  estimate follows the best-supported species; the others are reported as ``hypotheses``. A
  species whose support falls below ``dissolve_ratio`` of the best is dissolved and its
  particles join the best one, unless it is young and better: the mean of the fitness along
  its particles' paths (the evidence without the bias of its age) is at least
  ``dissolve_mean_ratio`` of the best one's. A scout that finds the true place survives
  until its evidence takes the estimate; a young species that is not better does not.
- **Attractors ahead** (``predict_attractor``, off by default). Each sub-swarm is attracted
  to where its seed will be at the next frame (the seed plus the tracked step), and the
  quantum particles are redrawn there: a motion prior for a robot that moves about an image
  spacing per frame.
- **Scouts.** A few particles with the least evidence are redrawn at random map images every
  frame (more while recovering, and on a map with the camera while tracking is not yet
  confirmed by a located frame, ``scout_unconfirmed``). They are the background the lost
  detection measures against, and the way the swarm discovers a place it is not searching.
- **The start follows places along the wheels** (``sequence_frames``). While the swarm
  searches for the first time and the frames carry odometry, places on the map's path are
  moved by the wheels and scored frame after frame (service/estimators/place_sequence.py);
  one that stands out over a sequence draws the swarm there, where single frames at dusk
  match look-alike places as well as the true one.
- **Local scouts.** While tracking, every ``local_scout_every``-th frame, a few more are
  redrawn at map images 4-15 m from the estimate: the local search a particle filter's motion
  noise gives. A swarm that stalled (the robot set off after a stop while weak matches kept
  the estimate still) finds the robot again through them. On a map with the camera a frame
  the geometry located at the held place draws none (``local_scout_unlocated``): the swarm
  is where the robot is, and their comparisons (a quarter of a tracked frame's) would buy
  nothing.
- **The estimate** is the place the images say: the centre of the map images compared near
  the best species, weighted by m ** ``estimate_image_power``; its covariance is that
  species' spread, scaled to a calibrated 68 % radius. While tracking, the reported position
  is that estimate smoothed along the map's path (service/estimators/along_track.py: the correction
  across the path in full, ``along_track_alpha`` of it along the path); the swarm itself
  works on the raw estimate.
- **The located camera** (``metric_pose``; maps with the camera's intrinsics): while
  tracking, the frame is located against the best-matching compared image near the estimate
  by two-view geometry (service/vision/map_geometry.py); where that succeeds, the estimate is the
  located position, beside and along the path, up to ``metric_reach_m`` from the image (a
  place held a few metres off is corrected), with a radius from the map's position error
  and the located positions' measured jitter (service/estimators/located_noise.py). A frame located
  more than ``metric_steer_m`` from the swarm's estimate steers the swarm: the best
  sub-swarm is attracted to the located position, and its quantum particles and local
  scouts are drawn around it. A frame the geometry does not locate moves the reported
  position less along the path (``along_track_alpha_unlocated``, ``along_track_alpha_weak``
  for a weak one). ``verify_frames``
  (off by default) also lets frames that cannot be located within ``metric_gate_m`` for
  that many tracked frames in a row count as not good for the lost detection;
  ``verify_switch_frames`` (off by default) then moves the estimate to another sub-swarm
  where the frame is located. A tracked frame located more than ``metric_disagree_m`` from
  the images' estimate carries two answers that disagree: it is reported ``recovering``
  with an ``accuracy_m`` of at least that distance (report only: the swarm follows the
  located camera as on any located frame). A located frame's heading is the camera's yaw (the map
  image camera's heading plus the frame's yaw relative to it, ``heading_source`` "camera",
  its std from service/vision/map_geometry.py); a frame not located keeps the odometry's
  heading or the direction of motion.
- **Lost detection** is relative (service/estimators/lost_detection.py): recovery starts when no
  match stands out for ``lost_frames`` frames, not when matches are merely weak. On a map of
  two feature types the first type's own m may vouch for a frame the fused m leaves in doubt
  (``vouch_distinct``): a vouched frame counts as good only while the swarm tracks with no
  bad frame in a row (it holds tracking, it never restores it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from service.api.params import DPSOParams
from service.estimators.along_track import AlongTrackSmoother, along_path, path_tangent
from service.estimators.base import (
    Hypothesis,
    Status,
    StepResult,
    disc_sample,
    sigma_for_accuracy,
    weighted_covariance,
)
from service.estimators.fitness import FrameFitness, MapIndex
from service.estimators.jump_hold import JumpHold
from service.estimators.located_noise import LocatedNoise
from service.estimators.lost_detection import DistinctnessMonitor, Evidence, vouch
from service.estimators.odometry import LocatedGate, OdomStep
from service.estimators.paper_dpso import DPSO
from service.estimators.place_sequence import PlaceSequence

if TYPE_CHECKING:
    from service.vision.metric_pose import Offset


def speciate(x: np.ndarray, evidence: np.ndarray, radius: float, max_species: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """(seed index per species, species label per particle; -1 = no species).

    Seeds are taken in decreasing evidence; a particle joins the first seed within ``radius``.
    """
    order = np.argsort(-evidence, kind="stable")
    label = np.full(len(x), -1, np.int64)
    seeds: list[int] = []
    r2 = radius * radius
    for i in order:
        if len(seeds) >= max_species:
            break
        if label[i] >= 0:
            continue
        d2 = np.einsum("ij,ij->i", x - x[i], x - x[i])
        free = (label < 0) & (d2 <= r2)
        label[free] = len(seeds)
        seeds.append(int(i))
    return np.asarray(seeds, np.int64), label


class MultiSwarmDPSO(DPSO):
    """DPSO with a motion prior, path evidence, sub-swarms, scouts and relative lost detection."""

    name = "dpso"

    def __init__(self, index: MapIndex, params: DPSOParams, rng: np.random.Generator) -> None:
        super().__init__(index, params, rng)
        self.evidence = np.zeros(params.n_particles)
        self.age = np.zeros(params.n_particles)  # frames of evidence each particle carries
        self.frame_count = 0  # frames stepped (local scouts run every local_scout_every-th)
        self.monitor = DistinctnessMonitor(params.distinct_ratio, params.distinct_floor_m,
                                           params.distinct_far_m, params.ema_alpha)
        # the first feature type's own m on a map of two types, with its own background
        self.first_monitor = DistinctnessMonitor(params.distinct_ratio, params.distinct_floor_m,
                                                 params.distinct_far_m, params.ema_alpha)
        self.smoother = AlongTrackSmoother()  # the reported position (tracked frames)
        self.unverified = 0  # tracked frames in a row the geometry could not locate
        # a tracked frame was located at the held place since the swarm converged (False
        # from the first frame on, _initialize; True here for a session stored before it)
        self.confirmed = True
        self.noise = LocatedNoise()  # the located positions' noise: their radius
        self.gate = LocatedGate()  # located frames against the odometry's prediction
        self.jump = JumpHold()  # a far jump of the reported place, until confirmed
        # places followed along the wheels while the swarm searches (``sequence_frames``);
        # None otherwise, so that a tracking session's stored state stays small
        self.sequence: PlaceSequence | None = None
        self._reset_coasting()

    def start_v0(self) -> float:
        """v0 at the start: at least ``v0_spacings`` map image spacings per frame over the
        longer axis range (a short map with images far apart: a robot moving an image per
        frame outruns the papers' fraction of its extent), at most ``v0_max``."""
        p = self.params
        floor = p.v0_spacings * self._spacing / float(np.max(self.delta))
        return float(min(max(p.v0, floor), max(p.v0, p.v0_max)))

    def _initialize(self) -> None:
        super()._initialize()
        self.evidence = np.zeros(self.params.n_particles)
        self.age = np.zeros(self.params.n_particles)
        self.monitor.reset()
        self.first_monitor.reset()
        self.smoother.reset()
        self.unverified = 0
        self.confirmed = False
        self.noise.reset()
        self.gate.reset()
        self.jump.reset()
        self.sequence = None
        self._reset_coasting()

    def _reset_coasting(self) -> None:
        self.level: float | None = None  # EMA of the best match in good, non-weak frames
        self.weak_frames = 0  # weak frames in a row (their estimates do not feed ema_step)

    def _step(self, fitness: FrameFitness, t: float | None, odom: OdomStep | None
              ) -> StepResult:
        starting = not self._converged  # the session's first search (or a reset's)
        if self._needs_init:
            self._initialize()
        p = self.params
        dt = self.frame_dt(t)
        odom_d = None
        if odom is not None:  # every sub-swarm moves with the robot (the odometry step)
            odom_d = self.odometry_prediction(odom)
        elif p.motion_prior and self.ema_step is not None and self._converged \
                and not self.recovering:
            self.x = np.clip(self.x + self.ema_step, self.lower, self.upper)  # motion prior
        elif self._coasting():  # carried through weak frames by the kept velocity
            assert self.ema_step is not None
            self.x = np.clip(self.x + self.ema_step, self.lower, self.upper)
        self.frame_count += 1
        f, _, _ = fitness(self.x)
        self.evidence = p.evidence_decay * self.evidence + f
        self.age = self.age + 1
        # sub-swarms around the best particles of this frame (their attractors, as p^n in the
        # papers); a sub-swarm's support is the most evidence any of its particles carries
        seeds, label = speciate(self.x, f, p.species_radius_m, p.max_species)
        species_xy = self.x[seeds]  # the places the sub-swarms hold in this frame (a copy)
        support = np.array([self.evidence[label == s].max() for s in range(len(seeds))])
        best_s = int(np.argmax(support))
        if 0 < p.verify_switch_frames <= self.unverified and len(seeds) > 1:
            alt = self._verified_alternative(fitness, seeds, support, best_s)
            if alt is not None:  # the geometry locates the frame there, not at the held place
                self.evidence[label == alt] += support[best_s]
                support[alt] += support[best_s]
                best_s = alt
        # the estimate: the particles of the best group near its best particle (the front of
        # a moving swarm: a centre over the whole group trails the robot)
        seed_x = self.x[seeds[best_s]]
        members = (label == best_s) & (np.linalg.norm(self.x - seed_x, axis=1)
                                       <= p.estimate_radius_m)
        w = f[members] if f[members].sum() > 0 else self.evidence[members]
        pos = weighted_centre(self.x[members], w)
        cov = weighted_covariance(self.x[members], w, p.estimate_floor_m) * p.covariance_scale
        spread = float(np.mean(np.linalg.norm(self.x - pos, axis=1)))
        hypotheses = self._hypotheses(seeds, label, support, f, best_s)

        ids, scores = fitness.compared
        compared_xy = np.asarray(self.index.positions)[ids]
        pos = image_centre(compared_xy, scores, pos, p.estimate_image_radius_m,
                           p.estimate_image_power)
        ev = self.monitor.judge(compared_xy, scores, pos, p.species_radius_m)
        if fitness.first is not None:  # a map of two types: the first may vouch
            own = self.first_monitor.judge(compared_xy, fitness.first(ids), pos,
                                           p.species_radius_m)
            ev = vouch(ev, own, p.vouch_distinct)
        cov = cov + np.eye(2) * (match_sigma(ev.best_m, p) ** 2 + p.lateral_sigma_m ** 2)
        # the geometry's verdict on the last frames: the place the swarm holds is refuted
        # when the frame could not be located at it for verify_frames tracked frames in a row
        refuted = 0 < p.verify_frames <= self.unverified
        good = self._counts_good(ev) and not refuted
        step_before = odom_d if odom_d is not None else self.ema_step  # the predicted motion
        # jumps are judged from the first convergence on: the global search before it has no
        # place to leave
        hold_m = p.jump_hold_m if self._converged else 0.0
        status, lost = self._update_evidence_status(good)
        # a weak frame's estimate lags where images look alike: it does not teach the velocity;
        # nor does a jump to another place (the search's, before the first convergence too)
        self.track_motion(pos, learn=not self._judge_weak(ev.best_m, ev.good),
                          predicted=step_before, jump_m=p.along_track_gate_m)
        if self.recovery_phase(lost):
            status = Status.RECOVERING
        camera = self._located(fitness, status, pos, ids, scores, compared_xy)
        # this frame was located at the held place (_located has just counted it)
        held = status is Status.TRACKING and self._geometry_runs(fitness) \
            and self.unverified == 0
        if odom is not None and odom_d is not None:  # the located position against the
            # odometry's prediction
            if not self.gate.admit(None if camera is None else camera[0],
                                   self.smoother.predicted(odom_d), odom.distance,
                                   p.odom_locate_gate_m):
                camera = None  # contradicted, not yet confirmed by a second located frame
                held = False  # the local scouts search on
            elif self.gate.moved:  # two located frames agree, against the odometry: the
                self.smoother.reset()  # reported position restarts at the located one,
                if self.odometry is not None:  # and the heading fit's pairs may belong to
                    self.odometry.forget()  # the place the robot is not at
        located = camera[0] if camera is not None else None
        # how far the located camera lies from the images' estimate (inf: not located)
        apart = float(np.linalg.norm(located - pos)) if located is not None else math.inf
        unconfirmed = self._unconfirmed(fitness, status, apart)
        # a tracked frame located far from the images' estimate carries two answers that
        # disagree: reported recovering, its radius at least the distance (report only)
        disagree = apart if located is not None else 0.0
        if not (status is Status.TRACKING and 0 < p.metric_disagree_m < disagree):
            disagree = 0.0

        # attractors: the seeds where the robot will be at the next frame (the tracked step
        # ahead), so the swarm does not trail the robot where matches are weak
        lead = self.ema_step if p.predict_attractor and self.ema_step is not None else 0.0
        attractor = self.x[seeds][np.where(label >= 0, label, best_s)] + lead
        # a sub-swarm is dissolved when it carries less than dissolve_ratio of the best one's
        # evidence and is not better per frame: a young one (a scout that found the place has
        # one frame of evidence against the incumbent's five) survives while the mean of the
        # fitness along its particles' paths is at least dissolve_mean_ratio of the best's
        weak_s = support < p.dissolve_ratio * support[best_s]
        if p.dissolve_mean_ratio > 0 and weak_s.any():
            mean_ev = self.mean_evidence()
            judge = np.array([mean_ev[label == s].max() for s in range(len(seeds))])
            weak_s &= judge < p.dissolve_mean_ratio * judge[best_s]
        dissolve = (label >= 0) & weak_s[label.clip(0)]
        p_n, around = self.x[seeds[best_s]] + lead, pos + lead
        if located is not None and p.metric_steer_m > 0 and \
                float(np.linalg.norm(located - pos)) > p.metric_steer_m:
            # the located camera steers the swarm: the best sub-swarm is attracted to it and
            # its quantum particles and local scouts are drawn around it
            p_n = around = located + lead
            attractor = np.where((label == best_s)[:, None], p_n, attractor)
        self._move_species(attractor, p_n, dissolve, around,
                           local_scouts=not (p.local_scout_unlocated and held),
                           searching=p.scout_unconfirmed and unconfirmed)
        speed, heading = self.motion(dt)
        if located is not None:
            pos = located
            self.noise.add(self.frame_count, pos)
            # with odometry the reported position filters the located ones (_reported)
            share = p.odom_jitter_share if odom_d is not None and status is Status.TRACKING \
                else 1.0
            sigma = self.noise.sigma(p.metric_map_sigma_m, p.metric_jitter_gain,
                                     p.metric_jitter_prior_m, share)
            cov = np.eye(2) * max(sigma, sigma_for_accuracy(disagree)) ** 2
        geometry = self._geometry_runs(fitness)
        # the images confirm the place: a located frame, or a strong one without geometry
        confirmed = located is not None if geometry else self.weak_frames == 0
        reported = self._reported(pos, status, ids, compared_xy,
                                  self._along_alpha(geometry, located is not None), odom_d,
                                  confirmed, ev.good)
        # a far jump of the reported place is not tracking until confirmed (report only)
        jumped = self.jump.judge(reported, step_before, hold_m, good, located is not None,
                                 p.jump_confirm_frames)
        if jumped:
            cov = cov + np.eye(2) * sigma_for_accuracy(jumped) ** 2
        self.odom_observe(odom, pos, status is Status.TRACKING and confirmed,
                          lost or self.recovering)
        cam = camera[1] if camera is not None else None
        if cam is not None and cam.heading is not None and cam.heading_sigma is not None \
                and odom is not None and self.odometry is not None and self.params.odom_look:
            self.odometry.look(cam.heading, cam.heading_sigma, self.params.odom_drift)
        heading, source, h_sigma = self.odom_heading(odom, heading)
        if cam is not None and cam.heading is not None:  # the camera's yaw
            heading, source, h_sigma = cam.heading, "camera", cam.heading_sigma
        # last, so that its comparisons judge nothing of this frame: the sequence's place
        # draws the swarm for the next frame
        self._follow_sequence(fitness, odom, starting, species_xy)
        return StepResult(reported, cov, heading, speed,
                          Status.RECOVERING if disagree or unconfirmed
                          or (jumped and status is Status.TRACKING) else status,
                          lost or self.recovering,
                          ev.best_m, fitness.comparisons, spread, hypotheses, source, h_sigma,
                          located is not None, unconfirmed)

    def odometry_prediction(self, odom: OdomStep) -> np.ndarray:
        """Move every particle by the odometry step in the map frame, with its noise
        (service/estimators/odometry.py); the step (m) for the reported position's
        prediction."""
        d, sigma = self.odom_move(odom)
        noise = self.rng.normal(0.0, sigma, self.x.shape) if sigma > 0 else 0.0
        self.x = np.clip(self.x + d + noise, self.lower, self.upper)
        return d

    def _geometry_runs(self, fitness: FrameFitness) -> bool:
        """Whether frames are located by two-view geometry: ``metric_pose`` is on and the
        map keeps the camera (the fitness can locate)."""
        return self.params.metric_pose and fitness.locate is not None

    def _along_alpha(self, geometry: bool, located: bool) -> float:
        """The share of the along-path correction the reported position takes this frame:
        ``along_track_alpha``; where the map's geometry runs but did not locate the frame,
        ``along_track_alpha_unlocated`` (the image estimate scatters along the path more than
        a located camera), and ``along_track_alpha_weak`` when the frame is also weak (its
        best match below ``coast_ratio`` of the tracking level: the images say little, the
        smoother's prediction carries the position)."""
        p = self.params
        if not geometry or located:
            return p.along_track_alpha
        return p.along_track_alpha_weak if self.weak_frames > 0 else p.along_track_alpha_unlocated

    def _located(self, fitness: FrameFitness, status: Status, pos: np.ndarray,
                 ids: np.ndarray, scores: np.ndarray, compared_xy: np.ndarray
                 ) -> tuple[np.ndarray, Offset] | None:
        """While tracking, the camera's position from two-view geometry against the
        best-matching compared image within ``estimate_image_radius_m`` of ``pos``: that
        image's position plus the located offset, right and ahead along the path there
        (service/vision/metric_pose.py); where it cannot be located there within
        ``metric_reach_m``, against the next best compared images within
        ``metric_search_m``, ``metric_tries`` images in all, with the offset that placed it
        (its heading); None where none locates it."""
        p = self.params
        if not self._geometry_runs(fitness) or status is not Status.TRACKING:
            self.unverified = 0  # counted while tracking only
            return None
        locate = fitness.locate
        assert locate is not None  # _geometry_runs
        anchor = best_image_near(ids, scores, compared_xy, pos, p.estimate_image_radius_m)
        if anchor is None:
            self.unverified += 1
            return None
        # the best image near the estimate first (its verdict confirms the place), then the
        # next best compared within metric_search_m: where the light left the first
        # unlocatable, another often is (a lab count: 23-77 % of such frames)
        d = compared_xy - pos
        near = np.einsum("ij,ij->i", d, d) <= p.metric_search_m ** 2
        others = ids[near][np.argsort(-scores[near], kind="stable")]
        tries = [anchor, *[int(i) for i in others if i != anchor]][:p.metric_tries]
        for k, image in enumerate(tries):
            tangent = path_tangent(self._map_positions, image, self._spacing)
            off = locate(image) if tangent is not None else None
            reach = math.hypot(off.right_m, off.ahead_m) if off is not None else math.inf
            if k == 0:  # the held place is confirmed where the camera stands near its image
                self.unverified = 0 if reach <= p.metric_gate_m else self.unverified + 1
            if off is not None and tangent is not None and reach <= p.metric_reach_m:
                return along_path(self._map_positions[image], tangent, off.right_m,
                                  off.ahead_m), off
        return None

    def _unconfirmed(self, fitness: FrameFitness, status: Status, apart: float) -> bool:
        """Whether this tracked frame's place is not yet confirmed by the geometry
        (``confirm_tracking``): since the swarm last converged or came back, no tracked frame
        was located at the held place, at its best image (``_located`` has just judged this
        one: ``unverified``) or within ``metric_gate_m`` of the images' estimate (``apart``:
        the located camera's distance from it, inf where not located). Always False where
        the geometry does not run."""
        if status is not Status.TRACKING:
            self.confirmed = False
            return False
        if not (self.params.confirm_tracking and self._geometry_runs(fitness)):
            return False
        self.confirmed = self.confirmed or self.unverified == 0 or \
            apart <= self.params.metric_gate_m
        return not self.confirmed

    def _verified_alternative(self, fitness: FrameFitness, seeds: np.ndarray,
                              support: np.ndarray, best_s: int) -> int | None:
        """The best-supported other sub-swarm (of the next two) at whose best-matching
        compared image the frame is located, or None."""
        p = self.params
        if fitness.locate is None:
            return None
        ids, scores = fitness.compared
        xy = np.asarray(self.index.positions)[ids]
        for s in [s for s in np.argsort(-support) if s != best_s][:2]:
            anchor = best_image_near(ids, scores, xy, self.x[seeds[s]],
                                     p.estimate_image_radius_m)
            off = fitness.locate(anchor) if anchor is not None else None
            if off is not None and math.hypot(off.right_m, off.ahead_m) <= p.metric_gate_m:
                return int(s)
        return None

    def _reported(self, pos: np.ndarray, status: Status, ids: np.ndarray,
                  compared_xy: np.ndarray, alpha: float, odom_d: np.ndarray | None = None,
                  confirmed: bool = True, good: bool = True) -> np.ndarray:
        """The position reported for the estimate ``pos``: smoothed along the map's path
        while tracking (service/estimators/along_track.py; ``alpha`` of the along-path correction),
        ``pos`` itself otherwise. The path's
        direction is taken at the compared image nearest ``pos`` (the estimate is their
        centre, so no map-wide query is needed). With odometry (``odom_d``), the odometry
        predicts and a frame the images confirm corrects a share (``odom_alpha``); while
        the place is lost, the odometry carries the position alone (``odom_carry_frames``)
        unless the search finds a ``good`` place beyond ``along_track_gate_m``."""
        p = self.params
        carried = None if odom_d is None else self.smoother.predicted(odom_d)
        far = carried is not None and \
            float(np.linalg.norm(pos - carried)) > p.along_track_gate_m
        if status is not Status.TRACKING and odom_d is not None and carried is not None \
                and not (far and good) and self.smoother.carried < p.odom_carry_frames:
            # the place is lost where no match stands out: the odometry carries the
            # position the images last confirmed (for at most odom_carry_frames frames);
            # a place the search finds far from it (a match that stands out there, as after
            # a kidnap) is reported at once
            return self.smoother.carry(odom_d)
        if status is not Status.TRACKING or p.along_track_alpha >= 1 or not len(ids):
            if far:
                self._odom_restart()
            self.smoother.reset()
            return pos
        nearest = int(ids[np.argmin(np.einsum("ij,ij->i", compared_xy - pos,
                                              compared_xy - pos))])
        tangent = path_tangent(self._map_positions, nearest, self._spacing)
        if odom_d is not None:  # the odometry predicts, the images correct a share of it
            if far and (confirmed or self.smoother.carried):
                # the images (or the search after a carried stretch) place the robot far
                # from the odometry's track: the estimate restarts there, and so does the
                # odometry's map heading
                self._odom_restart()
                self.smoother.reset()
            gain = p.odom_alpha if confirmed else p.odom_alpha_weak
            return self.smoother.update(pos, tangent, gain, p.along_track_gate_m,
                                        self.ema_step, motion=odom_d, across=gain,
                                        hold=not confirmed)
        return self.smoother.update(pos, tangent, alpha, p.along_track_gate_m, self.ema_step)

    def _follow_sequence(self, fitness: FrameFitness, odom: OdomStep | None,
                         starting: bool, held: np.ndarray) -> None:
        """While the swarm searches for the first time (``starting``: not yet converged
        since the session began or was reset) with odometry, the places followed along the
        wheels take this frame (service/estimators/place_sequence.py; ``held``: the
        sub-swarms' places); where one stands out and less than half of the swarm is within
        ``species_radius_m`` of it, the other particles are redrawn there, with no evidence
        and no velocity. Any other frame, or one without odometry, drops the places. (A
        swarm that lost a place it held is left to its own search: there a look-alike that
        stood out over 8 frames drew a swarm that was right 77 m away, lab replays of seed
        23 at dusk.)"""
        p = self.params
        if p.sequence_frames <= 0 or odom is None or not starting:
            self.sequence = None
            return
        if self.sequence is None:
            self.sequence = PlaceSequence()
        # born at the frame's place candidates and at the places the sub-swarms hold (the
        # incumbent competes: a swarm already at the robot's place is not drawn away)
        births = held if self.place_candidates is None else \
            np.concatenate([self.place_candidates, held])
        # a robot backing up moves the places against their direction
        self.sequence.step(math.copysign(odom.distance, odom.forward), births,
                           self._map_positions, self._spacing,
                           lambda x: self.index.nearest(x)[0], lambda x: fitness(x)[0])
        at = self.sequence.place(p.sequence_frames, p.sequence_ratio, p.sequence_travel_m)
        if at is None:
            return
        out = np.linalg.norm(self.x - at, axis=1) > p.species_radius_m
        if 2 * int(out.sum()) <= len(self.x):
            return
        self.x[out] = disc_sample(self.rng, at, p.species_radius_m, int(out.sum()))
        self.v[out] = 0.0
        self.evidence[out] = 0.0
        self.age[out] = 0.0

    def _odom_restart(self) -> None:
        """After a jump beyond along_track_gate_m: the odometry's map heading restarts."""
        if self.odometry is not None and self.params.odom_restart_heading:
            self.odometry.restart()

    def mean_evidence(self) -> np.ndarray:
        """Each particle's evidence as a decayed mean of the fitness along its path (A with
        the bias of its age removed: A (1 - lambda) / (1 - lambda ** age))."""
        lam = self.params.evidence_decay
        age = np.maximum(self.age, 1)
        return self.evidence * (1 - lam) / (1 - lam ** age)

    def _coasting(self) -> bool:
        """Whether this frame's swarm is carried by the kept velocity: the previous frame was
        weak, the robot was being tracked, and the weak stretch is not too long."""
        return (self.weak_frames > 0 and self.ema_step is not None and self._converged
                and not self.recovering and self.weak_frames <= self.params.coast_max_frames)

    def _judge_weak(self, best_m: float, good: bool) -> bool:
        """A frame is weak when its best match falls below ``coast_ratio`` of the level seen
        while tracking; strong, good frames update that level (EMA)."""
        p = self.params
        if self.weak_frames >= p.coast_max_frames:
            # weak for longer than coasting may last: a lasting change of the match level
            # (less texture, other light) is the new normal, not a stretch to carry through
            self.level = None
        weak = self.level is not None and best_m < p.coast_ratio * self.level
        if not weak and good:
            a = p.level_alpha
            self.level = best_m if self.level is None else (1 - a) * self.level + a * best_m
        self.weak_frames = self.weak_frames + 1 if weak else 0
        return weak

    def _counts_good(self, ev: Evidence) -> bool:
        """Whether a frame counts as good for the status: a vouched one only while the swarm
        tracks with no bad frame in a row (it holds tracking, never restores it)."""
        if ev.vouched:
            return self._converged and self._bad == 0
        return ev.good

    def _update_evidence_status(self, good: bool) -> tuple[Status, bool]:
        p = self.params
        if good:
            self._good += 1
            self._bad = 0
        else:
            self._bad += 1
            self._good = 0
        if self._good >= p.converge_frames:
            self._converged = True
        if self._bad >= p.lost_frames:
            return Status.LOST, True
        return (Status.TRACKING if self._converged else Status.INITIALIZING), False

    def _hypotheses(self, seeds: np.ndarray, label: np.ndarray, support: np.ndarray,
                    f: np.ndarray, best_s: int) -> tuple[Hypothesis, ...]:
        p = self.params
        keep = [s for s in np.argsort(-support) if support[s] >= p.hypothesis_ratio
                * support[best_s] and support[s] > 0][: p.max_species]
        total = float(sum(support[s] for s in keep)) or 1.0
        out = []
        for s in keep:
            mem = label == s
            w = f[mem] if f[mem].sum() > 0 else self.evidence[mem]
            c = weighted_centre(self.x[mem], w)
            out.append(Hypothesis(float(c[0]), float(c[1]), float(support[s] / total)))
        return tuple(out)

    def _move_species(self, attractor: np.ndarray, p_n: np.ndarray, weak: np.ndarray,
                      around: np.ndarray, local_scouts: bool = True,
                      searching: bool = False) -> None:
        """Eqs. 4-5 towards each particle's species seed; Eq. 6 quantum particles around the
        best seed; scouts (weak species and the least evidence) redrawn at map images, as
        many as while recovering where ``searching``, and (``local_scouts``, every
        ``local_scout_every``-th frame while tracking) around ``around``."""
        p, rng, n = self.params, self.rng, self.params.n_particles
        r0 = rng.uniform(-1.0, 1.0, (n, 2))
        r2 = rng.uniform(0.0, 1.0, (n, 2))
        v = p.omega * self.v + p.phi0 * r0 * self.delta * self.v0 \
            + self.phi2 * r2 * (attractor - self.x)
        norm = np.linalg.norm(v / self.delta, axis=1)
        limit = self.v0 * np.where(self.high_energy, p.high_energy_factor, 1.0)
        v *= np.minimum(1.0, limit / np.maximum(norm, 1e-12))[:, None]
        x = self.x + v
        # Eq. 6 around the best seed: local while tracking, the papers' q_d while recovering
        k = min(round(self.q_r * n), n - int(self.high_energy.sum()))
        sigma = self.delta * p.quantum_sigma if self.recovering else \
            np.full(2, p.quantum_track_sigma_m)
        x[:k] = p_n + sigma * rng.normal(0.0, 1.0, (k, 2))
        v[:k] = 0.0
        fresh = np.zeros(n, bool)
        fresh[:k] = True
        # particles of dissolved sub-swarms join the best one (redrawn like quantum particles)
        joiners = weak & ~fresh
        nj = int(joiners.sum())
        if nj:
            x[joiners] = p_n + sigma * rng.normal(0.0, 1.0, (nj, 2))
            v[joiners] = 0.0
        fresh |= joiners
        # scouts: the particles with the least evidence, redrawn at random map images; and
        # while tracking, every local_scout_every-th frame, local scouts around the estimate
        n_scouts = round((p.scout_ratio_recovery if self.recovering or searching
                          else p.scout_ratio) * n)
        self._redraw_least_evidence(x, v, fresh, n_scouts, self.sample_map_positions)
        if not self.recovering and self.frame_count % p.local_scout_every == 0 \
                and local_scouts:
            self._redraw_least_evidence(
                x, v, fresh, round(p.local_scout_ratio * n),
                lambda k: self.sample_map_positions_near(
                    around, p.local_scout_inner_m, p.local_scout_radius_m, k))
        below, above = x < self.lower, x > self.upper
        x = np.where(below, 2 * self.lower - x, np.where(above, 2 * self.upper - x, x))
        x = np.clip(x, self.lower, self.upper)
        v = np.where(below | above, -v, v)
        self.x, self.v = x, v
        self.evidence = np.where(fresh, 0.0, self.evidence)
        self.age = np.where(fresh, 0.0, self.age)

    def _redraw_least_evidence(self, x: np.ndarray, v: np.ndarray, fresh: np.ndarray, k: int,
                               draw: Callable[[int], np.ndarray]) -> None:
        """Redraw the ``k`` not yet fresh particles with the least evidence at ``draw(k)``."""
        candidates = np.flatnonzero(~fresh)
        chosen = candidates[np.argsort(self.evidence[candidates], kind="stable")[:k]]
        if len(chosen):
            x[chosen] = draw(len(chosen))
            v[chosen] = 0.0
            fresh[chosen] = True


def match_sigma(best_m: float, p: DPSOParams) -> float:
    """Std (m) of the image estimate from the strength of its best match: fewer matched
    features place the robot less sharply between neighbouring images (``match_sigma_m`` at
    m = 1, times m ** -``match_sigma_power``; m floored at ``distinct_floor_m``)."""
    return float(p.match_sigma_m * max(best_m, p.distinct_floor_m, 1e-6)
                 ** -p.match_sigma_power)


def best_image_near(ids: np.ndarray, m: np.ndarray, xy: np.ndarray, around: np.ndarray,
                    radius: float) -> int | None:
    """The compared map image with the best similarity within ``radius`` of ``around``;
    None where no compared image lies there."""
    d = xy - around
    near = np.einsum("ij,ij->i", d, d) <= radius ** 2
    return int(ids[near][np.argmax(m[near])]) if near.any() else None


def image_centre(xy: np.ndarray, m: np.ndarray, around: np.ndarray, radius: float,
                 power: float) -> np.ndarray:
    """Centre of the compared map images within ``radius`` of ``around``, weighted by
    m ** power; ``around`` itself where no image there matched."""
    near = np.linalg.norm(xy - around, axis=1) <= radius
    w = m[near] ** power
    total = float(w.sum())
    return (w @ xy[near]) / total if total > 0 else np.asarray(around, float)


def weighted_centre(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    total = float(w.sum())
    return (w @ x) / total if total > 0 else x.mean(axis=0)
