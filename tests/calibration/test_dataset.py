"""Dataset and extrinsics files: round trips and strict loading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robonav.calibration.board import BoardSpec
from robonav.calibration.dataset import (
    DATASET_FORMAT,
    Dataset,
    GroundTruth,
    IntrinsicsSpec,
    ViewSpec,
    load_dataset,
    save_dataset,
)
from robonav.pipeline.camera import CameraExtrinsics
from robonav.pipeline.config import ConfigError
from robonav.pipeline.transforms import PoseSpec
from robonav.services.config import read_extrinsics, write_extrinsics


def _dataset() -> Dataset:
    pose = PoseSpec.from_matrix(np.eye(4))
    return Dataset(format=DATASET_FORMAT, setup="eye_to_hand", camera_id="cam0",
                   intrinsics=IntrinsicsSpec(640, 480, 500.0, 500.0, 319.5, 239.5, (0.01, -0.02, 0.0, 0.0, 0.001)),
                   board=BoardSpec(), views=(ViewSpec("images/a.png", (0.1, 0.2), pose), ViewSpec("images/b.png", (0.3, 0.4))),
                   joint_names=("j1", "j2"), ground_truth=GroundTruth(world_from_camera=pose, ee_from_board=pose),
                   source={"kind": "sim", "seed": 3})


def test_dataset_round_trip(tmp_path: Path) -> None:
    dataset = _dataset()
    save_dataset(tmp_path, dataset)
    assert load_dataset(tmp_path) == dataset


def test_pose_spec_round_trip() -> None:
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    t[:3, 3] = [1.0, -2.0, 0.5]
    np.testing.assert_allclose(PoseSpec.from_matrix(t).matrix, t, atol=1e-12)


@pytest.mark.parametrize(("edit", "pattern"), [
    (lambda text: text.replace("setup: eye_to_hand", "setup: eye_on_hand"), r"key 'setup': expected one of"),
    (lambda text: text.replace("camera_id: cam0", "camera_id: cam0\nlens: wide"), r"key 'lens': unknown key"),
    (lambda text: text.replace("squares_x: 7", "squares_x: seven"), r"key 'board.squares_x': expected int"),
    (lambda text: text.replace(f"format: {DATASET_FORMAT}", "format: other/2"), r"format must be"),
])
def test_bad_dataset_files_name_the_key(tmp_path: Path, edit, pattern: str) -> None:  # noqa: ANN001
    path = save_dataset(tmp_path, _dataset())
    path.write_text(edit(path.read_text()))
    with pytest.raises(ConfigError, match=pattern):
        load_dataset(tmp_path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_dataset(tmp_path / "missing")


def test_extrinsics_round_trip_and_strictness(tmp_path: Path) -> None:
    extrinsics = CameraExtrinsics("cam0", "world", (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), "refined", 0.1, "now")
    path = write_extrinsics(tmp_path / "calibration" / "cam0.yaml", extrinsics)
    assert read_extrinsics(path) == extrinsics
    np.testing.assert_allclose(read_extrinsics(path).parent_from_camera[:3, 3], [1, 2, 3])
    path.write_text(path.read_text() + "extra: 1\n")
    with pytest.raises(ConfigError, match="key 'extra': unknown key"):
        read_extrinsics(path)
    path.write_text(path.read_text().replace("extra: 1\n", "").replace("- 0.0\n", "- 2.0\n", 1))
    with pytest.raises(ConfigError, match="unit quaternion"):
        read_extrinsics(path)
