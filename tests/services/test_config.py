"""Config loading: good files load into frozen dataclasses; bad files fail naming file, key and type."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from robonav.pipeline.config import ConfigError
from robonav.services.config import RobonavConfig, default_config_path, load_config

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
