"""The planner's collision spheres in the view: where they are drawn for a joint state (each
sphere of the model in its link's pose, covering the link's hull there), built only when shown."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

pytest.importorskip("viser", reason="the `view` extra (viser) is not installed")

import viser  # noqa: E402

from robonav.pipeline.collision.spheres.sphere_model import robot_sphere_model  # noqa: E402
from robonav.pipeline.robot.model import RobotModel  # noqa: E402
from robonav.pipeline.transforms import rotation_from_quat_xyzw  # noqa: E402
from robonav.services.config import load_config  # noqa: E402
from robonav.services.view.app import parse_args  # noqa: E402
from robonav.services.view.scene import SceneLayers  # noqa: E402
from robonav.services.view.spheres import SPHERE_OPACITY, world_spheres  # noqa: E402

CONFIG = load_config()
GOALS = np.array(CONFIG.demo.goals_rad)


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_config(CONFIG.robot)


@pytest.fixture
def server() -> Iterator[viser.ViserServer]:
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


def _hull_excess_m(robot: RobotModel, centers_m: np.ndarray, radii_m: np.ndarray, link_index: np.ndarray,
                   q: np.ndarray) -> float:
    """Largest distance by which a link's hull vertex, posed at `q`, lies outside all of that
    link's spheres (<= 0: the drawn spheres cover the link where it is drawn)."""
    worst = -np.inf
    poses = robot.link_poses(q)
    for li, link in enumerate(robot.collision_link_names):
        world_from_link = poses[link]
        vertices = robot.link_hull_vertices[link] @ world_from_link[:3, :3].T + world_from_link[:3, 3]
        mine = link_index == li
        gaps = np.linalg.norm(vertices[:, None, :] - centers_m[mine][None], axis=2) - radii_m[mine][None]
        worst = max(worst, float(gaps.min(axis=1).max()))
    return worst


def test_world_spheres_cover_every_link_at_its_pose(robot: RobotModel) -> None:
    model = robot_sphere_model(robot)
    for q in (robot.home_position_rad, *GOALS):
        centers, radii = world_spheres(robot, model, q)
        assert centers.shape == (model.sphere_count, 3)
        np.testing.assert_array_equal(radii, model.radii_m)
        assert _hull_excess_m(robot, centers, radii, model.link_index, q) <= 1e-9
        # Not the home pose's spheres: the moving links' spheres move with the state.
        if not np.allclose(q, robot.home_position_rad):
            home, _ = world_spheres(robot, model, robot.home_position_rad)
            moved = np.linalg.norm(centers - home, axis=1) > 1e-3
            assert moved.any() and not moved[model.link_index == 0].any()  # the base stays put


def test_the_layer_draws_the_models_spheres_where_the_arm_is(robot: RobotModel, server: viser.ViserServer) -> None:
    layers = SceneLayers(server, robot, [])
    spheres = layers.spheres
    assert not spheres.root.visible and spheres.model is None, "nothing is built while the layer is off"
    layers.set_robot_joints(robot.joint_names, GOALS[0].tolist())
    assert spheres.sphere_nodes == []

    layers.set_visible("spheres", True)
    model = spheres.model
    assert model is not None and spheres.root.visible
    assert len(spheres.sphere_nodes) == model.sphere_count
    for q in (GOALS[0], GOALS[1]):  # posed at the state seen while hidden, then following the arm
        if q is not GOALS[0]:
            layers.set_robot_joints(robot.joint_names, q.tolist())
        centers, radii = world_spheres(robot, model, q)
        drawn = []
        for s, node in enumerate(spheres.sphere_nodes):
            frame = spheres.link_frames[model.link_names[model.link_index[s]]]
            w, x, y, z = frame.wxyz
            drawn.append(rotation_from_quat_xyzw((x, y, z, w)) @ np.asarray(node.position) + np.asarray(frame.position))
            assert node.radius == pytest.approx(radii[s]) and node.opacity == SPHERE_OPACITY
        np.testing.assert_allclose(np.array(drawn), centers, atol=1e-6)

    layers.set_visible("spheres", False)
    assert not spheres.root.visible and spheres.model is model


def test_spheres_show_from_the_start_with_the_flag(robot: RobotModel, server: viser.ViserServer) -> None:
    assert parse_args(["--spheres"]).spheres and not parse_args([]).spheres
    layers = SceneLayers(server, robot, [], show_spheres=True)
    assert layers.spheres.root.visible and len(layers.spheres.sphere_nodes) == robot_sphere_model(robot).sphere_count
