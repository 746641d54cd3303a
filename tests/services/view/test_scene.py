"""The view's drawn robot: its URDF root stands where the planner's model puts it."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np
import pytest

pytest.importorskip("viser", reason="the `view` extra (viser) is not installed")

import viser  # noqa: E402

from robonav.pipeline.robot.config import RobotConfig  # noqa: E402
from robonav.pipeline.robot.model import RobotModel  # noqa: E402
from robonav.pipeline.transforms import PoseSpec  # noqa: E402
from robonav.services.view.scene import UrdfPose  # noqa: E402


@pytest.fixture
def server() -> Iterator[viser.ViserServer]:
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


def test_the_robot_is_drawn_where_robot_world_from_base_puts_it(server: viser.ViserServer) -> None:
    pose = PoseSpec((0.8, -0.6, 0.3), (0.1, -0.2, math.sin(0.4), math.sqrt(1.0 - 0.05 - math.sin(0.4) ** 2)))
    robot = RobotModel.from_config(dataclasses.replace(RobotConfig(), world_from_base=pose))
    drawn = UrdfPose(server, robot, "/robot")
    np.testing.assert_allclose(drawn.frame.position, pose.position_m, atol=1e-9)
    x, y, z, w = pose.quat_xyzw
    wxyz = np.asarray(drawn.frame.wxyz)
    # A quaternion and its negative are one rotation.
    assert np.allclose(wxyz, [w, x, y, z], atol=1e-6) or np.allclose(wxyz, [-w, -x, -y, -z], atol=1e-6), wxyz
