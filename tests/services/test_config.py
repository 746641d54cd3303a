"""Config loading: good files load into frozen dataclasses; bad files fail naming file, key and type."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from robonav.pipeline.config import ConfigError
from robonav.services.config import RobonavConfig, default_config_path, load_config, perceived_world_from_camera

HERE = Path(__file__).resolve().parent.parent / "configs"
ERROR_CASES = sorted((HERE / "errors").glob("*.yaml"))


def test_packaged_default_loads_and_is_complete() -> None:
    cfg = load_config()
    assert isinstance(cfg, RobonavConfig)
    assert len(cfg.robot.joint_names) == 7
    assert len(cfg.demo.goals_rad) >= 3
    assert {o.name for o in cfg.sim.objects} >= {"table"}
    assert cfg.zenoh.multicast_scouting is False
    assert default_config_path().name == "default.yaml"


def test_minimal_file_takes_defaults() -> None:
    cfg = load_config(HERE / "good" / "minimal.yaml")
    assert cfg.cell == "arm1"
    assert cfg.planner.seed == 7
    assert cfg.planner.allowed_planning_time_s == RobonavConfig().planner.allowed_planning_time_s


def test_configs_are_frozen() -> None:
    cfg = load_config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.cell = "other"  # type: ignore[misc]


@pytest.mark.parametrize("path", ERROR_CASES, ids=[p.stem for p in ERROR_CASES])
def test_bad_config_names_file_and_key(path: Path) -> None:
    pattern = (path.with_suffix(".error_regex")).read_text(encoding="utf-8").strip()
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    assert re.search(pattern, message), f"{message!r} does not match {pattern!r}"


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.yaml")


def _with_extrinsics_file(tmp_path: Path, extrinsics: dict | None) -> Path:
    data = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    data["cameras"][0]["extrinsics_file"] = "calibration/cam0.yaml"
    if extrinsics is not None:
        (tmp_path / "calibration").mkdir()
        (tmp_path / "calibration" / "cam0.yaml").write_text(yaml.safe_dump(extrinsics), encoding="utf-8")
    path = tmp_path / "robonav.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


GOOD_EXTRINSICS = {"camera_id": "cam0", "parent_frame": "world", "position_m": [1.4, 0.5, 1.0],
                   "quat_xyzw": [0.0, 0.0, 0.0, 1.0]}


def test_a_camera_extrinsics_file_resolves_beside_the_config_and_moves_only_what_perception_sees(tmp_path: Path) -> None:
    camera = load_config(_with_extrinsics_file(tmp_path, GOOD_EXTRINSICS)).cameras[0]
    assert Path(camera.extrinsics_file) == tmp_path / "calibration" / "cam0.yaml"
    np.testing.assert_allclose(perceived_world_from_camera(camera)[:3, 3], [1.4, 0.5, 1.0])
    np.testing.assert_allclose(camera.world_from_camera, load_config().cameras[0].world_from_camera)


@pytest.mark.parametrize(("extrinsics", "pattern"), [
    (None, "does not exist.*robonav calibrate solve"),
    ({**GOOD_EXTRINSICS, "camera_id": "cam7"}, "calibrates camera 'cam7', not 'cam0'"),
    ({**GOOD_EXTRINSICS, "parent_frame": "panda_hand"}, "eye-in-hand"),
    ({**GOOD_EXTRINSICS, "scale": 2.0}, "scale"),
], ids=["missing", "other-camera", "eye-in-hand", "unknown-key"])
def test_a_bad_extrinsics_file_is_a_config_error(tmp_path: Path, extrinsics: dict | None, pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        load_config(_with_extrinsics_file(tmp_path, extrinsics))
