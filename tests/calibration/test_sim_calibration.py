"""Hand-eye calibration end to end in the sim (pybullet DIRECT), and the refusals of bad datasets.

One small dataset (640x480, few views) is collected once per module through the CLI and
solved; the degenerate datasets are edited copies of it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from robonav.calibration import cli
from robonav.calibration.board import BoardSpec, board_corners_m, detect_board
from robonav.calibration.dataset import IntrinsicsSpec, load_dataset
from robonav.calibration.hand_eye import invert, transform_error
from robonav.calibration.sim_collect import ee_from_board_mount
from robonav.calibration.sim_scene import CalibrationScene, camera_intrinsics
from robonav.pipeline.transforms import look_at_quat_xyzw, make_transform
from robonav.services.config import default_config_path, load_config, perceived_world_from_camera, read_extrinsics

CONFIG = load_config()
SMALL = ["--views", "8", "--width", "640", "--height", "480", "--supersample", "2", "--seed", "1"]
EXPECTED_TRANSLATION_MM = 1.0
EXPECTED_ROTATION_DEG = 0.05


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("handeye") / "small"
    assert cli.main(["collect", "--out", str(out), *SMALL]) == 0
    return out


@pytest.mark.parametrize("supersample", [1, 2])
def test_renders_follow_the_stated_intrinsics(supersample: int) -> None:
    """A board at a known pose lands where OpenCV projects it: the TinyRenderer offset is cancelled."""
    board = BoardSpec()
    camera = CONFIG.cameras[0]
    intrinsics = camera_intrinsics(camera, 800, 600)
    world_from_camera = make_transform([0.0, 0.0, 0.0], look_at_quat_xyzw([0, 0, 0], [1.0, 0.05, -0.05]))
    world_from_board = world_from_camera @ make_transform([-0.15, -0.1, 0.7], [0.1, 0.05, 0.0, 0.994])
    with CalibrationScene(CONFIG.robot, board) as scene:
        scene.set_joint_positions(np.array(CONFIG.robot.home_position_rad))
        scene.set_board_pose(world_from_board)
        image = scene.render_rgb(world_from_camera, intrinsics, supersample=supersample)
    detection = detect_board(board, image)
    assert detection.ids.size == board.corner_count
    camera_from_board = invert(world_from_camera) @ world_from_board
    points = board_corners_m(board)[detection.ids] @ camera_from_board[:3, :3].T + camera_from_board[:3, 3]
    projected = np.column_stack([intrinsics.fx * points[:, 0] / points[:, 2] + intrinsics.cx,
                                 intrinsics.fy * points[:, 1] / points[:, 2] + intrinsics.cy])
    offset = (detection.corners_px - projected).mean(axis=0)
    assert np.all(np.abs(offset) < 0.12), offset


def test_small_sim_calibration_lands_within_its_expected_error(dataset_dir: Path, tmp_path: Path) -> None:
    dataset = load_dataset(dataset_dir)
    assert len(dataset.views) == 8 and dataset.ground_truth is not None
    assert dataset.intrinsics == IntrinsicsSpec(**{**camera_intrinsics(CONFIG.cameras[0], 640, 480).__dict__})
    np.testing.assert_allclose(dataset.ground_truth.ee_from_board.matrix, ee_from_board_mount(dataset.board), atol=1e-9)
    image = cv2.imread(str(dataset_dir / dataset.views[0].image))
    assert image.shape == (480, 640, 3)

    report_path, extrinsics_path = tmp_path / "report.json", tmp_path / "cam0.yaml"
    assert cli.main(["solve", str(dataset_dir), "--json", str(report_path), "--extrinsics-out", str(extrinsics_path)]) == 0
    report = json.loads(report_path.read_text())
    methods = {m["method"] for m in report["methods"]}
    assert methods == {"tsai", "park", "horaud", "andreff", "daniilidis", "shah", "li", "refined"}
    error = report["error_vs_truth"]
    assert error["translation_mm"] < EXPECTED_TRANSLATION_MM and error["rotation_deg"] < EXPECTED_ROTATION_DEG, error
    refined = next(m for m in report["methods"] if m["method"] == "refined")
    assert refined["reprojection_rms_px"] <= min(m["reprojection_rms_px"] for m in report["methods"])

    extrinsics = read_extrinsics(extrinsics_path)
    assert extrinsics.camera_id == "cam0" and extrinsics.parent_frame == "world"
    t_mm, r_deg = transform_error(extrinsics.parent_from_camera, CONFIG.cameras[0].world_from_camera)
    assert t_mm == pytest.approx(error["translation_mm"], abs=1e-3)
    assert r_deg == pytest.approx(error["rotation_deg"], abs=1e-4)

    # A config naming the file gives perception the calibrated pose; the sim keeps the true one.
    data = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    data["cameras"][0]["extrinsics_file"] = "cam0.yaml"  # beside the config file
    (tmp_path / "robonav.yaml").write_text(yaml.safe_dump(data), encoding="utf-8")
    camera = load_config(tmp_path / "robonav.yaml").cameras[0]
    np.testing.assert_allclose(perceived_world_from_camera(camera), extrinsics.parent_from_camera, atol=1e-12)
    np.testing.assert_allclose(camera.world_from_camera, CONFIG.cameras[0].world_from_camera, atol=1e-12)


def _edited_copy(source: Path, target: Path, edit) -> Path:  # noqa: ANN001
    shutil.copytree(source, target)
    data = yaml.safe_load((target / "dataset.yaml").read_text())
    edit(data, target)
    (target / "dataset.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return target


def test_degenerate_datasets_are_refused(dataset_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    def too_few(data: dict, _: Path) -> None:
        data["views"] = data["views"][:2]

    def no_board(data: dict, folder: Path) -> None:
        for view in data["views"]:
            cv2.imwrite(str(folder / view["image"]), np.full((480, 640, 3), 128, np.uint8))

    def no_rotation(data: dict, _: Path) -> None:
        for view in data["views"]:  # every end-effector pose turned like the first: only translations remain
            view["base_from_ee"]["quat_xyzw"] = data["views"][0]["base_from_ee"]["quat_xyzw"]

    cases = [(too_few, "too few usable views: 2"), (no_board, "board not found in any of the 8 images"),
             (no_rotation, "degenerate motion: the end effector rotates at most 0.00 deg")]
    for edit, message in cases:
        folder = _edited_copy(dataset_dir, tmp_path / edit.__name__, edit)
        caplog.clear()
        assert cli.main(["solve", str(folder), "--no-write"]) == 2
        assert message in caplog.text, caplog.text
    caplog.clear()
    assert cli.main(["solve", str(tmp_path / "nowhere")]) == 2
    assert "cannot read" in caplog.text
    caplog.clear()
    assert cli.main(["solve", str(dataset_dir), "--no-write", "--config", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml" in caplog.text
