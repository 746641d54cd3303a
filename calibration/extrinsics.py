"""The camera extrinsics file hand-eye calibration writes and perception reads.

`configs/calibration/<camera_id>.yaml`:

```yaml
camera_id: cam0
parent_frame: world          # eye-to-hand: the robot base (world) frame; eye-in-hand: the
                             # end-effector link the camera rides on, e.g. panda_hand
position_m: [1.45, 0.55, 1.05]            # camera optical frame origin in parent_frame [m]
quat_xyzw: [-0.444, -0.751, 0.420, 0.249] # optical frame orientation in parent_frame
# informative, ignored when read:
method: refined
reprojection_rms_px: 0.08
```

The optical frame is OpenCV's (z forward, x right, y down), the same as the `cameras[]`
entries of the robonav config, so for a fixed camera `position_m`/`quat_xyzw` are exactly
what `cameras[].position_m`/`cameras[].quat_xyzw` hold: world_from_camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from robonav.calibration.dataset import PoseSpec
from robonav.pipeline.config import ConfigError, from_mapping, require
from robonav.pipeline.transforms import FloatArray

DEFAULT_DIRECTORY = Path("configs") / "calibration"


@dataclass(frozen=True)
class CameraExtrinsics:
    camera_id: str
    parent_frame: str
    """"world" for a fixed camera (world_from_camera), else the link it is mounted on (link_from_camera)."""
    position_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    method: str = ""
    reprojection_rms_px: float | None = None
    calibrated_at: str = ""

    def __post_init__(self) -> None:
        require(bool(self.camera_id), "camera_id must not be empty")
        require(bool(self.parent_frame), "parent_frame must not be empty")
        PoseSpec(self.position_m, self.quat_xyzw)  # validates the quaternion

    @property
    def parent_from_camera(self) -> FloatArray:
        return PoseSpec(self.position_m, self.quat_xyzw).matrix


def default_path(camera_id: str) -> Path:
    return DEFAULT_DIRECTORY / f"{camera_id}.yaml"


def write_extrinsics(path: str | Path, extrinsics: CameraExtrinsics) -> Path:
    file = Path(path)
    file.parent.mkdir(parents=True, exist_ok=True)
    data: dict[str, Any] = {
        "camera_id": extrinsics.camera_id, "parent_frame": extrinsics.parent_frame,
        "position_m": [float(v) for v in extrinsics.position_m], "quat_xyzw": [float(v) for v in extrinsics.quat_xyzw],
        "method": extrinsics.method, "calibrated_at": extrinsics.calibrated_at,
    }
    if extrinsics.reprojection_rms_px is not None:
        data["reprojection_rms_px"] = float(extrinsics.reprojection_rms_px)
    file.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return file


def read_extrinsics(path: str | Path) -> CameraExtrinsics:
    """Read an extrinsics file strictly (unknown keys and wrong types raise ConfigError)."""
    file = Path(path)
    try:
        data = yaml.safe_load(file.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(str(file), "<file>", f"cannot read: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(str(file), "<file>", f"invalid YAML: {exc}") from exc
    return from_mapping(CameraExtrinsics, data, source=str(file))
