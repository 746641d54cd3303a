"""A headless pybullet world: the arm, obstacles (static bodies, moved by teleporting) and depth cameras.

Each `SimWorld` owns its own DIRECT physics client and passes `physicsClientId` to every
call, so several worlds coexist in one process. The arm's root link stands at
`robot.world_from_base` in the world frame (the identity by default).
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import numpy as np
import numpy.typing as npt

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.link_geometry import urdf_with_resolved_meshes
from robonav.pipeline.robot.model import resolve_urdf_path
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.bullet import pybullet as p
from robonav.pipeline.sim.bullet import quiet_native_output
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.rendering import DepthFrame, opengl_projection_matrix, render_depth

__all__ = ["Contact", "DepthFrame", "SimWorld", "opengl_projection_matrix"]

_GRAVITY_M_S2 = 9.81
# pybullet's POSITION_CONTROL motor asks the solver for the joint velocity
# kp * position_error / dt + kd * (target_velocity - velocity) + velocity (roughly), capped by
# the force. kp = 1 would be dead-beat but rings on the light wrist links; these values settle a
# 0.3 rad step to 1e-3 rad in ~15 steps at 240 Hz without overshoot (see tests).
_POSITION_GAIN = 0.5
_VELOCITY_GAIN = 1.0
# The Panda URDF efforts (87 / 12 Nm) saturate when the motor chases a step target, which turns
# tracking into a slow ramp; the sim arm stands in for a stiff, well-tuned joint controller.
_MOTOR_FORCE_SCALE = 10.0
_MIN_MOTOR_FORCE = 50.0
_OBSTACLE_RGBA = ((0.85, 0.33, 0.10, 1.0), (0.00, 0.45, 0.74, 1.0), (0.47, 0.67, 0.19, 1.0),
                  (0.93, 0.69, 0.13, 1.0), (0.49, 0.18, 0.56, 1.0), (0.30, 0.75, 0.93, 1.0))


@dataclass(frozen=True)
class Contact:
    """The deepest contact (or the closest approach) between one robot link and one obstacle."""

    link: str
    object: str
    distance_m: float
    """Signed distance [m]; negative is penetration (<= 0 for contacts)."""


class SimWorld:
    """The simulated arm among obstacles, stepped explicitly by its owner; obstacles change at run time.

    The world never sleeps: pacing steps to wall time is the caller's job. How joints follow
    `set_joint_target` depends on `SimConfig.follow` (see `SimConfig`). Self-collision is off.

    Args:
        robot: Robot description; its URDF is loaded with a fixed base at `robot.world_from_base`.
        camera: Depth camera `render_depth` renders unless given another.
        sim: Physics rate, following mode and obstacles.

    Raises:
        ValueError: the URDF cannot be loaded, or a configured joint or link is missing.
    """

    def __init__(self, robot: RobotConfig, camera: CameraConfig, sim: SimConfig) -> None:
        self._robot_config = robot
        self._camera = camera
        self._sim = sim
        self._dt_s = 1.0 / sim.physics_rate_hz
        self._steps = 0
        self._client: int = p.connect(p.DIRECT)
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def _build(self) -> None:
        cid = self._client
        p.setTimeStep(self._dt_s, physicsClientId=cid)
        p.setGravity(0.0, 0.0, -_GRAVITY_M_S2 if self._sim.gravity else 0.0, physicsClientId=cid)
        self._load_robot()
        self._obstacles: dict[int, str] = {}
        """Body unique id -> object name."""
        self._objects: dict[str, SceneObject] = {}
        """Object name -> the object at its current pose."""
        self._bodies: dict[str, int] = {}
        self._colours_used = 0
        for obj in self._sim.objects:
            self.add_object(obj)
        p.performCollisionDetection(physicsClientId=cid)

    def _load_robot(self) -> None:
        cid, config = self._client, self._robot_config
        urdf_path = resolve_urdf_path(config.urdf, config.package_paths)
        # pybullet knows no ROS packages: it loads a copy whose mesh paths are resolved as the
        # collision model resolves them (package paths, ROS_PACKAGE_PATH, the URDF's folder).
        with tempfile.TemporaryDirectory(prefix="robonav-urdf-") as folder:
            resolved = Path(folder) / urdf_path.name
            resolved.write_text(urdf_with_resolved_meshes(urdf_path, config.package_paths), encoding="utf-8")
            try:
                # No URDF_USE_SELF_COLLISION flag: the arm never collides with itself here; self-collision
                # is the planner's business and would only add solver noise at the wrist.
                position, quat = config.world_from_base.position_m, np.asarray(config.world_from_base.quat_xyzw)
                with quiet_native_output():
                    self._robot = p.loadURDF(str(resolved), basePosition=list(position),
                                             baseOrientation=(quat / np.linalg.norm(quat)).tolist(), useFixedBase=True,
                                             physicsClientId=cid)
            except p.error as exc:
                raise ValueError(f"robot.urdf '{config.urdf}' could not be loaded from {urdf_path}") from exc

        base_name = p.getBodyInfo(self._robot, physicsClientId=cid)[0].decode()
        if config.base_link != base_name:
            raise ValueError(f"robot.base_link '{config.base_link}' is not the root link '{base_name}' of "
                             f"{config.urdf}; the sim places the root link at robot.world_from_base")
        self._link_names: dict[int, str] = {-1: base_name}
        all_joints: list[str] = []
        movable: dict[str, tuple[int, float, float, float]] = {}  # name -> (index, lower, upper, effort)
        for j in range(p.getNumJoints(self._robot, physicsClientId=cid)):
            info = p.getJointInfo(self._robot, j, physicsClientId=cid)
            all_joints.append(info[1].decode())
            self._link_names[j] = info[12].decode()
            if info[2] != p.JOINT_FIXED:
                # pybullet reports a continuous joint as revolute with lower 0 > upper -1: unbounded.
                lower, upper = (info[8], info[9]) if info[8] <= info[9] else (-math.inf, math.inf)
                movable[all_joints[-1]] = (j, lower, upper, info[10])
        for name in (*config.joint_names, *config.fixed_joint_positions):
            if name not in all_joints:
                raise ValueError(f"joint '{name}' from the robot config is not in {config.urdf} "
                                 f"(joints: {', '.join(all_joints)})")
            if name not in movable:
                raise ValueError(f"joint '{name}' from the robot config is a fixed joint in {config.urdf}")
            if name in config.joint_names and name in config.fixed_joint_positions:
                raise ValueError(f"joint '{name}' is both a planning joint and in robot.fixed_joint_positions")

        def motor_force(name: str) -> float:
            return max(_MOTOR_FORCE_SCALE * movable[name][3], _MIN_MOTOR_FORCE)

        self._joint_ids = [movable[name][0] for name in config.joint_names]
        self._joint_limits = (np.array([movable[name][1] for name in config.joint_names], dtype=np.float64),
                              np.array([movable[name][2] for name in config.joint_names], dtype=np.float64))
        self._joint_forces = [motor_force(name) for name in config.joint_names]
        self._target_q = np.asarray(config.home_position_rad, dtype=np.float64)
        self._target_qd = np.zeros(len(self._joint_ids))
        self._target_step = 0
        for j, q in zip(self._joint_ids, self._target_q):
            p.resetJointState(self._robot, j, float(q), 0.0, physicsClientId=cid)
        # Movable joints outside the planning group (the Panda fingers) are held still, at the
        # configured position or else at zero clamped into their limits.
        held = [name for name in movable if name not in config.joint_names]
        held_q = [float(config.fixed_joint_positions.get(name, np.clip(0.0, movable[name][1], movable[name][2])))
                  for name in held]
        for name, q in zip(held, held_q):
            p.resetJointState(self._robot, movable[name][0], q, 0.0, physicsClientId=cid)
        if held:
            p.setJointMotorControlArray(self._robot, [movable[name][0] for name in held], p.POSITION_CONTROL,
                                        targetPositions=held_q, forces=[motor_force(name) for name in held],
                                        physicsClientId=cid)

    @property
    def sim_time_s(self) -> float:
        """Simulated time since construction: steps taken x physics time step [s]."""
        return self._steps * self._dt_s

    @property
    def dt_s(self) -> float:
        """Duration of one `step()` [s]."""
        return self._dt_s

    @property
    def joint_limits(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(lower (n,), upper (n,)) position limits of the planning joints, as the URDF gives them
        (-inf, inf for a continuous joint)."""
        return self._joint_limits[0].copy(), self._joint_limits[1].copy()

    def set_joint_target(self, q_rad: npt.ArrayLike, qd_rad_s: npt.ArrayLike | None = None) -> None:
        """Set the setpoint the arm follows from the next `step()` on.

        `(q, qd)` is the desired state now. "kinematic" worlds jump to exactly `q`, `qd` on each
        step. "dynamic" worlds chase `q + qd * (time since this call)` with target velocity `qd`
        until the next call (setpoints come slower than physics steps; a first-order hold keeps
        the arm from being pulled back to a stale position), for at most
        `sim.setpoint_timeout_s`, after which they hold the extrapolated position (the sim
        service's driver brakes smoothly before that, `pipeline/sim/driver.py`).

        Args:
            q_rad: (n,) joint positions in `robot.joint_names` order [rad or m].
            qd_rad_s: (n,) joint velocities [rad/s or m/s]; None means zero.

        Raises:
            ValueError: a vector has the wrong shape or is not finite.
        """
        n = len(self._joint_ids)
        q = _finite_vector(q_rad, n, "joint target q_rad")
        qd = np.zeros(n) if qd_rad_s is None else _finite_vector(qd_rad_s, n, "joint target qd_rad_s")
        self._target_q, self._target_qd = q, qd
        self._target_step = self._steps

    def set_joint_positions(self, q_rad: npt.ArrayLike) -> None:
        """Teleport the arm to `q_rad` at rest, without stepping (for worlds that only mirror a pose).

        Args:
            q_rad: (n,) joint positions in `robot.joint_names` order [rad or m].

        Raises:
            ValueError: the vector has the wrong shape or is not finite.
        """
        q = _finite_vector(q_rad, len(self._joint_ids), "joint positions q_rad")
        p.resetJointStatesMultiDof(self._robot, self._joint_ids, [[v] for v in q],
                                   targetVelocities=[[0.0]] * len(q), physicsClientId=self._live_client())
        self._target_q, self._target_qd = q, np.zeros_like(q)
        self._target_step = self._steps

    @property
    def objects(self) -> tuple[SceneObject, ...]:
        """Every obstacle at its current (true) pose, in the order added."""
        return tuple(self._objects.values())

    def add_object(self, obj: SceneObject) -> None:
        """Add a static obstacle; an obstacle of the same name is replaced.

        Raises:
            ValueError: the name is 'robot' (reserved for the arm's label).
        """
        if obj.name == "robot":
            raise ValueError("an obstacle must not be named 'robot' (reserved label)")
        cid = self._live_client()
        if obj.name in self._objects:
            self.remove_object(obj.name)
        body = _create_obstacle(obj, _OBSTACLE_RGBA[self._colours_used % len(_OBSTACLE_RGBA)], cid)
        self._colours_used += 1
        self._obstacles[body] = obj.name
        self._bodies[obj.name] = body
        self._objects[obj.name] = obj

    def remove_object(self, name: str) -> None:
        """Remove the obstacle `name`.

        Raises:
            ValueError: no obstacle has that name.
        """
        body = self._body(name)
        p.removeBody(body, physicsClientId=self._live_client())
        del self._obstacles[body], self._bodies[name], self._objects[name]

    def set_objects(self, objects: Sequence[SceneObject]) -> None:
        """Replace every obstacle with `objects` (a new scene).

        Raises:
            ValueError: two objects share a name, or one is named 'robot'.
        """
        names = [obj.name for obj in objects]
        if len(set(names)) != len(names) or "robot" in names:
            raise ValueError(f"scene object names must be unique and not 'robot', got {names}")
        for name in list(self._objects):
            self.remove_object(name)
        for obj in objects:
            self.add_object(obj)

    def set_object_pose(self, name: str, position_m: npt.ArrayLike, quat_xyzw: npt.ArrayLike | None = None) -> None:
        """Teleport obstacle `name` (it stays static: moving obstacles are kinematic).

        Args:
            name: The obstacle.
            position_m: (3,) new origin in the world frame [m].
            quat_xyzw: (4,) new orientation, any non-zero norm; None keeps the current one.

        Raises:
            ValueError: unknown name, or a non-finite or zero-norm pose.
        """
        body = self._body(name)
        position = _finite_vector(position_m, 3, f"position_m of '{name}'")
        quat = np.asarray(self._objects[name].quat_xyzw, dtype=np.float64) if quat_xyzw is None \
            else _finite_vector(quat_xyzw, 4, f"quat_xyzw of '{name}'")
        norm = float(np.linalg.norm(quat))
        if norm < 1e-9:
            raise ValueError(f"quat_xyzw of '{name}' has zero norm")
        quat = quat / norm
        p.resetBasePositionAndOrientation(body, position.tolist(), quat.tolist(), physicsClientId=self._live_client())
        self._objects[name] = dataclasses.replace(self._objects[name], position_m=tuple(position.tolist()),
                                                  quat_xyzw=tuple(quat.tolist()))

    def _body(self, name: str) -> int:
        if name not in self._bodies:
            raise ValueError(f"no obstacle named {name!r} (obstacles: {sorted(self._bodies)})")
        return self._bodies[name]

    def step(self) -> None:
        """Advance the world by one physics time step of 1/physics_rate_hz."""
        cid = self._live_client()
        if self._sim.follow == "kinematic":
            p.resetJointStatesMultiDof(self._robot, self._joint_ids, [[q] for q in self._target_q],
                                       targetVelocities=[[qd] for qd in self._target_qd], physicsClientId=cid)
            p.performCollisionDetection(physicsClientId=cid)
        else:
            self._apply_motor_targets()
            p.stepSimulation(physicsClientId=cid)
        self._steps += 1

    def joint_state(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Current joint positions (n,) [rad or m] and velocities (n,) in `robot.joint_names` order."""
        states = p.getJointStates(self._robot, self._joint_ids, physicsClientId=self._live_client())
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def render_depth(self, camera: CameraConfig | None = None) -> DepthFrame:
        """Render a camera (the world's own by default) with pybullet's CPU (tiny) renderer.

        Returns:
            The depth image (linear metres along the optical axis), per-pixel body ids, the
            intrinsics and the camera pose it was rendered with.
        """
        return render_depth(self._live_client(), self._camera if camera is None else camera)

    def pixels_of(self, name: str, cameras: Sequence[CameraConfig]) -> list[int]:
        """How many pixels of obstacle `name` each camera shows, past the arm and the other obstacles."""
        body = self._body(name)
        return [int(np.count_nonzero(self.render_depth(camera).segmentation == body)) for camera in cameras]

    def body_labels(self) -> dict[int, str]:
        """Body unique id -> obstacle name, or 'robot' for the arm."""
        return {self._robot: "robot", **self._obstacles}

    def robot_obstacle_contacts(self) -> list[Contact]:
        """Touching or penetrating robot-obstacle pairs as of the last `step()` (or construction).

        Returns:
            One `Contact` per (robot link, obstacle) pair, with its most negative distance,
            sorted by object then link name.
        """
        cid = self._live_client()
        candidates: set[tuple[int, int]] = set()
        for body in self._obstacles:
            for point in p.getContactPoints(bodyA=self._robot, bodyB=body, physicsClientId=cid):
                if float(point[8]) <= 0.0:
                    candidates.add((body, point[3]))
        # Contact manifolds persist across teleports (kinematic following, moved obstacles) and
        # can hold stale points for a step; a fresh closest-point query confirms each pair.
        deepest: dict[tuple[str, str], float] = {}
        for body, link in candidates:
            fresh = p.getClosestPoints(self._robot, body, 0.0, linkIndexA=link, physicsClientId=cid)
            distances = [float(point[8]) for point in fresh if float(point[8]) <= 0.0]
            if distances:
                deepest[(self._obstacles[body], self._link_names[link])] = min(distances)
        return [Contact(link=link, object=obj, distance_m=d) for (obj, link), d in sorted(deepest.items())]

    def min_robot_obstacle_distance_m(self, max_distance_m: float = 0.5) -> float:
        """Smallest signed distance between any robot link and any obstacle [m].

        Args:
            max_distance_m: Query range [m]; pairs farther apart are not considered.

        Returns:
            The distance (negative when penetrating), or +inf if nothing is within range.

        Raises:
            ValueError: `max_distance_m` is negative or not finite.
        """
        closest = self.closest_robot_obstacle(max_distance_m)
        return math.inf if closest is None else closest.distance_m

    def closest_robot_obstacle(self, max_distance_m: float = 0.5) -> Contact | None:
        """The closest (robot link, obstacle) pair and its signed distance, if within `max_distance_m`.

        Raises:
            ValueError: `max_distance_m` is negative or not finite.
        """
        if not (math.isfinite(max_distance_m) and max_distance_m >= 0.0):
            raise ValueError(f"max_distance_m must be finite and >= 0, got {max_distance_m}")
        cid = self._live_client()
        best: Contact | None = None
        for body, name in self._obstacles.items():
            for point in p.getClosestPoints(self._robot, body, max_distance_m, physicsClientId=cid):
                if best is None or float(point[8]) < best.distance_m:
                    best = Contact(link=self._link_names[point[3]], object=name, distance_m=float(point[8]))
        return best

    def close(self) -> None:
        """Disconnect the physics client; idempotent."""
        if self._client >= 0:
            p.disconnect(physicsClientId=self._client)
            self._client = -1

    def __enter__(self) -> SimWorld:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _live_client(self) -> int:
        if self._client < 0:
            raise RuntimeError("SimWorld is closed")
        return self._client

    def commanded_target(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(q (n,), qd (n,)) the joints are driven toward at this step (see `set_joint_target`)."""
        if self._sim.follow == "kinematic":
            return self._target_q.copy(), self._target_qd.copy()
        # pybullet's motor compares the target with the state at the start of the step, so the
        # target is the setpoint advanced to now.
        elapsed_s = (self._steps - self._target_step) * self._dt_s
        cap_s = self._sim.setpoint_timeout_s
        if elapsed_s <= cap_s:
            return self._target_q + self._target_qd * elapsed_s, self._target_qd.copy()
        return self._target_q + self._target_qd * cap_s, np.zeros_like(self._target_qd)

    def _apply_motor_targets(self) -> None:
        q, qd = self.commanded_target()
        n = len(self._joint_ids)
        p.setJointMotorControlArray(
            self._robot, self._joint_ids, p.POSITION_CONTROL,
            targetPositions=q.tolist(), targetVelocities=qd.tolist(),
            forces=self._joint_forces, positionGains=[_POSITION_GAIN] * n, velocityGains=[_VELOCITY_GAIN] * n,
            physicsClientId=self._client)


def _create_obstacle(obj: SceneObject, rgba: tuple[float, float, float, float], cid: int) -> int:
    """A static (mass 0) body with matching collision and visual shapes; returns its id."""
    if obj.type == "box":
        assert obj.size_m is not None  # validated by SceneObject
        half = [s / 2.0 for s in obj.size_m]
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=rgba, physicsClientId=cid)
    elif obj.type == "sphere":
        col = p.createCollisionShape(p.GEOM_SPHERE, radius=obj.radius_m, physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_SPHERE, radius=obj.radius_m, rgbaColor=rgba, physicsClientId=cid)
    elif obj.type == "mesh":
        assert obj.vertices_m is not None and obj.triangles is not None  # validated by SceneObject
        vertices, indices = obj.vertices_m.tolist(), obj.triangles.ravel().tolist()
        # A concave triangle mesh is only allowed on static bodies in bullet, which obstacles are.
        col = p.createCollisionShape(p.GEOM_MESH, vertices=vertices, indices=indices, physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_MESH, vertices=vertices, indices=indices, rgbaColor=rgba, physicsClientId=cid)
    else:
        # Collision shapes call the axial length `height`, visual shapes `length`. For a capsule
        # both are the cylindrical section between the cap centers (as in FCL).
        geom = p.GEOM_CYLINDER if obj.type == "cylinder" else p.GEOM_CAPSULE
        col = p.createCollisionShape(geom, radius=obj.radius_m, height=obj.length_m, physicsClientId=cid)
        vis = p.createVisualShape(geom, radius=obj.radius_m, length=obj.length_m, rgbaColor=rgba, physicsClientId=cid)
    quat_xyzw = np.asarray(obj.quat_xyzw, dtype=np.float64)  # SceneObject allows any non-zero norm
    return p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
                             basePosition=list(obj.position_m), baseOrientation=(quat_xyzw / np.linalg.norm(quat_xyzw)).tolist(),
                             physicsClientId=cid)


def _finite_vector(values: npt.ArrayLike, n: int, what: str) -> npt.NDArray[np.float64]:
    vec = np.array(values, dtype=np.float64)
    if vec.shape != (n,):
        raise ValueError(f"{what} must have shape ({n},), got {vec.shape}")
    if not np.all(np.isfinite(vec)):
        raise ValueError(f"{what} must be finite, got {vec.tolist()}")
    return vec
