"""`robonav bench faults`, short: the live stack through one SIGKILL of each service and of the
router mid-motion, unsafe commands, and 1,000 mutated payloads. The timings are the benchmark's
to report; this checks what must hold however busy the machine is."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robonav.services.bench.faults.run import KILLABLE
from robonav.services.cli import main as cli_main

pytestmark = pytest.mark.e2e


def test_the_stack_comes_out_of_kills_unsafe_commands_and_fuzz(tmp_path: Path) -> None:
    out = tmp_path / "faults.json"
    cli_main(["bench", "faults", "--seed", "2", "--sections", "kill,safety,fuzz", "--fuzz", "1000",
              "--json", str(out), "--logs", str(tmp_path / "logs")])
    report = json.loads(out.read_text(encoding="utf-8"))
    assert "error" not in report, report["error"]
    for name in KILLABLE:
        kill = report["kill"][name]
        assert "error" not in kill, (name, kill)
        assert kill["killed_mid_motion"], (name, kill)
        assert kill["restarted_s"] is not None, (name, kill)  # back within the section's 60 s
        assert kill["contacts"] == 0, (name, kill)
        assert kill["next_goal_reached"], (name, kill)
    assert report["kill"]["executor"]["arm_at_rest_s"] is not None  # the sim braked the arm on its own
    safety = report["safety"]
    assert "error" not in safety, safety
    assert safety["unsafe_execute_tried"] > 0 and safety["unsafe_execute_refused"] == safety["unsafe_execute_tried"]
    assert safety["contacts"] == 0 and safety["bad_setpoints_followed"] == 0
    assert safety["forged_delivered"] in (0, None)
    fuzz = report["fuzz"]
    assert "error" not in fuzz, fuzz
    assert fuzz["sent"] == 1000
    assert (fuzz["crashes"], fuzz["unstructured"], fuzz["no_reply"]) == (0, 0, 0), fuzz
    assert fuzz["alive_after"]
