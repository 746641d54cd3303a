"""The pybullet world: joint following, depth rendering conventions, contacts, isolation."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.config import ConfigError, from_mapping
from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.world import SimWorld, _create_obstacle, opengl_projection_matrix
from robonav.pipeline.transforms import PoseSpec, look_at_quat_xyzw, transform_points
from robonav.pipeline.types import FloatArray

ROBOT = RobotConfig()
HOME = np.array(ROBOT.home_position_rad)
# Off-axis, rotated, looking down at the arm's workspace: a mirrored or flipped convention
# would put points far from where the objects are.
EYE_M = (1.6, 0.2, 1.0)
CAMERA = CameraConfig(position_m=EYE_M, quat_xyzw=tuple(look_at_quat_xyzw(EYE_M, (0.6, 0.0, 0.3))))
SMALL_CAMERA = dataclasses.replace(CAMERA, width=320, height=240)
BOX = SceneObject("box", "box", (0.8, 0.3, 0.4), quat_xyzw=(0.0, 0.0, 0.2, 1.0), size_m=(0.2, 0.3, 0.4))
# Beside the arm, where joint 1 at +90 degrees swings the wrist into it.
WALL = SceneObject("wall", "box", (0.0, 0.38, 0.5), size_m=(0.4, 0.1, 0.6))
STEP_OFFSET = np.array([0.3, 0.3, -0.3, 0.3, 0.3, -0.3, 0.3])


def make_world(*objects: SceneObject, follow: str = "kinematic", camera: CameraConfig = SMALL_CAMERA) -> SimWorld:
    return SimWorld(ROBOT, camera, SimConfig(objects=objects, follow=follow))  # type: ignore[arg-type]


# --- signed distance functions in the object frame, for the rendering tests ---------------

def _box_sdf(obj: SceneObject, pts: FloatArray) -> FloatArray:
    q = np.abs(pts) - np.asarray(obj.size_m) / 2.0
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def _sphere_sdf(obj: SceneObject, pts: FloatArray) -> FloatArray:
    return np.linalg.norm(pts, axis=1) - obj.radius_m


def _cylinder_sdf(obj: SceneObject, pts: FloatArray) -> FloatArray:
    d = np.column_stack([np.linalg.norm(pts[:, :2], axis=1) - obj.radius_m, np.abs(pts[:, 2]) - obj.length_m / 2.0])
    return np.minimum(d.max(axis=1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=1)


def _capsule_sdf(obj: SceneObject, pts: FloatArray) -> FloatArray:
    # length_m is the cylindrical section between the cap centers.
    z = np.clip(pts[:, 2], -obj.length_m / 2.0, obj.length_m / 2.0)
    return np.linalg.norm(pts - np.column_stack([np.zeros_like(z), np.zeros_like(z), z]), axis=1) - obj.radius_m


SDF: dict[str, Callable[[SceneObject, FloatArray], FloatArray]] = {
    "box": _box_sdf, "sphere": _sphere_sdf, "cylinder": _cylinder_sdf, "capsule": _capsule_sdf,
}


def _object_points_in_object_frame(world: SimWorld, obj: SceneObject, camera: CameraConfig) -> FloatArray:
    frame = world.render_depth()
    body = next(b for b, name in world.body_labels().items() if name == obj.name)
    depth = np.where(frame.segmentation == body, frame.depth_m, np.nan)
    points_camera = points_from_depth(depth, frame.intrinsics)
    np.testing.assert_allclose(frame.world_from_camera, camera.world_from_camera)
    points_world = transform_points(frame.world_from_camera, points_camera)
    return transform_points(np.linalg.inv(obj.world_from_object), points_world)


# --- joints -----------------------------------------------------------------------------------

@pytest.mark.parametrize("follow", ["kinematic", "dynamic"])
def test_starts_at_home_at_rest(follow: str) -> None:
    with make_world(follow=follow) as world:
        q, qd = world.joint_state()
        np.testing.assert_allclose(q, HOME, atol=1e-9)
        np.testing.assert_allclose(qd, 0.0, atol=1e-9)
        assert world.sim_time_s == 0.0


def test_kinematic_follows_setpoint_exactly() -> None:
    with make_world(follow="kinematic") as world:
        target = HOME + STEP_OFFSET
        velocity = np.linspace(-0.5, 0.5, 7)
        world.set_joint_target(target, velocity)
        world.step()
        q, qd = world.joint_state()
        np.testing.assert_allclose(q, target, atol=1e-9)
        np.testing.assert_allclose(qd, velocity, atol=1e-9)
        for _ in range(9):
            world.step()
        np.testing.assert_allclose(world.joint_state()[0], target, atol=1e-9)
        assert world.sim_time_s == pytest.approx(10 / 240.0)


def test_dynamic_holds_home_against_gravity() -> None:
    with make_world(follow="dynamic") as world:
        for _ in range(240):
            world.step()
        np.testing.assert_allclose(world.joint_state()[0], HOME, atol=1e-3)


def test_dynamic_settles_on_a_step_target() -> None:
    with make_world(follow="dynamic") as world:
        target = HOME + STEP_OFFSET
        world.set_joint_target(target)
        errors = []
        for _ in range(120):
            world.step()
            errors.append(np.abs(world.joint_state()[0] - target).max())
        # Measured: 10 steps to 1e-2 rad, 13 steps to 1e-3 rad at 240 Hz.
        assert next(i for i, e in enumerate(errors) if e < 1e-2) < 30
        assert max(errors[60:]) < 1e-3
        assert np.abs(world.joint_state()[1]).max() < 1e-2


def test_dynamic_tracks_a_smooth_trajectory_sent_at_100_hz() -> None:
    amplitude = np.array([0.4, 0.3, 0.4, 0.3, 0.5, 0.4, 0.6])  # peak 1.9 rad/s at 0.5 Hz
    omega = 2.0 * math.pi * 0.5

    def reference(t_s: float) -> tuple[FloatArray, FloatArray]:
        return HOME + amplitude * math.sin(omega * t_s), amplitude * omega * math.cos(omega * t_s)

    with make_world(follow="dynamic") as world:
        world.set_joint_target(*reference(0.0))
        next_setpoint_s, errors = 0.0, []
        while world.sim_time_s < 2.0:
            if world.sim_time_s >= next_setpoint_s - 1e-9:
                world.set_joint_target(*reference(world.sim_time_s))
                next_setpoint_s += 0.01
            world.step()
            errors.append(np.abs(world.joint_state()[0] - reference(world.sim_time_s)[0]).max())
        assert max(errors[10:]) < 5e-3


def test_dynamic_extrapolation_stops_when_setpoints_stop() -> None:
    with make_world(follow="dynamic") as world:
        velocity = np.zeros(7)
        velocity[0] = 0.2
        world.set_joint_target(HOME, velocity)
        for _ in range(240):
            world.step()
        q, qd = world.joint_state()
        hold_s = world._sim.setpoint_timeout_s  # a first-order hold this long, then stop
        assert q[0] == pytest.approx(HOME[0] + 0.2 * hold_s, abs=1e-3)
        assert abs(qd[0]) < 1e-3


def test_set_joint_target_rejects_bad_vectors() -> None:
    with make_world() as world:
        with pytest.raises(ValueError, match=r"q_rad must have shape \(7,\)"):
            world.set_joint_target(np.zeros(6))
        with pytest.raises(ValueError, match="qd_rad_s must be finite"):
            world.set_joint_target(HOME, np.full(7, np.nan))
        with pytest.raises(ValueError, match="q_rad must be finite"):
            world.set_joint_target(np.full(7, np.inf))


# --- camera -----------------------------------------------------------------------------------

def test_box_depth_lands_on_the_box_surface_in_the_world_frame() -> None:
    with make_world(BOX, camera=CAMERA) as world:
        frame = world.render_depth()
        assert frame.depth_m.shape == (480, 640) and frame.depth_m.dtype == np.float32
        assert frame.segmentation.shape == (480, 640) and frame.segmentation.dtype == np.int32
        assert frame.intrinsics == CAMERA.intrinsics
        points = _object_points_in_object_frame(world, BOX, CAMERA)
    assert len(points) > 10_000
    assert np.abs(_box_sdf(BOX, points)).max() < 0.01


def test_box_center_projects_to_a_box_pixel() -> None:
    with make_world(BOX, camera=CAMERA) as world:
        frame = world.render_depth()
        labels = world.body_labels()
    center_camera = transform_points(np.linalg.inv(frame.world_from_camera), np.array([BOX.position_m]))[0]
    k = frame.intrinsics
    u = round(k.fx * center_camera[0] / center_camera[2] + k.cx)
    v = round(k.fy * center_camera[1] / center_camera[2] + k.cy)
    assert labels[int(frame.segmentation[v, u])] == "box"
    assert 0.0 < frame.depth_m[v, u] < center_camera[2]  # the visible face is in front of the center


def test_segmentation_labels_identify_objects_and_background() -> None:
    with make_world(BOX) as world:
        frame = world.render_depth()
        labels = world.body_labels()
    assert sorted(labels.values()) == ["box", "robot"]
    ids = set(np.unique(frame.segmentation).tolist())
    assert {labels[i] for i in ids if i >= 0} == {"box", "robot"}
    assert -1 in ids
    assert np.all(np.isinf(frame.depth_m[frame.segmentation == -1]))
    assert np.all(np.isfinite(frame.depth_m[frame.segmentation >= 0]))


def test_pixels_of_an_object_count_what_each_camera_sees_past_the_others() -> None:
    behind = SceneObject("behind", "box", (0.5, 0.3, 0.3), size_m=(0.1, 0.1, 0.1))
    # Between the camera and the box, tall and wide enough to hide it completely.
    screen = SceneObject("screen", "box", (1.1, 0.25, 0.55), size_m=(0.05, 0.8, 1.1))
    with make_world(behind) as world:
        seen = world.pixels_of("behind", [SMALL_CAMERA, CAMERA])
        world.add_object(screen)
        hidden = world.pixels_of("behind", [SMALL_CAMERA])
        with pytest.raises(ValueError, match="no obstacle named"):
            world.pixels_of("ghost", [SMALL_CAMERA])
    assert seen[0] > 100 and seen[1] > 3 * seen[0]  # 4x the pixels at 640x480
    assert hidden == [0]


@pytest.mark.parametrize(("obj", "inside_tolerance_m"), [
    (SceneObject("ball", "sphere", (0.7, -0.3, 0.3), radius_m=0.1), 0.01),
    (SceneObject("can", "cylinder", (0.7, -0.3, 0.3), quat_xyzw=(0.3, 0.0, 0.0, 1.0), radius_m=0.08, length_m=0.3), 0.01),
    # The renderer's capsule caps are coarsely tessellated: points sit up to ~2 cm inside the ideal cap.
    (SceneObject("pill", "capsule", (0.7, -0.3, 0.3), quat_xyzw=(0.0, 0.4, 0.0, 1.0), radius_m=0.06, length_m=0.25), 0.025),
], ids=["sphere", "cylinder", "capsule"])
def test_primitive_shapes_render_with_their_configured_size(obj: SceneObject, inside_tolerance_m: float) -> None:
    with make_world(obj) as world:
        points = _object_points_in_object_frame(world, obj, SMALL_CAMERA)
    assert len(points) > 500
    sdf = SDF[obj.type](obj, points)
    assert sdf.max() < 0.01
    assert sdf.min() > -inside_tolerance_m
    if obj.type == "capsule":
        # length_m is the cylindrical section: the visible cap tip is at length/2 + radius.
        assert np.abs(points[:, 2]).max() == pytest.approx(obj.length_m / 2.0 + obj.radius_m, abs=0.01)


@pytest.mark.parametrize(("obj", "probe_m", "expected_distance_m"), [
    (SceneObject("b", "box", (0, 0, 0), size_m=(0.2, 0.4, 0.6)), [(0.5, 0, 0), (0, 0.5, 0), (0, 0, 0.5)], [0.4, 0.3, 0.2]),
    (SceneObject("s", "sphere", (0, 0, 0), radius_m=0.1), [(0.5, 0, 0)], [0.4]),
    (SceneObject("c", "cylinder", (0, 0, 0), radius_m=0.1, length_m=0.4), [(0.5, 0, 0), (0, 0, 0.5)], [0.4, 0.3]),
    (SceneObject("k", "capsule", (0, 0, 0), radius_m=0.1, length_m=0.4), [(0.5, 0, 0), (0, 0, 0.5)], [0.4, 0.2]),
], ids=["box", "sphere", "cylinder", "capsule"])
def test_obstacle_collision_shapes_have_the_configured_size(
    obj: SceneObject, probe_m: list[tuple[float, float, float]], expected_distance_m: list[float]
) -> None:
    client = p.connect(p.DIRECT)
    try:
        body = _create_obstacle(obj, (1.0, 0.0, 0.0, 1.0), client)
        probe = p.createMultiBody(0.0, p.createCollisionShape(p.GEOM_SPHERE, radius=1e-3, physicsClientId=client),
                                  physicsClientId=client)
        for position_m, expected_m in zip(probe_m, expected_distance_m):
            p.resetBasePositionAndOrientation(probe, position_m, (0, 0, 0, 1), physicsClientId=client)
            closest = p.getClosestPoints(body, probe, 1.0, physicsClientId=client)
            assert min(c[8] for c in closest) + 1e-3 == pytest.approx(expected_m, abs=1e-4)
    finally:
        p.disconnect(physicsClientId=client)


def test_projection_matrix_matches_pinhole_model() -> None:
    k = dataclasses.replace(CAMERA.intrinsics, cx=300.0, cy=250.0, fx=500.0, fy=520.0)
    proj = opengl_projection_matrix(k, 0.1, 3.0)
    point_camera = np.array([0.2, -0.1, 1.5])  # optical frame
    clip = proj @ np.array([point_camera[0], -point_camera[1], -point_camera[2], 1.0])  # OpenGL eye frame
    ndc = clip[:3] / clip[3]
    u = (ndc[0] + 1.0) / 2.0 * k.width - 0.5  # pixel centers at integers, v downwards
    v = (1.0 - ndc[1]) / 2.0 * k.height - 0.5
    assert u == pytest.approx(k.fx * 0.2 / 1.5 + k.cx)
    assert v == pytest.approx(k.fy * -0.1 / 1.5 + k.cy)


# --- contacts ---------------------------------------------------------------------------------

@pytest.mark.parametrize("follow", ["kinematic", "dynamic"])
def test_no_contacts_at_home(follow: str) -> None:
    with make_world(follow=follow) as world:
        world.step()
        assert world.robot_obstacle_contacts() == []
        assert world.min_robot_obstacle_distance_m() == math.inf
    with make_world(WALL, follow=follow) as world:
        world.step()
        assert world.robot_obstacle_contacts() == []
        assert world.min_robot_obstacle_distance_m() == pytest.approx(0.2, abs=0.02)
        assert world.min_robot_obstacle_distance_m(max_distance_m=0.1) == math.inf


@pytest.mark.parametrize("follow", ["kinematic", "dynamic"])
def test_driving_the_arm_into_a_wall_reports_the_link_and_the_wall(follow: str) -> None:
    with make_world(WALL, follow=follow) as world:
        target = HOME.copy()
        target[0] = math.pi / 2.0
        world.set_joint_target(target)
        for _ in range(240):
            world.step()
        contacts = world.robot_obstacle_contacts()
        assert contacts, "expected the wrist to touch the wall"
        assert {c.object for c in contacts} == {"wall"}
        assert {c.link for c in contacts} <= {"panda_link5", "panda_link6", "panda_link7", "panda_hand",
                                              "panda_leftfinger", "panda_rightfinger"}
        assert all(c.distance_m <= 0.0 for c in contacts)
        assert world.min_robot_obstacle_distance_m() <= 1e-3
    if follow == "kinematic":
        assert min(c.distance_m for c in contacts) < -0.01  # passes through: penetration is visible


# --- lifecycle, isolation, config -------------------------------------------------------------

def test_two_worlds_do_not_interfere() -> None:
    with make_world(follow="kinematic") as moving, make_world(BOX, follow="dynamic") as still:
        moving.set_joint_target(HOME + STEP_OFFSET)
        for _ in range(20):
            moving.step()
        still.step()
        np.testing.assert_allclose(moving.joint_state()[0], HOME + STEP_OFFSET, atol=1e-9)
        np.testing.assert_allclose(still.joint_state()[0], HOME, atol=1e-3)
        assert sorted(moving.body_labels().values()) == ["robot"]
        assert sorted(still.body_labels().values()) == ["box", "robot"]
        assert moving.sim_time_s == pytest.approx(20 / 240.0)
        assert still.sim_time_s == pytest.approx(1 / 240.0)
        moving.close()
        still.step()
        assert "box" in {still.body_labels()[i] for i in np.unique(still.render_depth().segmentation) if i >= 0}


def test_closed_world_refuses_use_and_close_is_idempotent() -> None:
    world = make_world()
    world.close()
    world.close()
    with pytest.raises(RuntimeError, match="closed"):
        world.step()


def test_missing_joint_or_wrong_base_is_a_value_error() -> None:
    bad_joint = dataclasses.replace(ROBOT, joint_names=(*ROBOT.joint_names[:6], "panda_joint99"))
    with pytest.raises(ValueError, match="panda_joint99"):
        SimWorld(bad_joint, SMALL_CAMERA, SimConfig())
    bad_fixed = dataclasses.replace(ROBOT, fixed_joint_positions={"gripper": 0.0})
    with pytest.raises(ValueError, match="gripper"):
        SimWorld(bad_fixed, SMALL_CAMERA, SimConfig())
    bad_base = dataclasses.replace(ROBOT, base_link="panda_link1")
    with pytest.raises(ValueError, match="base_link"):
        SimWorld(bad_base, SMALL_CAMERA, SimConfig())


def test_the_arm_stands_where_robot_world_from_base_puts_it() -> None:
    # Turned about a tilted axis and moved: pybullet's link frames are the planner model's.
    pose = PoseSpec((0.5, -0.4, 0.3), (0.1, 0.2, 0.3, math.sqrt(1.0 - 0.14)))
    posed = dataclasses.replace(ROBOT, world_from_base=pose)
    model = RobotModel.from_config(posed)
    rng = np.random.default_rng(9)
    with SimWorld(posed, SMALL_CAMERA, SimConfig()) as world:
        body, cid = world._robot, world._client  # noqa: SLF001 (pybullet's own view of the arm)
        index = {p.getJointInfo(body, j, physicsClientId=cid)[12].decode(): j
                 for j in range(p.getNumJoints(body, physicsClientId=cid))}
        for q in rng.uniform(model.lower_limits_rad, model.upper_limits_rad, size=(5, model.dof)):
            world.set_joint_positions(q)
            ours = model.link_poses(q)
            for link in ("panda_link2", "panda_link5", "panda_hand", "panda_leftfinger"):
                state = p.getLinkState(body, index[link], computeForwardKinematics=True, physicsClientId=cid)
                np.testing.assert_allclose(state[4], ours[link][:3, 3], atol=1e-6, err_msg=link)
                rotation = np.array(p.getMatrixFromQuaternion(state[5])).reshape(3, 3)
                np.testing.assert_allclose(rotation, ours[link][:3, :3], atol=1e-6, err_msg=link)
        base_position, base_quat = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        np.testing.assert_allclose(np.array(p.getMatrixFromQuaternion(base_quat)).reshape(3, 3),
                                   pose.matrix[:3, :3], atol=1e-6)
    # A ball at the posed hand touches the posed arm and is far from the arm at the origin.
    hand_m = model.frame_pose(model.home_position_rad, "panda_hand")[:3, 3]
    ball = SceneObject("ball", "sphere", tuple(float(v) for v in hand_m), radius_m=0.02)
    for config, touches in ((posed, True), (ROBOT, False)):
        with SimWorld(config, SMALL_CAMERA, SimConfig(objects=(ball,))) as world:
            closest = world.closest_robot_obstacle(0.5)
            assert (closest is not None and closest.distance_m <= 0.0) is touches, closest


def test_sim_config_validation_and_loading() -> None:
    config = from_mapping(SimConfig, {
        "physics_rate_hz": 500, "follow": "kinematic",
        "objects": [{"name": "table", "type": "box", "position_m": [0.5, 0, 0.2], "size_m": [1, 1, 0.05]}],
    }, source="sim.yaml", key="sim")
    assert config.physics_rate_hz == 500.0 and config.objects[0].name == "table"
    with pytest.raises(ValueError, match="physics_rate_hz"):
        SimConfig(physics_rate_hz=0.0)
    with pytest.raises(ValueError, match="joint_state_rate_hz"):
        SimConfig(physics_rate_hz=100.0, joint_state_rate_hz=200.0)
    with pytest.raises(ValueError, match="duplicate"):
        SimConfig(objects=(BOX, BOX))
    with pytest.raises(ConfigError, match="sim.follow"):
        from_mapping(SimConfig, {"follow": "teleport"}, key="sim")


# --- objects at run time ----------------------------------------------------------------------

def test_objects_are_added_moved_removed_and_replaced_at_run_time() -> None:
    with make_world(BOX) as world:
        world.add_object(WALL)
        assert [o.name for o in world.objects] == ["box", "wall"]
        assert sorted(world.body_labels().values()) == ["box", "robot", "wall"]
        world.set_object_pose("box", (0.9, -0.3, 0.5), (0.0, 0.0, 0.0, 2.0))
        moved = next(o for o in world.objects if o.name == "box")
        assert moved.position_m == pytest.approx((0.9, -0.3, 0.5)) and moved.quat_xyzw == pytest.approx((0, 0, 0, 1))
        body = next(b for b, n in world.body_labels().items() if n == "box")
        position, _ = p.getBasePositionAndOrientation(body, physicsClientId=world._client)
        assert position == pytest.approx((0.9, -0.3, 0.5))
        world.remove_object("wall")
        assert sorted(world.body_labels().values()) == ["box", "robot"]
        world.set_objects([WALL])
        assert [o.name for o in world.objects] == ["wall"]
        with pytest.raises(ValueError, match="no obstacle named 'box'"):
            world.remove_object("box")
        with pytest.raises(ValueError, match="robot"):
            world.add_object(dataclasses.replace(WALL, name="robot"))
        with pytest.raises(ValueError, match="unique"):
            world.set_objects([WALL, WALL])
        with pytest.raises(ValueError, match="zero norm"):
            world.set_object_pose("wall", (0, 0, 0), (0, 0, 0, 0))


@pytest.mark.parametrize("follow", ["kinematic", "dynamic"])
def test_an_obstacle_moved_onto_the_arm_is_a_contact(follow: str) -> None:
    with make_world(WALL, follow=follow) as world:
        world.step()
        assert world.robot_obstacle_contacts() == []
        world.set_object_pose("wall", (0.3, 0.0, 0.5))  # through the upper arm
        world.step()
        assert {c.object for c in world.robot_obstacle_contacts()} == {"wall"}


def test_set_joint_positions_teleports_without_stepping() -> None:
    with make_world() as world:
        world.set_joint_positions(HOME + STEP_OFFSET)
        np.testing.assert_allclose(world.joint_state()[0], HOME + STEP_OFFSET, atol=1e-12)
        assert world.sim_time_s == 0.0
        with pytest.raises(ValueError, match="shape"):
            world.set_joint_positions(HOME[:3])


def test_a_continuous_joint_is_unbounded_and_a_prismatic_one_moves_in_metres(spinner_urdf: Path) -> None:
    urdf = spinner_urdf
    robot = RobotConfig(name="spinner", urdf=str(urdf), base_link="foot", end_effector_link="slider",
                        joint_names=("spin", "slide"), max_velocity_rad_s=(2.0, 0.5), max_acceleration_rad_s2=(8.0, 2.0),
                        max_jerk_rad_s3=(4000.0, 1000.0), home_position_rad=(0.0, 0.0))
    world = SimWorld(robot, SMALL_CAMERA, SimConfig(follow="kinematic", gravity=False))
    try:
        lower, upper = world.joint_limits
        # pybullet says (0, -1) for a continuous joint: the sim's driver would refuse every setpoint.
        assert lower[0] == -math.inf and upper[0] == math.inf
        np.testing.assert_allclose([lower[1], upper[1]], [0.0, 0.2])
        world.set_joint_target([4.0, 0.15])
        world.step()
        np.testing.assert_allclose(world.joint_state()[0], [4.0, 0.15], atol=1e-9)
    finally:
        world.close()
