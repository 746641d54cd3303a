"""`robonav config check` reports every error of a file at once, each with its line;
`robonav config print` shows the effective config, which loads back to the same values."""

from __future__ import annotations

from pathlib import Path

import pytest

from robonav.services.config import check_config, default_config_path, load_config
from robonav.services.tools import config_check

from ...conftest import REPO_ROOT

THREE_ERRORS = """\
cell: arm0
executor:
  rate_hz: fast
planner:
  planer_id: rrtconnect
cameras:
  - camera_id: cam0
    width: wide
"""


def test_three_errors_are_reported_at_once_each_with_its_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "three.yaml"
    path.write_text(THREE_ERRORS, encoding="utf-8")
    assert config_check.main(["check", str(path)]) == config_check.EXIT_ERRORS
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3, lines
    assert lines[0] == f"{path}:3: key 'executor.rate_hz': expected float, got str ('fast')"
    assert lines[1].startswith(f"{path}:5: key 'planner.planer_id': unknown key (known keys of PlannerConfig: ")
    assert lines[2] == f"{path}:8: key 'cameras[0].width': expected int, got str ('wide')"


def test_cross_key_checks_of_good_sections_still_run_and_duplicates_are_errors(tmp_path: Path) -> None:
    path = tmp_path / "mixed.yaml"
    path.write_text("planner:\n  workers: 0\nexecutor:\n  rate_hz: 1000.0\n  rate_hz: 500.0\nlimits:\n  max_goals: -1\n"
                    "zenoh:\n  mode: broker\n", encoding="utf-8")
    cfg, issues = check_config(path)
    assert cfg is None
    assert [(i.line, i.key) for i in issues] == [(1, "planner"), (5, "executor.rate_hz"), (6, "limits"), (9, "zenoh.mode")]
    assert "planner.workers must be >= 1" in issues[0].message and "duplicate key" in issues[1].message


def test_a_yaml_syntax_error_names_its_line(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("cell: arm0\nplanner: {workers: 1\nexecutor: {}\n", encoding="utf-8")
    _, issues = check_config(path)
    assert len(issues) == 1 and issues[0].line >= 2 and "invalid YAML" in issues[0].message


@pytest.mark.parametrize("name", ["default.yaml", "iiwa.yaml"])
def test_the_shipped_configs_are_clean(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    path = default_config_path().parent / name
    assert config_check.main(["check", str(path)]) == config_check.EXIT_OK
    assert capsys.readouterr().out == ""


def test_print_shows_every_default_and_loads_back_equal(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    small = tmp_path / "small.yaml"
    small.write_text("planner:\n  workers: 1\n", encoding="utf-8")
    assert config_check.main(["print", str(small)]) == config_check.EXIT_OK
    printed = capsys.readouterr().out
    assert "workers: 1" in printed and "max_request_bytes: 16777216" in printed and "rate_hz:" in printed
    full = tmp_path / "full.yaml"
    full.write_text(printed, encoding="utf-8")
    assert repr(load_config(full)) == repr(load_config(small))
    bad = tmp_path / "bad.yaml"
    bad.write_text("planer: {}\n", encoding="utf-8")
    assert config_check.main(["print", str(bad)]) == config_check.EXIT_BAD_CONFIG
    assert f"{bad}:1: key 'planer': unknown key" in capsys.readouterr().err


def test_a_robot_file_is_checked_as_the_robot_section(tmp_path: Path) -> None:
    shipped = REPO_ROOT / "configs" / "ur5.yaml"
    cfg, issues = check_config(shipped)
    assert issues == [] and cfg is not None and cfg.robot.name == "ur5_robotiq85"
    bad = tmp_path / "robot.yaml"
    text = shipped.read_text(encoding="utf-8").replace("padding_m: 0.01", "padding_m: thick\ngripper: 2")
    bad.write_text(text.replace('"../../shared', f'"{REPO_ROOT.parent / "shared"}'), encoding="utf-8")
    cfg, issues = check_config(bad)
    assert cfg is None
    assert [(issue.key, issue.line) for issue in issues] == [("robot.padding_m", 15), ("robot.gripper", 16)], issues
