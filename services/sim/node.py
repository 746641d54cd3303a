"""Sim service: a pybullet world paced to wall time that follows setpoints and streams sensors.

Publishes `robot/joint_states` and `sim/contacts/events`; follows `executor/setpoint`; answers
`sim/contacts`, `sim/objects` and `sim/stats`. Cameras render in their own processes
(`sim_render.py`): this process only steps physics, so a slow render never delays a step, a
joint state or a setpoint. Everything that touches the world runs on the physics thread;
queries hand their work to it.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from robonav.pipeline.sim.driver import DriverLimits, DriverState, SetpointFollower
from robonav.pipeline.sim.motion import MotionScript
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.joint_order import reorder_to_robot
from robonav.pipeline.wire.messages import (
    ContactEvent,
    ContactsRequest,
    ContactsResponse,
    ExecutorStatus,
    JointState,
    Setpoint,
    SimObjectsRequest,
    SimStatsRequest,
)
from robonav.services.common import (
    Node,
    check_publication_size,
    declare_latched_publisher,
    decode_request,
    guarded_queryable,
    guarded_subscriber,
    reply_ok,
    run_service,
)
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys
from robonav.services.limits import check_scene_request
from robonav.services.sim.description import camera_descriptions
from robonav.services.sim.objects import SimObjects
from robonav.services.sim.render import LabelRegistry, RenderJob, RenderWorker, snapshot_scene
from robonav.services.sim.stats import LoopStats

log = logging.getLogger("robonav.sim")

CLEARANCE_QUERY_RANGE_M = 0.3
"""Ground-truth clearance is tracked up to this distance; beyond it is reported as absent."""
MAX_CATCH_UP_STEPS = 24
"""After a stall, at most this many physics steps run back to back; older time is dropped."""
COMMAND_TIMEOUT_S = 5.0
"""A query waits this long for the physics thread to run its work."""


class ContactTracker:
    """Counts contact onsets: a touching (link, object) pair counts once until it separates."""

    def __init__(self) -> None:
        self.count = 0
        self.pairs: set[str] = set()
        self.min_distance_m = float("inf")
        self.min_distance_pair = ""
        self._touching: set[str] = set()

    def update(self, touching: set[str]) -> tuple[set[str], set[str]]:
        """Returns the pairs that began and that ended touching."""
        began, ended = touching - self._touching, self._touching - touching
        self.count += len(began)
        self.pairs |= touching
        self._touching = touching
        return began, ended

    def reset(self) -> None:
        """Zero the counters; pairs still touching are not counted again until they separate."""
        self.count = 0
        self.pairs = set(self._touching)
        self.min_distance_m = float("inf")
        self.min_distance_pair = ""


class SimNode(Node):
    def __init__(self, cfg: RobonavConfig, session: zenoh.Session) -> None:
        self.cfg = cfg
        self.world = SimWorld(cfg.robot, cfg.cameras[0], cfg.sim)
        self.names = cfg.robot.joint_names
        self.contacts = ContactTracker()
        script = MotionScript()
        script.arm(cfg.sim.motions, 0.0)
        self.objects = SimObjects(self.world, script)
        self.labels = LabelRegistry()
        self.stats = LoopStats(tuple(c.camera_id for c in cfg.cameras))
        self._lock = threading.Lock()
        lower, upper = self.world.joint_limits
        self.follower = SetpointFollower(
            DriverLimits(lower=lower, upper=upper, velocity=np.array(cfg.robot.max_velocity_rad_s, float),
                         acceleration=np.array(cfg.robot.max_acceleration_rad_s2, float),
                         jerk=np.array(cfg.robot.max_jerk_rad_s3, float)),
            self.world.commanded_target()[0], timeout_s=cfg.sim.setpoint_timeout_s, slack_s=cfg.sim.setpoint_slack_s)
        """The arm's own rules for setpoints, as a real driver's: only what the arm can do, brake when they stop."""
        self._reported_trajectory: str | None = None
        """The motion whose refused setpoints were last logged (or passed over by the rate limit)."""
        self._reported_malformed: set[str] = set()
        self._reported_at_s = -math.inf
        """time.monotonic() of the last refusal logged while the arm was not moving."""
        self._commands: queue.SimpleQueue[tuple[Callable[[], Any], concurrent.futures.Future[Any]]] = queue.SimpleQueue()
        keys = Keys(cfg.cell)
        self._joint_pub = session.declare_publisher(keys.joint_states)
        self._event_pub = session.declare_publisher(keys.contact_events)
        # Discovery: the cell's cameras, latched, so a client needs no config file.
        self._cameras_pub = declare_latched_publisher(session, keys.cameras)
        self._cameras_pub.put(camera_descriptions(cfg).to_wire())
        # Setpoints arrive at 1 kHz and only the newest matters: a ring channel keeps it in Zenoh
        # (no Python callback per sample competing for the GIL); the physics loop decodes one per step.
        self._setpoint_sub = session.declare_subscriber(keys.setpoint, zenoh.handlers.RingChannel(1))
        # The executor's status (progress for scripted objects) likewise waits in Zenoh for the
        # physics loop, which reads it on its own thread: a Python callback would make Zenoh's
        # receive thread, which setpoints share, wait for the GIL the physics step holds. Sixteen
        # statuses cover a stall of the loop far longer than any observed (0.8 s at 20 Hz).
        self._status_sub = session.declare_subscriber(keys.status, zenoh.handlers.RingChannel(16))
        self._on_status = guarded_subscriber(self.on_status, "sim")
        self._queryables = [
            session.declare_queryable(keys.contacts, guarded_queryable(self.handle_contacts, "sim")),
            session.declare_queryable(keys.sim_objects, guarded_queryable(self.handle_objects, "sim")),
            session.declare_queryable(keys.sim_stats, guarded_queryable(self.handle_stats, "sim")),
        ]
        self.workers = [RenderWorker(cfg, i) for i in range(len(cfg.cameras))]

    # --- Zenoh callbacks (any thread; on_status runs on the physics thread) ---------------------

    def on_status(self, sample: zenoh.Sample) -> None:
        """On the physics thread, for each status received since the last step."""
        status = ExecutorStatus.from_wire(sample.payload.to_bytes())
        self.objects.script.on_progress(status.trajectory_id, status.state, status.progress)

    def handle_contacts(self, query: zenoh.Query) -> None:
        request = decode_request(query, ContactsRequest)
        with self._lock:
            distance = self.contacts.min_distance_m
            response = ContactsResponse(contact_count=self.contacts.count, pairs=tuple(sorted(self.contacts.pairs)),
                                        min_distance_m=distance if np.isfinite(distance) else None,
                                        min_distance_pair=self.contacts.min_distance_pair if np.isfinite(distance) else None)
            if request.reset:
                self.contacts.reset()
        reply_ok(query, response)

    def handle_objects(self, query: zenoh.Query) -> None:
        request = decode_request(query, SimObjectsRequest)
        check_scene_request(request.objects, request.names, self.cfg.limits, motions=len(request.motions))
        reply_ok(query, self._on_physics_thread(lambda: self.objects.apply(request)))

    def handle_stats(self, query: zenoh.Query) -> None:
        request = decode_request(query, SimStatsRequest)

        def report() -> Any:
            for worker in self.workers:
                for render_ms in worker.render_ms:
                    self.stats.render(worker.camera.camera_id, render_ms)
                worker.render_ms.clear()
            counters = self.follower.counters
            response = dataclasses.replace(
                self.stats.report(self.world.sim_time_s), driver_state=self.follower.state.value,
                setpoints_followed=counters.followed, setpoints_rejected=dict(counters.rejected),
                setpoint_timeouts=counters.timeouts, brakes=counters.brakes, last_rejection=counters.last_rejection)
            if request.reset:
                self.stats.reset(self.world.sim_time_s)
            return response

        reply_ok(query, self._on_physics_thread(report))

    def _on_physics_thread(self, work: Callable[[], Any]) -> Any:
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._commands.put((work, future))
        try:
            return future.result(timeout=COMMAND_TIMEOUT_S)
        except concurrent.futures.TimeoutError:
            raise ProtocolError(ErrorCode.INTERNAL_ERROR, f"the physics loop did not answer within {COMMAND_TIMEOUT_S} s")

    # --- physics thread ----------------------------------------------------------------------

    def _run_commands(self) -> None:
        while True:
            try:
                work, future = self._commands.get_nowait()
            except queue.Empty:
                return
            try:
                future.set_result(work())
            except Exception as exc:  # reported to the waiting query, never fatal to the loop
                future.set_exception(exc)

    def _apply_setpoint(self) -> None:
        """The newest setpoint, if the driver's rules let the arm follow it; the driver's own
        command (a brake, a hold) otherwise. Runs every physics step."""
        commanded = self.world.commanded_target()
        sample = self._setpoint_sub.try_recv()
        # The driver's clock is the wall's when the sim keeps real time: a stalled physics loop
        # must not make time the commander saw pass look like a jump. It is read once the
        # setpoint is taken: read before, a stall in between (the thread preempted, or waiting
        # for the GIL) hands over a setpoint newer than the clock says, which looks like a jump.
        now_s = time.monotonic() if self.cfg.sim.realtime else self.world.sim_time_s
        if sample is not None:
            try:
                check_publication_size(sample)
                setpoint = Setpoint.from_wire(sample.payload.to_bytes())
                q = reorder_to_robot(setpoint.position, setpoint.names, self.names, "position")
                qd = reorder_to_robot(setpoint.velocity, setpoint.names, self.names, "velocity")
                qdd = reorder_to_robot(setpoint.acceleration, setpoint.names, self.names, "acceleration")
            except ValueError as exc:  # ProtocolError is one: garbage, wrong joint names
                braking = self.follower.state is DriverState.FOLLOWING
                self.follower.reject_malformed(str(exc), now_s, commanded)
                self._report("bad_message", str(exc), braking, None)
            else:
                braking = self.follower.state is DriverState.FOLLOWING
                rejection = self.follower.offer(q, qd, qdd, setpoint.stamp, now_s, commanded)
                if rejection is None:
                    self.world.set_joint_target(q, qd)
                else:
                    self._report(rejection.reason, rejection.message, braking, setpoint.trajectory_id)
        if self.follower.tick(now_s, commanded):
            log.warning("no setpoint for %.0f ms mid-motion: braking to rest (setpoint watchdog)",
                        self.cfg.sim.setpoint_timeout_s * 1e3)
        command = self.follower.command(now_s)
        if command is not None:
            self.world.set_joint_target(*command)

    def _report(self, reason: str, message: str, braking: bool, trajectory_id: str | None) -> None:
        """Log a rejected setpoint: every one that brakes a moving arm, else the first of each
        trajectory (the first undecodable one of all), at most one a second: a line per refused
        motion, and no flood from a commander that names every setpoint anew."""
        what = f"a setpoint of '{trajectory_id}'" if trajectory_id is not None else "a setpoint"
        seen = reason in self._reported_malformed if trajectory_id is None else trajectory_id == self._reported_trajectory
        now_s = time.monotonic()
        if braking:
            log.warning("rejected %s (%s: %s): braking to rest", what, reason, message)
        elif not seen and now_s - self._reported_at_s >= 1.0:
            log.warning("rejected %s (%s: %s); further ones while the arm is %s are counted in sim/stats",
                        what, reason, message, self.follower.state.value)
            self._reported_at_s = now_s
        if trajectory_id is None:
            self._reported_malformed.add(reason)
        else:
            self._reported_trajectory = trajectory_id

    def _step(self) -> None:
        self._apply_setpoint()
        self.objects.step_motions()
        self.world.step()
        deepest = {f"{c.link}|{c.object}": c.distance_m for c in self.world.robot_obstacle_contacts()}
        with self._lock:
            began, ended = self.contacts.update(set(deepest))
            count = self.contacts.count
        if began:
            log.warning("robot-obstacle contact: %s", ", ".join(sorted(began)))
        now = time.time()
        for pair, event in [*((p, "begin") for p in sorted(began)), *((p, "end") for p in sorted(ended))]:
            link, obj = pair.split("|", 1)
            self._event_pub.put(ContactEvent(stamp=now, link=link, object=obj, event=event,
                                             distance_m=deepest.get(pair, 0.0), contact_count=count).to_wire())

    def _publish_joint_state(self, stamp: float) -> np.ndarray:
        q, qd = self.world.joint_state()
        self._joint_pub.put(JointState(stamp=stamp, names=self.names, position=q, velocity=qd).to_wire())
        self.stats.joint_state(time.monotonic())
        closest = self.world.closest_robot_obstacle(CLEARANCE_QUERY_RANGE_M)
        if closest is not None:
            with self._lock:
                if closest.distance_m < self.contacts.min_distance_m:
                    self.contacts.min_distance_m = closest.distance_m
                    self.contacts.min_distance_pair = f"{closest.link}|{closest.object}"
        return q

    def _submit_render(self, worker: RenderWorker) -> None:
        # The frame's stamp is this moment; the joint state published with it is the pose rendered.
        stamp = time.time()
        q = self._publish_joint_state(stamp)
        objects = self.world.objects
        scene = None
        if worker.structure_sent != self.objects.structure_revision:
            scene = snapshot_scene(objects, self.labels)
            worker.structure_sent = self.objects.structure_revision
        worker.seq += 1
        worker.submit(RenderJob(stamp=stamp, seq=worker.seq, q=q, scene=scene,
                                poses={obj.name: (obj.position_m, obj.quat_xyzw) for obj in objects}))
        self.stats.frame(worker.camera.camera_id, stamp)

    def spin(self, stop: threading.Event) -> None:
        dt = self.world.dt_s
        joint_period = 1.0 / self.cfg.sim.joint_state_rate_hz
        next_joint = 0.0
        next_camera = [0.0] * len(self.workers)
        wall_start = time.monotonic()
        steps = 0
        self.stats.reset(0.0)
        while not stop.is_set():
            now = time.monotonic()
            due_steps = int((now - wall_start) / dt) if self.cfg.sim.realtime else steps + 1
            if due_steps - steps > MAX_CATCH_UP_STEPS:  # drop time we cannot catch up with
                skipped = due_steps - steps - MAX_CATCH_UP_STEPS
                wall_start += skipped * dt
                due_steps -= skipped
                self.stats.dropped(skipped * dt)
            while steps < due_steps:
                self.stats.step(time.monotonic() - (wall_start + (steps + 1) * dt))
                self._step()
                steps += 1
            self._run_commands()
            while (status := self._status_sub.try_recv()) is not None:
                self._on_status(status)
            sim_t = self.world.sim_time_s
            if sim_t >= next_joint:
                self._publish_joint_state(time.time())
                # Keep the phase (steps need not divide the period), but never owe a burst.
                next_joint = max(next_joint + joint_period, sim_t)
            for i, worker in enumerate(self.workers):
                worker.poll()
                if sim_t >= next_camera[i] and worker.idle:
                    self._submit_render(worker)
                    next_camera[i] = max(next_camera[i] + 1.0 / worker.camera.rate_hz, sim_t)
            if self.cfg.sim.realtime:
                delay = wall_start + (steps + 1) * dt - time.monotonic()
                if delay > 0:
                    time.sleep(delay)

    def close(self) -> None:
        for worker in self.workers:  # all at once: each may take a while to finish its frame
            worker.request_stop()
        for worker in self.workers:
            worker.close()
        for entity in (*self._queryables, self._status_sub, self._setpoint_sub, self._joint_pub, self._event_pub,
                       self._cameras_pub):
            entity.undeclare()
        self.world.close()


def main(argv: list[str] | None = None) -> int:
    return run_service("sim", argv, SimNode)
