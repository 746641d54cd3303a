"""`robonav plan` keeps its documented exit codes whatever the planner does: 1 for a structured
error, 3 when no reply of the protocol came (silence, Zenoh's own error, garbage), 2 for a bad
request; `examples/plan_client.py` reads replies by its own copy of the same rule. The planner
here is a bare Zenoh queryable standing in for a slow or broken peer."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import msgpack
import pytest
import yaml
import zenoh

from robonav.pipeline.wire.codes import ErrorCode
from robonav.services.common import open_session
from robonav.services.config import ZenohConfig
from robonav.services.keys import Keys
from robonav.services.tools import plan as plan_cli

from ...conftest import REPO_ROOT
from ..conftest import StandInPeer, free_port, write_config

GOAL = ["0.1", "-0.5", "0.0", "-2.0", "0.0", "1.6", "0.8"]
ANSWERS = {
    "silent": lambda q: None,
    "zenoh_error": lambda q: q.reply_err(b"Timeout"),
    "garbage": lambda q: q.reply(q.key_expr, b"\xc1\xc1"),
    "busy": lambda q: q.reply_err(msgpack.packb({"v": 1, "ok": False, "code": "BUSY", "message": "full", "details": {}})),
    "unknown_code": lambda q: q.reply_err(msgpack.packb({"v": 1, "ok": False, "code": "NEWER", "message": "?", "details": {}})),
}


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[tuple[Path, zenoh.Session, zenoh.Session]]:
    """A config naming a router, a session for the stand-in planner, and one that sees what a client sees."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    service = open_session(ZenohConfig(connect=(endpoint,)))
    observer = open_session(ZenohConfig(connect=(endpoint,)))
    yield write_config(tmp_path, "plan.yaml", zenoh={"connect": [endpoint]}), service, observer
    for s in (observer, service, router):
        s.close()


@pytest.mark.parametrize(("peer_kind", "code", "stage"), [("silent", 3, "no_reply"), ("zenoh_error", 3, "no_reply"),
                                                     ("garbage", 3, "no_reply"), ("busy", 1, "plan"),
                                                     ("unknown_code", 1, "plan"), (None, 3, "no_reply")])
def test_exit_codes_hold_for_every_kind_of_peer(cell: tuple[Path, zenoh.Session, zenoh.Session],
                                                capsys: pytest.CaptureFixture[str], peer_kind: str | None, code: int,
                                                stage: str) -> None:
    config, service, observer = cell
    peer = StandInPeer(service, Keys("arm0").plan, ANSWERS[peer_kind], observer=observer) if peer_kind else None
    assert plan_cli.main(["--goal", *GOAL, "--config", str(config), "--timeout", "1"]) == code
    record = json.loads(capsys.readouterr().out)
    assert record["ok"] is False and record["stage"] == stage, record
    if stage == "no_reply":
        assert record["key"] == Keys("arm0").plan and record["timeout_s"] == 1.0, record
    else:
        assert record["code"] == ("BUSY" if peer_kind == "busy" else "INTERNAL_ERROR"), record
    if peer is not None:
        peer.close()


def test_a_request_the_protocol_refuses_exits_2(cell: tuple[Path, zenoh.Session, zenoh.Session]) -> None:
    config, _, _ = cell
    too_short = ["--start", *GOAL[:6]]  # joint vectors of different lengths: refused before anything is sent
    assert plan_cli.main(["--goal", *GOAL, *too_short, "--config", str(config), "--timeout", "1"]) == plan_cli.EXIT_CONFIG


@pytest.mark.parametrize(("peer", "code", "said"), [("silent", 2, "'Timeout'"), ("zenoh_error", 2, "'Timeout'"),
                                                    ("garbage", 2, "no reply of the protocol"),
                                                    ("unknown_code", 1, "INTERNAL_ERROR: NEWER: ?")])
def test_the_example_client_has_its_own_copy_of_the_rule(cell: tuple[Path, zenoh.Session, zenoh.Session], peer: str,
                                                         code: int, said: str) -> None:
    config, service, observer = cell
    router = yaml.safe_load(config.read_text(encoding="utf-8"))["zenoh"]["connect"][0]
    stand_in = StandInPeer(service, Keys("arm0").plan, ANSWERS[peer], observer=observer)
    run = subprocess.run([sys.executable, str(REPO_ROOT / "examples" / "plan_client.py"), "--router", router,
                          "--goal", *GOAL, "--timeout", "1"], capture_output=True, text=True, timeout=60)
    assert run.returncode == code and said in run.stderr, (run.returncode, run.stderr)
    stand_in.close()


def test_the_example_client_knows_the_documented_codes() -> None:
    docs = (REPO_ROOT / "docs" / "protocol.md").read_text(encoding="utf-8")
    table = docs.split("| code | when |", 1)[1].split("\n\n", 1)[0]
    documented = set(re.findall(r"^\| `([A-Z_]+)` \|", table, flags=re.MULTILINE))
    source = (REPO_ROOT / "examples" / "plan_client.py").read_text(encoding="utf-8")
    known = set(re.findall(r'"([A-Z_]+)"', source.split("KNOWN_CODES = {", 1)[1].split("}", 1)[0]))
    assert known == documented and documented <= {c.value for c in ErrorCode}
