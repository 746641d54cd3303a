"""A hand-eye dataset folder: `dataset.yaml` plus the images it names.

`robonav calibrate collect` writes one from the sim; a real rig writes the same folder (its
controller's end-effector poses, its camera's intrinsics, no ground truth). Format
`robonav-handeye/1`:

```yaml
format: robonav-handeye/1
setup: eye_to_hand            # board on the end effector, camera fixed in the world;
                              # eye_in_hand: camera on the end effector, board fixed
camera_id: cam0
end_effector_link: panda_hand
joint_names: [panda_joint1, ...]
intrinsics: {width: 1280, height: 960, fx: 866.1, fy: 866.1, cx: 639.5, cy: 479.5, distortion: []}
board: {squares_x: 7, squares_y: 5, square_length_m: 0.05, marker_length_m: 0.0375, dictionary: DICT_5X5_100}
views:
  - image: images/view_000.png            # relative to the folder
    joint_positions: [0.1, ...]           # optional when base_from_ee is given
    base_from_ee: {position_m: [x, y, z], quat_xyzw: [x, y, z, w]}   # optional: FK of joint_positions
ground_truth:                             # optional (the sim writes it)
  world_from_camera: {...}                # eye_to_hand: with ee_from_board
  ee_from_board: {...}                    # eye_in_hand: ee_from_camera and world_from_board
source: {kind: sim, seed: 0}
```

Pixel centers are at integer (u, v); `distortion` is OpenCV's (k1, k2, p1, p2[, k3...]), empty
for none. The world frame is the robot base frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from robonav.calibration.board import BoardSpec
from robonav.pipeline.config import ConfigError, from_mapping, require
from robonav.pipeline.transforms import PoseSpec
from robonav.pipeline.types import FloatArray

DATASET_FORMAT = "robonav-handeye/1"
DATASET_FILE = "dataset.yaml"
Setup = Literal["eye_to_hand", "eye_in_hand"]


@dataclass(frozen=True)
class IntrinsicsSpec:
    """Pinhole intrinsics [px] of the images, pixel centers at integers, plus OpenCV distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        require(self.width > 0 and self.height > 0, f"intrinsics width/height must be > 0, got {self.width}x{self.height}")
        require(self.fx > 0 and self.fy > 0, f"intrinsics fx/fy must be > 0, got {self.fx}, {self.fy}")
        require(len(self.distortion) in (0, 4, 5, 8, 12, 14),
                f"intrinsics.distortion must have 0, 4, 5, 8, 12 or 14 OpenCV coefficients, got {len(self.distortion)}")

    @property
    def camera_matrix(self) -> FloatArray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> FloatArray:
        return np.asarray(self.distortion or (0.0, 0.0, 0.0, 0.0), dtype=np.float64)


@dataclass(frozen=True)
class ViewSpec:
    image: str
    """Image file, relative to the dataset folder."""
    joint_positions: tuple[float, ...] = ()
    """Planning joints [rad], in `joint_names` order."""
    base_from_ee: PoseSpec | None = None
    """End-effector pose in the robot base (world) frame; computed from `joint_positions` when absent."""


@dataclass(frozen=True)
class GroundTruth:
    world_from_camera: PoseSpec | None = None
    ee_from_board: PoseSpec | None = None
    ee_from_camera: PoseSpec | None = None
    world_from_board: PoseSpec | None = None


@dataclass(frozen=True)
class Dataset:
    format: str
    setup: Setup
    camera_id: str
    intrinsics: IntrinsicsSpec
    board: BoardSpec
    views: tuple[ViewSpec, ...]
    end_effector_link: str = "panda_hand"
    joint_names: tuple[str, ...] = ()
    ground_truth: GroundTruth | None = None
    source: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        require(self.format == DATASET_FORMAT, f"format must be {DATASET_FORMAT!r}, got {self.format!r}")
        for i, view in enumerate(self.views):
            require(view.base_from_ee is not None or len(view.joint_positions) > 0,
                    f"views[{i}] needs base_from_ee or joint_positions")
            require(not view.joint_positions or len(view.joint_positions) == len(self.joint_names),
                    f"views[{i}].joint_positions has {len(view.joint_positions)} values but joint_names names "
                    f"{len(self.joint_names)} joints")


def load_dataset(folder: str | Path) -> Dataset:
    """Read `<folder>/dataset.yaml` strictly.

    Raises:
        ConfigError: missing or unreadable file, bad YAML, unknown key or wrong type (names
            the file and the key).
    """
    path = Path(folder) / DATASET_FILE
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(str(path), "<file>", f"cannot read: {exc.strerror or exc} (is {folder} a dataset folder "
                          f"written by `robonav calibrate collect`?)") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), "<file>", f"invalid YAML: {exc}") from exc
    return from_mapping(Dataset, data, source=str(path))


def save_dataset(folder: str | Path, dataset: Dataset) -> Path:
    """Write `<folder>/dataset.yaml` (the images are the caller's)."""
    path = Path(folder) / DATASET_FILE
    path.write_text(yaml.safe_dump(_plain(dataset), sort_keys=False, width=120), encoding="utf-8")
    return path


def _plain(value: Any) -> Any:
    """Dataclasses and tuples as YAML-safe maps and lists; None-valued keys left out."""
    if hasattr(value, "__dataclass_fields__"):
        return {k: _plain(getattr(value, k)) for k in value.__dataclass_fields__ if getattr(value, k) is not None}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value
