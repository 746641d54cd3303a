"""The view in a real browser: a `robonav view` process fed over real Zenoh on loopback, opened
in headless Chromium (Debian's, software WebGL). Once two screenshots in a row are identical,
the path's colour must be where the path projects, and hiding the robot (showing the collision
spheres) must change the pixels where the robot (the spheres) project; the same for the UR5 of
`robonav view --robot configs/ur5.yaml` (COLLADA visual meshes), in a view in process."""

from __future__ import annotations

import dataclasses
import io
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("viser", reason="the `view` extra (viser) is not installed")
pytest.importorskip("playwright", reason="the `view` extra (playwright) is not installed")

from PIL import Image  # noqa: E402

from robonav.pipeline.collision.spheres.sphere_model import robot_sphere_model  # noqa: E402
from robonav.pipeline.robot.model import RobotModel  # noqa: E402
from robonav.pipeline.wire.messages import (  # noqa: E402
    ExecutorPath,
    ExecutorStatus,
    JointState,
    PlanningSceneState,
    SceneObjectSpec,
)
from robonav.services.common import declare_latched_publisher, open_session  # noqa: E402
from robonav.services.config import RobonavConfig, ZenohConfig, load_config  # noqa: E402
from robonav.services.keys import Keys  # noqa: E402
from robonav.services.stack.up import Stack  # noqa: E402
from robonav.services.view.app import (  # noqa: E402
    CAMERA_FOV_RAD,
    CAMERA_LOOK_AT_M,
    CAMERA_POSITION_M,
    ViewNode,
    ViewOptions,
    initial_camera_m,
    parse_args,
    view_config,
)
from robonav.services.view.browser import find_chromium, open_page, page_url, stable_screenshot  # noqa: E402
from robonav.services.view.scene import PATH_RGB, interpolate_path  # noqa: E402
from robonav.services.view.spheres import world_spheres  # noqa: E402

from ...conftest import REPO_ROOT  # noqa: E402
from ..conftest import free_port, write_config  # noqa: E402
from .conftest import project  # noqa: E402

pytestmark = [pytest.mark.e2e, pytest.mark.skipif(find_chromium() is None,
                               reason="Debian's chromium is not installed (`make e2e` installs it)")]

VIEW_START_TIMEOUT_S = 60.0
WIDTH, HEIGHT = 800, 480
"""The control panel takes 320 px on the right; the 3D view gets the rest."""
PATH_WAIT_S = 30.0
"""How long the drawn path may take to show after the first settled picture [s]."""
SNAPSHOT_TIMEOUT_S = 120.0
"""A guard against a hung process, not a speed target (a loaded 2-core machine is slow)."""
CAMERA_QUERY = (f"initialCameraPosition={','.join(map(str, CAMERA_POSITION_M))}"
                f"&initialCameraLookAt={','.join(map(str, CAMERA_LOOK_AT_M))}&initialCameraUp=0,0,1"
                f"&initialCameraFov={CAMERA_FOV_RAD}")
"""The view's own initial camera, stated in the address: the tests project points with it."""


class Scene:
    """A router, a `robonav view` process and a publisher of a robot, a path and a status."""

    def __init__(self, cfg: RobonavConfig, config_path: Path) -> None:
        self.cfg = cfg
        self.config_path = config_path
        self.robot = RobotModel.from_config(cfg.robot)
        self.q_robot = np.array(cfg.robot.home_position_rad)
        goals = np.array(cfg.demo.goals_rad)
        self.path = np.vstack([self.q_robot, goals[0], goals[1]])
        self.view_port = free_port()
        self.stack = Stack(cfg, str(config_path), services=(), view_port=self.view_port, log_level="WARNING")
        self.session = open_session(cfg.zenoh)
        keys = Keys(cfg.cell)
        self._path_pub = declare_latched_publisher(self.session, keys.executor_path)
        self._path_pub.put(ExecutorPath(stamp=time.time(), trajectory_id="t1", joint_names=self.robot.joint_names,
                                        path=self.path, duration_s=4.0).to_wire())
        # A planner object in front of the arm, clear of the path, latched as the planner publishes it.
        self.box = SceneObjectSpec("crate", "box", (0.55, -0.45, 0.15), size_m=(0.2, 0.2, 0.2))
        self._scene_pub = declare_latched_publisher(self.session, keys.scene_state)
        self._scene_pub.put(PlanningSceneState(stamp=time.time(), revision=1, objects=(self.box,)).to_wire())
        self.session.put(keys.status, ExecutorStatus(stamp=time.time(), state="idle", trajectory_id="t1",
                                                     progress=1.0, last_result="succeeded").to_wire())
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._publish_joint_states, args=(keys.joint_states,), daemon=True)
        self._thread.start()

    def _publish_joint_states(self, key: str) -> None:
        while not self._stop.wait(0.05):
            self.session.put(key, JointState(stamp=time.time(), names=self.robot.joint_names, position=self.q_robot,
                                             velocity=np.zeros(len(self.q_robot))).to_wire())

    def wait_for_view(self) -> str:
        url = f"http://127.0.0.1:{self.view_port}/"
        deadline = time.monotonic() + VIEW_START_TIMEOUT_S
        while True:
            assert "view" not in self.stack.dead(), f"robonav view exited: {self.stack.dead()}"
            try:
                with urllib.request.urlopen(url, timeout=2.0) as response:
                    if response.status == 200:
                        return url
            except OSError:
                pass
            assert time.monotonic() < deadline, f"the view did not serve {url} within {VIEW_START_TIMEOUT_S:.0f} s"
            time.sleep(0.2)

    def close(self) -> dict[str, int]:
        self._stop.set()
        self._thread.join()
        self._path_pub.undeclare()
        self._scene_pub.undeclare()
        self.session.close()
        return self.stack.close()


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Scene]:
    directory = tmp_path_factory.mktemp("view")
    config_path = write_config(directory, "view.yaml", zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]})
    scene = Scene(load_config(config_path), config_path)
    yield scene
    codes = scene.close()
    assert codes == {"view": 0, "router": 0}, f"robonav view did not stop cleanly: {codes}"


def rgb(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def path_mask(image: np.ndarray) -> np.ndarray:
    """Pixels of the path colour (lines are unlit; antialiased edges are left out)."""
    return np.all(np.abs(image - np.array(PATH_RGB)) <= (40, 60, 50), axis=2)


def near(mask: np.ndarray, pixels: np.ndarray, radius: int) -> np.ndarray:
    """For each pixel (N, 2), whether `mask` is set within `radius` of it."""
    height, width = mask.shape
    out = []
    for x, y in np.round(pixels).astype(int):
        window = mask[max(0, y - radius):min(height, y + radius + 1), max(0, x - radius):min(width, x + radius + 1)]
        out.append(bool(window.any()))
    return np.array(out)


def test_browser_draws_the_robot_and_the_path(scene: Scene) -> None:
    url = scene.wait_for_view()
    with open_page(page_url(f"{url}?{CAMERA_QUERY}"), width=WIDTH, height=HEIGHT) as page:
        canvas = page.locator("canvas").first
        everything = rgb(stable_screenshot(page, canvas))
        height, width, _ = everything.shape
        ee = scene.robot.config.end_effector_link
        trace_px = project(np.array([scene.robot.frame_pose(q, ee)[:3, 3]
                                     for q in interpolate_path(scene.path, 0.05)]), width, height)
        # A picture can settle before the latched path reaches the page (a loaded machine): look
        # again for a while before calling it missing.
        deadline = time.monotonic() + PATH_WAIT_S
        while True:
            on_path = path_mask(everything)
            hits = near(on_path, trace_px, radius=4)
            if hits.mean() >= 0.6 or time.monotonic() > deadline:
                break
            page.wait_for_timeout(500)
            everything = rgb(stable_screenshot(page, canvas))
        # Parts of the trace may pass behind the arm; most of it must show.
        assert hits.mean() >= 0.6, f"path colour near {hits.mean():.0%} of the projected trace after {PATH_WAIT_S:.0f} s"
        page.get_by_role("checkbox", name="Path", exact=True).click()
        no_path = rgb(stable_screenshot(page, canvas))
        assert path_mask(no_path).sum() < 0.05 * on_path.sum(), "hiding the path left its colour on the page"
        page.get_by_role("checkbox", name="Robot", exact=True).click()
        no_robot = rgb(stable_screenshot(page, canvas))
    changed = np.any(no_path != no_robot, axis=2)
    links = scene.robot.link_poses(scene.q_robot)
    link_px = project(np.array([pose[:3, 3] for pose in links.values()]), width, height)
    moved = near(changed, link_px, radius=3)
    assert moved.mean() >= 0.8, f"hiding the robot changed nothing at {sorted(np.array(list(links))[~moved])}"
    # ...and little away from it: the changed pixels lie around the robot's projection.
    ys, xs = np.nonzero(changed)
    low, high = link_px.min(axis=0) - 80, link_px.max(axis=0) + 80
    inside = (xs >= low[0]) & (xs <= high[0]) & (ys >= low[1]) & (ys <= high[1])
    assert inside.mean() > 0.95


def test_browser_draws_the_planner_objects(scene: Scene) -> None:
    """Hiding the 'Planner objects' layer changes the pixels where the planner's box projects, and
    little elsewhere."""
    url = scene.wait_for_view()
    with open_page(page_url(f"{url}?{CAMERA_QUERY}"), width=WIDTH, height=HEIGHT) as page:
        canvas = page.locator("canvas").first
        with_objects = rgb(stable_screenshot(page, canvas))
        page.get_by_role("checkbox", name="Planner objects", exact=True).click()
        without = rgb(stable_screenshot(page, canvas))
    height, width, _ = with_objects.shape
    changed = np.any(np.abs(with_objects - without) > 8, axis=2)
    center = np.array(scene.box.position_m)
    half = np.array(scene.box.size_m) / 2.0
    corners = center + half * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    box_px = project(np.vstack([center, corners]), width, height)
    assert near(changed, box_px[:1], radius=3).all(), "hiding the planner objects left the box's center unchanged"
    ys, xs = np.nonzero(changed)
    low, high = box_px.min(axis=0) - 10, box_px.max(axis=0) + 10
    inside = (xs >= low[0]) & (xs <= high[0]) & (ys >= low[1]) & (ys <= high[1])
    assert changed.sum() > 100 and inside.mean() > 0.95, (changed.sum(), inside.mean())


def test_browser_draws_the_collision_spheres(scene: Scene) -> None:
    """Ticking 'Collision spheres' changes the pixels where the planner's spheres project at the
    arm's joint state, and little beyond them."""
    url = scene.wait_for_view()
    with open_page(page_url(f"{url}?{CAMERA_QUERY}"), width=WIDTH, height=HEIGHT) as page:
        canvas = page.locator("canvas").first
        without = rgb(stable_screenshot(page, canvas))
        toggle = page.get_by_role("checkbox", name="Collision spheres", exact=True)
        toggle.click()
        # The view covers the robot on first show (seconds): a still picture may come first.
        deadline = time.monotonic() + SNAPSHOT_TIMEOUT_S
        while True:
            with_spheres = rgb(stable_screenshot(page, canvas))
            changed = np.any(np.abs(with_spheres - without) > 8, axis=2)
            if changed.sum() > 100 or time.monotonic() > deadline:
                break
            page.wait_for_timeout(500)
        toggle.click()  # the layer's state is the server's: leave it as found
    height, width, _ = with_spheres.shape
    centers, radii = world_spheres(scene.robot, robot_sphere_model(scene.robot), scene.q_robot)
    centers_px = project(centers, width, height)
    hits = near(changed, centers_px, radius=3)
    assert hits.mean() >= 0.8, f"the spheres changed nothing near {hits.size - hits.sum()} of {hits.size} centers"
    # Beyond the spheres' outline little changes: a margin of the largest radius seen from the camera.
    margin_px = (height / 2.0) / np.tan(CAMERA_FOV_RAD / 2.0) * radii.max() / 1.5
    ys, xs = np.nonzero(changed)
    low, high = centers_px.min(axis=0) - margin_px, centers_px.max(axis=0) + margin_px
    inside = (xs >= low[0]) & (xs <= high[0]) & (ys >= low[1]) & (ys <= high[1])
    assert inside.mean() > 0.95, inside.mean()


def test_view_snapshot_fails_clearly_without_a_robot(scene: Scene, tmp_path: Path) -> None:
    """`robonav view --snapshot` on a cell nobody publishes: exit 1 and say why, no browser needed."""
    data = yaml.safe_load(scene.config_path.read_text(encoding="utf-8"))
    data["cell"] = "nobody"
    config_path = tmp_path / "nobody.yaml"
    config_path.write_text(yaml.safe_dump(data), encoding="utf-8")
    out = tmp_path / "snap.png"
    result = subprocess.run([sys.executable, "-m", "robonav.services.cli", "view", "--config", str(config_path),
                             "--port", "0", "--snapshot", str(out), "--wait-s", "1"],
                            capture_output=True, text=True, timeout=SNAPSHOT_TIMEOUT_S)
    assert result.returncode == 1, result.stderr
    assert "no joint state on robonav/nobody/robot/joint_states" in result.stderr
    assert not out.exists()


def test_browser_draws_the_ur5_from_its_collada_meshes() -> None:
    """Another robot's COLLADA visual meshes reach the browser: `robonav view --robot
    configs/ur5.yaml`'s page, at the view's starting camera for that robot (placed for its shoulder
    and reach); hiding the robot changes the pixels where its links project, and little beyond."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    args = parse_args(["--robot", str(REPO_ROOT / "configs" / "ur5.yaml")])
    cfg = dataclasses.replace(view_config(args), zenoh=ZenohConfig(connect=(endpoint,)))
    session = open_session(cfg.zenoh)
    node = ViewNode(cfg, session, ViewOptions(port=0))
    try:
        ur5 = node.layers.robot
        node.layers.set_robot_joints(ur5.joint_names, ur5.home_position_rad.tolist())
        eye_m, target_m = initial_camera_m(ur5)
        query = (f"initialCameraPosition={','.join(map(str, eye_m))}&initialCameraLookAt={','.join(map(str, target_m))}"
                 f"&initialCameraUp=0,0,1&initialCameraFov={CAMERA_FOV_RAD}")
        with open_page(page_url(f"{node.url}?{query}"), width=WIDTH, height=HEIGHT) as page:
            canvas = page.locator("canvas").first
            with_robot = rgb(stable_screenshot(page, canvas))
            node.layers.set_visible("robot", False)
            without = rgb(stable_screenshot(page, canvas))
    finally:
        node.close()
        session.close()
        router.close()
    height, width, _ = with_robot.shape
    changed = np.any(np.abs(with_robot - without) > 8, axis=2)
    links = ur5.link_poses(ur5.home_position_rad)
    link_px = project(np.array([pose[:3, 3] for pose in links.values()]), width, height, eye_m, target_m)
    moved = near(changed, link_px, radius=3)
    assert moved.mean() >= 0.8, f"hiding the UR5 changed nothing at {sorted(np.array(list(links))[~moved])}"
    ys, xs = np.nonzero(changed)
    low, high = link_px.min(axis=0) - 80, link_px.max(axis=0) + 80
    inside = (xs >= low[0]) & (xs <= high[0]) & (ys >= low[1]) & (ys <= high[1])
    assert changed.sum() > 500 and inside.mean() > 0.95, (changed.sum(), inside.mean())
