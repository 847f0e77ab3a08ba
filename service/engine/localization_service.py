"""The localization engine behind both transports: maps, robot sessions, frame processing.

Nothing here knows HTTP or Zenoh. A frame is decoded and its features extracted outside any
lock (OpenCV and NumPy release the GIL, so robots run in parallel); only the estimator step
holds the session's lock. Every check that can reject a frame runs before that step, so a
rejected frame never changes the session.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from service.api.errors import (
    Conflict,
    InvalidParameters,
    NotFound,
    ServiceError,
    Unavailable,
    UnreadableSession,
)
from service.api.models import (
    Estimate,
    ExperienceInfo,
    LearningInfo,
    MapDetail,
    MapSummary,
    Odometry,
    PosePrior,
    SessionConfig,
    SessionInfo,
    check_robot_id,
    check_timestamp,
)
from service.api.params import ParamError
from service.engine.events import EventHub
from service.engine.experience_writer import Batch, ExperienceWriter, RedisHandover
from service.engine.geometry_warmer import GeometryWarmer
from service.engine.learning import (
    LEARN_IDLE_S,
    OUTCOMES,
    PROGRESS_WAIT_S,
    Learner,
    LearnGates,
    path_gate,
)
from service.engine.localizer import Localizer
from service.engine.map_admin import MapAdmin
from service.engine.map_mirror import MapMirror
from service.engine.metrics import Metrics
from service.engine.sqlite_store import SqliteStore, sqlite_location
from service.engine.state_codec import StateError, continued_on
from service.engine.store import (
    InProcessStore,
    RedisOptions,
    RedisStore,
    Session,
    SessionLimit,
    SessionStore,
)
from service.estimators.base import EstimatorStateError
from service.maps.experiences import compatible, with_usage
from service.maps.route_map import RouteMap, list_maps, load_map
from service.settings import Settings
from service.vision.imaging import decode_frame

__all__ = ["LocalizationService", "Session"]
log = logging.getLogger("swarmloc")


class LocalizationService:
    def __init__(self, settings: Settings, maps: dict[str, RouteMap] | None = None,
                 metrics: Metrics | None = None) -> None:
        self.settings = settings
        self.metrics = metrics or Metrics()
        self.events = EventHub(self.metrics)  # the estimate stream of GET /events
        self.maps: dict[str, RouteMap] = maps if maps is not None else {}
        self.load_errors: dict[str, str] = {}
        self._lock = threading.Lock()
        self.draining = False  # shutting down: new frames get 503
        self._in_flight = 0
        self._idle = threading.Condition(threading.Lock())
        # the maps' geometry structures, built ahead of the robots (settings.warm_geometry)
        self.warmer = GeometryWarmer(current=lambda m: self.maps.get(m.name) is m)
        self.admin = MapAdmin(self)  # upload / replace / delete / build without a restart
        if maps is None:
            self.load_maps(settings.maps_dir)
        self.store = open_store(settings, self.resolve_map)
        # learning sessions hand their batches to a background writer (one writer per map
        # fleet-wide with Redis): a frame never writes a map
        handover = RedisHandover(self.store.r, self.store.opt.key_prefix) \
            if isinstance(self.store, RedisStore) else None
        if settings.maps_sync == "redis" and isinstance(self.store, RedisStore):
            # replicas with a maps directory each: map files travel through Redis
            self.admin.attach_mirror(MapMirror(self.store.r, self.store.opt.key_prefix))
        self.writer = ExperienceWriter(self._write_batch, handover, lambda: list(self.maps),
                                       waiting=self.metrics.learned_waiting.set)
        self.learner = Learner(LearnGates(settings.learn_accuracy_m, settings.learn_weak_ratio,
                                          settings.learn_commit_images), self.writer.submit,
                               counted=lambda o: self.metrics.learning_frames.labels(o).inc())
        snap = settings.session_snapshot
        if isinstance(self.store, InProcessStore) and snap is not None and snap.exists():
            try:
                n, problems = self.store.load_snapshot(snap, self.resolve_map)
            except StateError as exc:  # kept aside for a look, never half-read
                aside = snap.with_name(snap.name + ".corrupt")
                snap.replace(aside)
                log.error("session snapshot not restored (%s); moved to %s", exc, aside)
            else:
                log.info("restored %d sessions from %s", n, snap)
                for p in problems:
                    log.warning("session not restored: %s", p)
        self._update_gauge()

    def close(self) -> None:
        """At shutdown: the learning robots' collected images are written (within
        ``shutdown_deadline_s``; what does not make it is logged), the in-process store
        writes its snapshot (if configured), the SQLite store checkpoints and releases its
        file."""
        self.warmer.close()
        self.learner.flush_all()
        self.writer.close(self.settings.shutdown_deadline_s)
        self.store.close()

    def _write_batch(self, batch: Batch) -> None:
        """The background writer's write: one learned batch into its map."""
        self.admin.commit_experience(batch.map, batch.exp_id, batch.images, batch.condition,
                                     batch.robot, batch.base)

    def _update_gauge(self) -> None:
        if not self.store.shared:  # Redis: each replica would count the fleet's sessions
            self.metrics.sessions.set(len(self.store))

    # ---- maps ---------------------------------------------------------------------------
    def load_maps(self, directory: Path) -> None:
        """Load every map file; a broken one is logged with its file name and skipped, the
        others still load. Two files with the same map name: the first (by file name) wins
        and the second is refused, naming both."""
        for path in list_maps(directory):
            try:
                # images checked on first use; the words matcher trains its vocabulary now
                m = load_map(path, verify="lazy", matcher=self.settings.matcher)
                if m.name in self.maps:
                    first = self.maps[m.name].path
                    raise ValueError(f"map name '{m.name}' is already loaded from "
                                     f"{first.name if first else '?'}; rename one of them")
            except Exception as exc:  # a broken map is reported, the others still load
                msg = str(exc) if str(path) in str(exc) else f"{path}: {exc}"
                self.load_errors[path.name] = msg
                self.metrics.map_loads.labels("startup", "failed").inc()
                log.error("map file %s skipped: %s", path, msg)
                continue
            self.maps[m.name] = m
            self.adopt(m)
            self.metrics.map_loads.labels("startup", "ok").inc()
        self.metrics.maps.set(len(self.maps))

    def adopt(self, m: RouteMap) -> None:
        """Apply the service's settings to a map it has just started to serve (every map
        loaded at start-up, uploaded, built, reloaded or given an experience passes here)."""
        m.image_cache.limit_bytes = self.settings.image_cache_mb * 2**20
        if self.settings.warm_geometry:
            self.warmer.submit(m)

    def check_pose(self, route_map: RouteMap, x: float, y: float, what: str) -> None:
        """A pose must lie within the map's extent plus ``pose_margin_m``."""
        lo, hi = route_map.bounds
        m = self.settings.pose_margin_m
        if not (lo[0] - m <= x <= hi[0] + m and lo[1] - m <= y <= hi[1] + m):
            raise InvalidParameters(
                f"{what} ({x:g}, {y:g}) is outside map '{route_map.name}': x must be in "
                f"[{lo[0] - m:g}, {hi[0] + m:g}] and y in [{lo[1] - m:g}, {hi[1] + m:g}] m "
                f"(its extent plus SWARMLOC_POSE_MARGIN_M={m:g})")

    def is_heavy(self, robot_id: str) -> bool:
        """A session over ``heavy_particles`` runs in its own smaller worker pool, so it
        cannot starve the light robots (fair scheduling)."""
        try:
            s = self.store.peek(robot_id)
        except ServiceError:  # the store is down: the frame's own error will say so
            return False
        n = getattr(s.localizer.estimator.params, "n_particles", 0) if s else 0
        return n > self.settings.heavy_particles

    # ---- shutdown -----------------------------------------------------------------------
    def begin_shutdown(self) -> None:
        """From now on new frames get 503; frames in flight finish."""
        self.draining = True

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until no frame is in flight, at most ``timeout_s``; True when idle."""
        deadline = time.monotonic() + timeout_s
        with self._idle:
            while self._in_flight:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._idle.wait(left)
        return True

    @property
    def ready(self) -> bool:
        return bool(self.maps)

    @property
    def default_map(self) -> str:
        name = self.settings.default_map
        if name:
            return name
        if len(self.maps) == 1:
            return next(iter(self.maps))
        if "demo" in self.maps:
            return "demo"
        raise InvalidParameters(f"no default map: name one of {sorted(self.maps)}")

    def get_map(self, name: str) -> RouteMap:
        """Map ``name``; one another service on the maps directory wrote is loaded first."""
        m = self.maps.get(name) or self.admin.discover(name)
        if m is None:
            raise NotFound(f"unknown map '{name}'; loaded maps: {sorted(self.maps)}")
        return m

    def map_summaries(self) -> list[MapSummary]:
        """The maps served, by name, after following the maps directory (maps another
        service on it added or deleted; one deleted while listed is left out)."""
        out = []
        for name in self.admin.sync():
            try:
                out.append(self.map_summary(name))
            except NotFound:
                pass
        return out

    def map_summary(self, name: str) -> MapSummary:
        return self._summary(self.admin.refresh(name))

    def _summary(self, m: RouteMap) -> MapSummary:
        s = m.summary()
        experiences = [ExperienceInfo(**e) for e in with_usage(m, self.learner.usage(m.name))]
        s.pop("experiences", None)
        s.pop("compatible_versions", None)
        return MapSummary(name=s.pop("name"), n_images=s.pop("n_images"),
                          n_features=s.pop("n_features"), bounds=s.pop("bounds"),
                          spacing_m=s.pop("spacing_m"), meta=s, checksum=m.meta.get("checksum"),
                          build_date=s.get("build_date"), experiences=experiences)

    def resolve_map(self, name: str, checksum: str | None, strict: bool = True) -> RouteMap:
        """The loaded map a stored session runs on; with ``strict`` the same version."""
        m = self.maps.get(name) or self.admin.discover(name)
        if m is None:
            raise NotFound(f"the session's map '{name}' is not served here (deleted, or its "
                           f"file is not in this service's maps directory); loaded maps: "
                           f"{sorted(self.maps)}; create the session again on one of them")
        # a version that differs only by experiences continues; one this replica has not
        # loaded yet (another replica wrote it) is loaded first
        if strict and not compatible(m, checksum):
            m = self.admin.refresh(name)
        have = m.meta.get("checksum")
        if strict and not compatible(m, checksum):
            raise Conflict(f"the session's map '{name}' (version {str(checksum)[:12]}) was "
                           f"replaced by version {str(have)[:12]}; reset the session to "
                           "continue on the new version")
        return m

    def map_detail(self, name: str) -> MapDetail:
        m = self.admin.refresh(name)  # one version for the summary and the positions
        return MapDetail(**self._summary(m).model_dump(),
                         positions=m.positions.tolist(), image_names=m.image_names)

    # ---- sessions -----------------------------------------------------------------------
    def put_session(self, robot_id: str, config: SessionConfig, replace: bool = True
                    ) -> tuple[SessionInfo, bool]:
        """Create or (with ``replace``) replace a robot's session; True when it was created.

        Without ``replace`` an existing session is kept: two transports creating the same
        robot's session at once end with one session, not one silently replacing the other.
        """
        check_robot_id(robot_id)
        map_name = config.map or self.default_map
        route_map = self.admin.refresh(map_name)  # the newest version on disk
        if config.learn:  # not on a maps directory that cannot take what it teaches
            self.admin.check_learnable(route_map)
        estimator = config.estimator or self.settings.default_estimator
        n = config.params.get("n_particles") if isinstance(config.params, dict) else None
        if isinstance(n, int) and not isinstance(n, bool) and n > self.settings.max_particles:
            self.metrics.rejected.labels("cost_ceiling").inc()
            raise InvalidParameters(f"invalid parameter: n_particles: {n} is over this "
                                    f"service's ceiling of {self.settings.max_particles} "
                                    "(SWARMLOC_MAX_PARTICLES)")
        if config.initial_pose is not None:
            self.check_pose(route_map, config.initial_pose.x, config.initial_pose.y,
                            "initial_pose")
        try:
            loc = Localizer(route_map, estimator, config.params, config.seed)
        except ParamError as exc:
            raise InvalidParameters(str(exc)) from None
        if config.initial_pose is not None:
            p = config.initial_pose
            loc.reset((p.x, p.y), p.radius)
        now = time.time()
        with self._lock:
            if self.maps.get(map_name) is not route_map:
                raise Conflict(f"map '{map_name}' was replaced or deleted meanwhile; retry")
            try:
                s, created = self.store.create(
                    Session(robot_id, loc, now, now, learn=config.learn,
                            condition=config.condition), replace, self.settings.max_sessions)
            except SessionLimit:
                self.metrics.rejected.labels("session_limit").inc()
                raise Unavailable(f"session limit of {self.settings.max_sessions} reached; "
                                  "delete idle sessions or raise SWARMLOC_MAX_SESSIONS"
                                  ) from None
            self._update_gauge()
        if not created and replace:  # viewers drop the old session (maybe on another map)
            self.events.remove(robot_id)
            self.learner.flush(robot_id, end=True)  # what the old session collected
        return self.info(s), created

    def session(self, robot_id: str) -> Session:
        s = self.store.get(robot_id)
        if s is None:
            raise NotFound(f"no session for robot '{robot_id}'; create it with "
                           f"PUT /sessions/{robot_id}")
        return s

    def session_info(self, robot_id: str) -> SessionInfo:
        """One session as ``GET /sessions/{robot_id}`` shows it: a learning one's progress
        waits up to ``PROGRESS_WAIT_S`` for the gates of the frames it sent (blocking)."""
        return self.info(self.session(robot_id), PROGRESS_WAIT_S)

    def info(self, s: Session, wait_s: float = 0.0) -> SessionInfo:
        """The session's info, with a learning session's progress on this replica (the
        frames whose gates have run, waiting up to ``wait_s`` for the others)."""
        info = s.info()
        if not s.learn:
            return info
        progress = self.learner.progress(s.robot_id, wait_s)
        if progress is None:
            return info
        exp_id, st = progress
        stopped = {g: st[g] for g in OUTCOMES if g in st and g not in ("taught", "bridged")}
        return info.model_copy(update={"learning": LearningInfo(
            experience=exp_id, frames=st["seen"], taught=st["taught"], bridged=st["bridged"],
            collected=st["waiting"], stopped=stopped)})

    def ensure_session(self, robot_id: str) -> Session:
        """The robot's session, created with the default map and estimator if missing."""
        s = self.store.get(robot_id)
        if s is None:
            self.put_session(robot_id, SessionConfig(), replace=False)
            s = self.session(robot_id)
        return s

    def sessions_on_map(self, name: str) -> list[str]:
        """Robots whose session runs on map ``name`` (any version of it)."""
        return sorted(rid for rid, m in self.store.maps_of().items() if m == name)

    def sessions(self) -> list[SessionInfo]:
        """The live sessions; one whose stored state cannot be read is left out (its own
        requests say why), so the listing serves everyone else."""
        out = []
        for rid in self.store.ids():
            try:
                s = self.store.get(rid)
            except UnreadableSession as exc:
                log.warning("%s", exc)
                continue
            if s is not None:
                out.append(self.info(s))
        return out

    def delete_session(self, robot_id: str) -> None:
        with self._lock:
            if not self.store.delete(robot_id):
                raise NotFound(f"no session for robot '{robot_id}'")
            self._update_gauge()
        self.events.remove(robot_id)
        self.learner.flush(robot_id, end=True)  # a learning session's last images

    def reset_session(self, robot_id: str, near: PosePrior | None = None) -> SessionInfo:
        with self.store.locked(robot_id, strict_map=False) as s:
            if near is not None:
                self.check_pose(self.maps.get(s.localizer.map.name) or s.localizer.map,
                                near.x, near.y, "reset pose")
            current = self.maps.get(s.localizer.map.name)
            if current is not None and (s.map_changed or current is not s.localizer.map):
                old = s.localizer  # the map was replaced: a reset moves to the new version
                s.localizer = Localizer(current, old.estimator_name, old.params, old.seed)
                s.map_changed = False
            if near is None:
                s.localizer.reset()
            else:
                s.localizer.reset((near.x, near.y), near.radius)
            s.last_t = None
            s.last_input_seq = None
            s.learn_path = []
            s.last_used = time.time()
        self.learner.flush(robot_id, reset=True)  # a reset breaks the path: its images are
        # written, and its frames before do not teach
        return self.info(s)

    def _followed(self, s: Session) -> Localizer:
        """The session's localizer, or where this service now serves a version of its map
        that differs from the session's only by experiences (a fleet's learning, an
        experience deleted), the localizer continued on that version: its state goes on,
        nothing is reset (``continued_on``; the frame's step then moves the session). Until
        its reset, a learning session stays on its version (it must not localize against,
        nor be gated by, what it has just taught), and so does a session whose map was
        rebuilt or replaced."""
        loc = s.localizer
        current = self.maps.get(loc.map.name)
        if s.learn or current is None or current is loc.map or \
                not compatible(current, loc.map.meta.get("checksum")):
            return loc
        try:
            return continued_on(loc, current)
        except StateError as exc:  # cannot happen for a state this version made; stay
            log.error("session of robot %s stays on its map version: %s", s.robot_id, exc)
            return loc

    def follow_maps(self) -> None:
        """Load the newer versions another service wrote of the maps served here (a header
        read each), so that their sessions move on live at their next frame; a map another
        service deleted is no longer served."""
        for name in list(self.maps):
            try:
                self.admin.refresh(name)
            except ServiceError as exc:  # deleted by another service: no longer served
                log.info("map %s not followed: %s", name, exc.message)
            except Exception:  # the sweep goes on; the map keeps serving its version
                log.exception("map %s: its file could not be checked for a new version",
                              name)

    def expire_idle(self, now: float | None = None) -> list[str]:
        now = time.time() if now is None else now
        with self._lock:
            try:
                gone = self.store.expire(self.settings.session_idle_s, now)
            except Unavailable as exc:  # Redis down: its TTLs expire sessions meanwhile
                log.warning("session expiry skipped: %s", exc.message)
                return []
            self._update_gauge()
        self.metrics.expired.inc(len(gone))
        for rid in gone:
            self.events.remove(rid)
            self.learner.flush(rid, end=True)
        # a learning robot whose frames now go to another replica, or that stopped: what this
        # replica collected is written (the session may live on in a shared store)
        self.learner.flush_idle(LEARN_IDLE_S)
        self.follow_maps()
        return gone

    def claim(self, robot_id: str) -> bool:
        """Whether this replica serves the robot's Zenoh traffic (service/engine/store.py)."""
        return self.store.claim(robot_id)

    # ---- frames -------------------------------------------------------------------------
    def process_frame(self, robot_id: str, data: bytes | np.ndarray, *,
                      content_type: str | None = None, t: float | None = None,
                      prior: PosePrior | None = None, transport: str = "http",
                      session: Session | None = None, input_seq: int | None = None,
                      create: bool = False, odom: Odometry | None = None) -> Estimate:
        """Decode, validate, extract and step one frame; raises ServiceError on bad input.

        ``data`` is an encoded PNG/JPEG, or already validated 8-bit grayscale pixels (a ROS 2
        sensor_msgs/Image, checked by service/zenoh/ros2.py). With ``create`` a missing session is
        created with the defaults, but only once the frame has passed every check. ``odom``: the
        robot's odometry pose at the frame (validated; its step from the previous frame's is
        checked before the estimator steps)."""
        if self.draining:
            self.metrics.rejected.labels("shutting_down").inc()
            raise Unavailable("the service is shutting down; send the frame to another "
                              "replica or retry after the restart")
        with self._idle:
            self._in_flight += 1
        try:
            return self._process_frame(robot_id, data, content_type, t, prior, transport,
                                       session, input_seq, create, odom)
        finally:
            with self._idle:
                self._in_flight -= 1
                self._idle.notify_all()

    def _process_frame(self, robot_id: str, data: bytes | np.ndarray, content_type: str | None,
                       t: float | None, prior: PosePrior | None, transport: str,
                       session: Session | None, input_seq: int | None, create: bool,
                       odom: Odometry | None = None) -> Estimate:
        t0 = time.perf_counter()
        s = session if session is not None or create else self.session(robot_id)
        try:
            image = data if isinstance(data, np.ndarray) else decode_frame(
                data, content_type, self.settings.max_body_bytes, self.settings.max_pixels,
                self.settings.min_frame_side)
            if t is not None:
                check_timestamp(t, None)
            if s is None:
                s = self.ensure_session(robot_id)
            if prior is not None:
                self.check_pose(s.localizer.map, prior.x, prior.y, "pose prior")
            loc = s.localizer
            features = loc.extract(image)
            with self.store.locked(robot_id) as s:
                if s.localizer.map is not loc.map and \
                        s.localizer.map.feature_params != loc.map.feature_params:
                    features = s.localizer.extract(image)  # reset onto a rebuilt map meanwhile
                last = s.localizer.last
                if input_seq is not None and input_seq == s.last_input_seq \
                        and t == s.last_t and last is not None:
                    # the last frame sent again (same seq and timestamp: a retry after a lost
                    # answer, possibly to another replica, or the same image in a second
                    # encoding): answered with its estimate, not applied twice
                    return last.model_copy(update={"robot_id": robot_id,
                                                   "input_seq": input_seq})
                if t is not None and s.last_t is not None and t < s.last_t:
                    raise Conflict(f"frame timestamp {t} is older than the last processed "
                                   f"frame ({s.last_t}); send frames in time order")
                if t is not None:
                    check_timestamp(t, s.last_t)
                stepped = self._followed(s)  # on a new version of its map, live
                try:
                    est = stepped.step(features, t,
                                       (prior.x, prior.y, prior.radius) if prior else None,
                                       odom)
                except EstimatorStateError as exc:  # re-initialised: the next frame works
                    raise ServiceError(f"internal error: {exc}", 500) from None
                if stepped is not s.localizer:  # moved only by a frame that was applied
                    s.localizer, s.map_changed = stepped, False
                    self.metrics.sessions_moved.inc()
                if t is not None:
                    s.last_t = t
                if input_seq is not None:
                    s.last_input_seq = input_seq
                s.last_used = time.time()
                particles = self.events.particles_due(robot_id, s.localizer)
                ran_on, learn, created, condition = (s.localizer.map, s.learn, s.created,
                                                     s.condition)
                stopped = None
                if learn:  # gates 1 and 2 on the path kept with the session (any replica)
                    s.learn_path, stopped = path_gate(s.learn_path, est,
                                                      self.settings.learn_accuracy_m)
        except Exception as exc:
            self.metrics.rejected.labels(type(exc).__name__).inc()
            raise
        if est.experience is not None:
            self.learner.used(ran_on.name, est.experience, time.time())
        if learn:  # the gates on the learner's threads; a full collection goes to the writer
            self.learner.submit(robot_id, created, condition, ran_on, features, est, stopped,
                                odom)
        self.metrics.frames.labels(transport).inc()
        self.metrics.comparisons.inc(est.comparisons)
        elapsed = time.perf_counter() - t0
        self.metrics.latency.labels(transport).observe(elapsed)
        est = est.model_copy(update={"robot_id": robot_id, "input_seq": input_seq})
        self.events.publish(est, elapsed, particles)
        return est


def open_store(settings: Settings,
               resolve: Callable[[str, str | None, bool], RouteMap]) -> SessionStore:
    """The store ``SWARMLOC_SESSION_STORE`` names: ``sqlite`` (the default file),
    ``sqlite:///PATH``, ``memory`` or ``redis://host:port/db``."""
    url = settings.session_store
    if url == "memory":
        return InProcessStore(settings.session_snapshot)
    if settings.session_snapshot is not None:
        log.warning("SWARMLOC_SESSION_SNAPSHOT is ignored: only the 'memory' store uses it "
                    "(the %s store keeps every session itself)", url.partition(":")[0])
    if url == "sqlite" or url.startswith("sqlite:"):
        path, synchronous = sqlite_location(url, settings.maps_dir)
        store = SqliteStore(path, resolve, synchronous)
        log.info("sessions kept in %s (SQLite, WAL, synchronous=%s): %d stored", path,
                 synchronous, len(store))
        return store
    if url.startswith(("redis://", "rediss://", "unix://")):
        return RedisStore(url, resolve, RedisOptions(
            idle_s=settings.session_idle_s, lock_lease_s=settings.session_lock_lease_s,
            lock_wait_s=settings.session_lock_wait_s,
            claim_lease_s=settings.zenoh_claim_lease_s, replica_id=settings.replica_id or ""))
    raise ValueError(f"SWARMLOC_SESSION_STORE={url!r}: use 'sqlite' (the default), "
                     "sqlite:///PATH, 'memory' or redis://host:port/db")


