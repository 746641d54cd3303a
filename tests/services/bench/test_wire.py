"""`robonav bench wire`: every measured message survives its own round trip, and the report says so."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from robonav.services.bench.wire import measure, sample_messages
from robonav.services.cli import main as cli_main


def test_each_sample_message_decodes_to_itself() -> None:
    for name, message in sample_messages(joints=6, points=50, seed=3).items():
        decoded = type(message).from_wire(message.to_wire())
        for f in dataclasses.fields(message):
            sent, got = getattr(message, f.name), getattr(decoded, f.name)
            if isinstance(sent, np.ndarray):
                assert np.array_equal(sent, got), (name, f.name)
            else:
                assert sent == got, (name, f.name)


def test_the_samples_are_drawn_from_the_seed() -> None:
    first, again, other = (sample_messages(joints=7, points=10, seed=s)["Setpoint"] for s in (1, 1, 2))
    assert np.array_equal(first.position, again.position) and not np.array_equal(first.position, other.position)


def test_measure_times_both_directions_of_every_message() -> None:
    rows = measure(sample_messages(joints=7, points=100, seed=0), calls=20, batches=2)
    assert [r["message"] for r in rows] == ["Setpoint", "JointState", "ExecutorStatus", "PointCloud"]
    for row in rows:
        assert row["bytes"] > 0 and 0 < row["encode_us_median"] <= row["encode_us_max"]
        assert 0 < row["decode_us_median"] <= row["decode_us_max"]
    assert rows[-1]["calls"] == 2  # clouds: a tenth of the calls


def test_the_command_prints_the_table_and_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "wire.json"
    assert cli_main(["bench", "wire", "--calls", "10", "--batches", "1", "--points", "10", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert table.splitlines()[0].split()[:3] == ["message", "bytes", "encode"] and "Setpoint" in table
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["config"]["calls"] == 10 and len(report["messages"]) == 4


@pytest.mark.parametrize("flag", ["--calls", "--batches", "--joints", "--points"])
def test_a_count_below_one_is_refused(flag: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bench", "wire", flag, "0"]) == 2
    assert f"{flag} must be > 0, got 0" in capsys.readouterr().err
