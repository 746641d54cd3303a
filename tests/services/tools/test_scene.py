"""`robonav scene` against a real planner over Zenoh: every shape, attach and detach, the errors."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.wire.messages import JointState
from robonav.services.common import open_session
from robonav.services.config import ZenohConfig, load_config
from robonav.services.keys import Keys
from robonav.services.planner.node import PlannerNode
from robonav.services.tools import scene
from robonav.services.tools.stop import EXIT_CONFIG, EXIT_FAILED, EXIT_NO_REPLY, EXIT_OK

from ..conftest import free_port, write_config

TETRAHEDRON_OBJ = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[Path]:
    """A router, a planner and a joint state stream at home; yields the config file of the cell."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = write_config(tmp_path, "cell.yaml", zenoh={"connect": [endpoint]})
    cfg = load_config(config)
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    node_session = open_session(ZenohConfig(connect=(endpoint,)))
    node = PlannerNode(cfg, node_session)
    robot = open_session(ZenohConfig(connect=(endpoint,)))
    stop = threading.Event()
    state = JointState(stamp=time.time(), names=cfg.robot.joint_names, position=np.array(cfg.robot.home_position_rad),
                       velocity=np.zeros(len(cfg.robot.joint_names))).to_wire()

    def publish() -> None:
        while not stop.wait(0.02):
            robot.put(Keys(cfg.cell).joint_states, state)

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        yield config
    finally:
        stop.set()
        thread.join()
        node.close()
        for s in (robot, node_session, router):
            s.close()


def _run(capsys: pytest.CaptureFixture[str], config: Path, *argv: str) -> tuple[int, str, str]:
    code = scene.main([*argv, "--config", str(config)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_every_shape_attach_detach_remove_and_clear(cell: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mesh = tmp_path / "tetra.obj"
    mesh.write_text(TETRAHEDRON_OBJ, encoding="utf-8")
    adds = [["box", "crate", "--position", "0.6", "0", "0.2", "--size", "0.1", "0.2", "0.3"],
            ["sphere", "ball", "--position", "0.6", "0.4", "0.2", "--radius", "0.05"],
            ["cylinder", "can", "--position", "0.6", "-0.4", "0.2", "--radius", "0.04", "--length", "0.12",
             "--quat", "0", "0", "0.7071068", "0.7071068"],
            ["mesh", "tetra", "--position", "-0.5", "0", "0.1", "--mesh", str(mesh), "--scale", "2"]]
    for add in adds:
        code, out, err = _run(capsys, cell, "add", *add)
        assert code == EXIT_OK, err
    code, out, _ = _run(capsys, cell, "list", "--json")
    listed = json.loads(out)
    objects = {o["name"]: o for o in listed["objects"]}
    assert code == EXIT_OK and listed["revision"] == 4 and listed["planners"] == 1
    assert objects["crate"]["size_m"] == [0.1, 0.2, 0.3] and objects["ball"]["radius_m"] == 0.05
    assert objects["can"]["length_m"] == 0.12 and objects["tetra"]["vertex_count"] == 4
    # A tool held in the hand: new and posed in the link's frame; then the crate, where it is.
    code, _, err = _run(capsys, cell, "add", "box", "tool", "--position", "0", "0", "0.1", "--size", "0.02", "0.02", "0.1",
                        "--attach", "panda_hand", "--frame", "panda_hand", "--touch-links", "panda_leftfinger",
                        "panda_rightfinger")
    assert code == EXIT_OK, err
    code, _, err = _run(capsys, cell, "attach", "crate", "--link", "panda_hand")
    assert code == EXIT_OK, err
    code, out, _ = _run(capsys, cell, "list")
    assert "attached to panda_hand" in out and "tool" in out and "revision 6" in out, out
    code, out, err = _run(capsys, cell, "detach", "crate", "--json")
    assert code == EXIT_OK, err
    crate = next(o for o in json.loads(out)["objects"] if o["name"] == "crate")
    assert "attached_link" not in crate and crate["frame_id"] == "world"
    np.testing.assert_allclose(crate["position_m"], [0.6, 0.0, 0.2], atol=1e-6)  # back where it was taken
    code, out, _ = _run(capsys, cell, "move", "ball", "--position", "0.5", "0.5", "0.5", "--json")
    assert code == EXIT_OK and next(o for o in json.loads(out)["objects"] if o["name"] == "ball")["position_m"] == [0.5] * 3
    code, out, _ = _run(capsys, cell, "remove", "ball", "tool", "--json")
    assert code == EXIT_OK and {o["name"] for o in json.loads(out)["objects"]} == {"crate", "can", "tetra"}
    code, out, _ = _run(capsys, cell, "clear", "--json")
    assert code == EXIT_OK and json.loads(out)["objects"] == []


def test_errors_bad_requests_and_a_silent_cell(cell: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, cell, "remove", "ghost")
    assert code == EXIT_FAILED and "INVALID_REQUEST" in err and "ghost" in err
    code, _, err = _run(capsys, cell, "add", "box", "b", "--position", "0", "0", "0")
    assert code == EXIT_CONFIG and "--size" in err
    code, _, err = _run(capsys, cell, "add", "mesh", "m", "--position", "0", "0", "0", "--mesh", str(tmp_path / "none.stl"))
    assert code == EXIT_CONFIG and "no triangle mesh" in err
    # A router with no planner behind it: no reply, exit 3, within the timeout.
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    empty = write_config(tmp_path, "empty.yaml", zenoh={"connect": [endpoint]})
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))):
        started = time.monotonic()
        code, _, err = _run(capsys, empty, "list", "--timeout", "1")
        assert code == EXIT_NO_REPLY and ("no planner answered" in err or "no reply" in err), err
        assert time.monotonic() - started < 5.0


def test_a_router_that_is_not_there_is_exit_3(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = write_config(tmp_path, "nobody.yaml", zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]})
    code, _, err = _run(capsys, config, "list", "--timeout", "1")
    assert code == EXIT_NO_REPLY and "cannot reach the router" in err
