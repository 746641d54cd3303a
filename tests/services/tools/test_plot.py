"""`robonav plot trajectory` from a JSON path and from setpoints recorded in MCAP."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.trajectory.setpoint_table import sample_table
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.wire.messages import Setpoint
from robonav.services.config import load_config
from robonav.services.recording.files import RecordingWriter
from robonav.services.tools import plot

CONFIG = load_config()
ROBOT = RobotModel.from_config(CONFIG.robot)
HOME = ROBOT.home_position_rad
KEY = "robonav/arm0/executor/setpoint"
PERIOD_S = 1e-3


def _record(path: Path, trajectories: dict[str, np.ndarray], *, malformed: bool = True) -> dict[str, np.ndarray]:
    """Record the setpoints the stream would send for each path, one after another; returns the
    positions of each trajectory's table (robot joint order)."""
    writer = RecordingWriter(path)
    names = list(ROBOT.joint_names)
    order = names[::-1]  # the recording names joints in another order than the robot
    tables = {}
    start_s = 1_700_000_000.0
    for trajectory_id, waypoints in trajectories.items():
        timed = time_parameterize(waypoints, max_velocity=ROBOT.velocity_limits, max_acceleration=ROBOT.acceleration_limits,
                                  max_jerk=ROBOT.jerk_limits, velocity_scaling=0.5, acceleration_scaling=0.5)
        table = sample_table(timed, trajectory_id, start_s, PERIOD_S)
        tables[trajectory_id] = table.position
        index = [names.index(n) for n in order]
        for k in range(len(table.position)):
            stamp = start_s + k * PERIOD_S
            setpoint = Setpoint(stamp=stamp, trajectory_id=trajectory_id, names=order, position=table.position[k][index],
                                velocity=table.velocity[k][index], acceleration=table.acceleration[k][index])
            writer.write(KEY, setpoint.to_wire(), receive_time_ns=int(stamp * 1e9), source_time_ns=int(stamp * 1e9))
        start_s += len(table.position) * PERIOD_S + 0.5
    if malformed:
        writer.write(KEY, b"\x93not a setpoint", receive_time_ns=int(start_s * 1e9), source_time_ns=int(start_s * 1e9))
    writer.finish()
    return tables


def _args(**values: object) -> argparse.Namespace:
    return argparse.Namespace(**{"trajectory_id": None, "velocity_scaling": None, "acceleration_scaling": None, **values})


def test_a_recorded_trajectory_is_plotted_at_its_stamps(tmp_path: Path) -> None:
    recording = tmp_path / "run.mcap"
    tables = _record(recording, {"first": np.array([HOME, HOME + 0.3]), "second": np.array([HOME + 0.3, HOME])})
    series = plot._from_recording(_args(recording=recording, trajectory_id="first"), CONFIG, ROBOT)  # noqa: SLF001
    np.testing.assert_array_equal(series.q, tables["first"])
    np.testing.assert_allclose(series.t_s, np.arange(len(tables["first"])) * PERIOD_S, atol=1e-6)
    last = plot._from_recording(_args(recording=recording), CONFIG, ROBOT)  # noqa: SLF001
    np.testing.assert_array_equal(last.q, tables["second"])  # by default the last trajectory streamed
    output = tmp_path / "plot.png"
    assert plot.main(["trajectory", "--recording", str(recording), "-o", str(output)]) == 0
    assert output.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_recording_errors_name_what_is_there(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    recording = tmp_path / "run.mcap"
    _record(recording, {"only": np.array([HOME, HOME + 0.2])})
    assert plot.main(["trajectory", "--recording", str(recording), "--trajectory-id", "other", "-o",
                      str(tmp_path / "x.png")]) == 2
    assert "holds: only" in capsys.readouterr().err
    empty = tmp_path / "empty.mcap"
    _record(empty, {}, malformed=False)
    assert plot.main(["trajectory", "--recording", str(empty), "-o", str(tmp_path / "y.png")]) == 2
    assert "no setpoints" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "y.png").exists()


def test_a_json_path_is_timed_and_plotted(tmp_path: Path) -> None:
    path_file = tmp_path / "path.json"
    path_file.write_text(json.dumps({"path": [HOME.tolist(), (HOME + 0.4).tolist()]}), encoding="utf-8")
    output = tmp_path / "path.png"
    assert plot.main(["trajectory", "--json", str(path_file), "-o", str(output)]) == 0
    assert output.stat().st_size > 10_000
    assert plot.main(["trajectory", "--path-json", '{"path": [[0, 1]]}', "-o", str(tmp_path / "bad.png")]) == 2
