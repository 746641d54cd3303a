"""TLS, mutual TLS, user/password and access control with the example configs in configs/security.

Real Zenoh over loopback: `robonav router` processes with the committed router configs, a real
executor process logged in as `executor`, and in-process client sessions with the committed
client configs, all run in a directory where `gen_certs.sh` wrote fresh certificates.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import ErrorReply, ExecutorStatus, StopResponse
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.config import load_config
from robonav.services.stack.roles import forged_delivered, logins, probe_roles
from robonav.services.stack.secrets import DEV_STACK_ENV, EXAMPLE_PASSWORD

from ..conftest import free_port, write_config
from .secure_cell import SECURITY_DIR, START_TIMEOUT_S, make_cell_dir, refused, router, running, session

REQUEST_LIMIT_BYTES = 64 * 1024

pytestmark = [pytest.mark.e2e, pytest.mark.skipif(shutil.which("openssl") is None, reason="gen_certs.sh needs the openssl command")]


@pytest.fixture(scope="module")
def cell_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_cell_dir(tmp_path_factory.mktemp("security"))


def round_trip(server: zenoh.Session, client: zenoh.Session) -> list[bytes]:
    queryable = server.declare_queryable("robonav/test/echo", lambda q: q.reply(q.key_expr, q.payload.to_bytes()))
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:  # the declaration reaches the router asynchronously
            replies = [r.ok.payload.to_bytes() for r in client.get("robonav/test/echo", payload=b"ping", timeout=1.0)
                       if r.ok is not None]
            if replies:
                return replies
            time.sleep(0.05)
        return []
    finally:
        queryable.undeclare()


def test_tls_session_works_and_plain_tcp_is_refused(cell_dir: Path) -> None:
    with router(cell_dir, "router-tls.json5") as port:
        endpoint = f"tls/localhost:{port}"
        with session(cell_dir, endpoint, "client-tls.json5") as a, session(cell_dir, endpoint, "client-tls.json5") as b:
            assert round_trip(a, b) == [b"ping"]
        refused(cell_dir, f"tcp/127.0.0.1:{port}", None)
        refused(cell_dir, endpoint, None)  # TLS without trusting the cell CA: the router's certificate is refused


def test_mutual_tls_needs_a_client_certificate(cell_dir: Path) -> None:
    with router(cell_dir, "router-mtls.json5") as port:
        endpoint = f"tls/localhost:{port}"
        refused(cell_dir, endpoint, "client-tls.json5")
        with session(cell_dir, endpoint, "client-mtls.json5") as a, session(cell_dir, endpoint, "client-mtls.json5") as b:
            assert round_trip(a, b) == [b"ping"]


def test_a_wrong_password_is_refused(cell_dir: Path) -> None:
    text = (cell_dir / "client-viewer.json5").read_text(encoding="utf-8")
    assert "example-viewer-password" in text
    (cell_dir / "client-intruder.json5").write_text(text.replace("example-viewer-password", "guessed"), encoding="utf-8")
    with router(cell_dir, "router-acl.json5") as port:
        refused(cell_dir, f"tls/localhost:{port}", "client-intruder.json5")
        refused(cell_dir, f"tls/localhost:{port}", "client-tls.json5")  # TLS but no credentials
        session(cell_dir, f"tls/localhost:{port}", "client-viewer.json5").close()


@pytest.fixture(scope="module")
def acl_cell(cell_dir: Path) -> Iterator[str]:
    """The access-controlled router and a real executor logged in as `executor`; yields the endpoint."""
    with router(cell_dir, "router-acl.json5") as port:
        endpoint = f"tls/localhost:{port}"
        config = write_config(cell_dir, "executor.yaml", zenoh={"connect": [endpoint]},
                              limits={"max_request_bytes": REQUEST_LIMIT_BYTES})
        assert load_config(config).limits.max_request_bytes == REQUEST_LIMIT_BYTES
        with running(["serve", "executor", "--config", str(config), "--zenoh-config", "client-executor.json5"], cell_dir):
            yield endpoint


@pytest.fixture
def operator(cell_dir: Path, acl_cell: str) -> Iterator[RobonavClient]:
    with session(cell_dir, acl_cell, "client-operator.json5") as s:
        client = RobonavClient(s)
        assert not client.wait_for_services(["executor"], START_TIMEOUT_S), "executor not alive"
        yield client
        client.close()


def test_only_the_executor_client_may_command_the_executor(cell_dir: Path, acl_cell: str,
                                                          operator: RobonavClient) -> None:
    assert isinstance(operator.stop(timeout_s=5.0), StopResponse)
    path = np.zeros((2, 7))
    answer = operator.execute(path, timeout_s=5.0)  # reaches the executor, which has no joint state to start from
    assert isinstance(answer, ErrorReply) and answer.code == ErrorCode.NO_JOINT_STATE.value

    with session(cell_dir, acl_cell, "client-viewer.json5") as s:
        viewer = RobonavClient(s)
        try:
            # The viewer may watch the executor: its status stream gets through.
            assert viewer.wait_for(lambda: isinstance(viewer.status, ExecutorStatus), 5.0)
            assert "executor" in viewer.alive_services()
            # But what it sends to executor/* is dropped by the router, and the call says so.
            with pytest.raises(QueryFailed, match="access control denied"):
                viewer.execute(path, timeout_s=2.0)
            with pytest.raises(QueryFailed, match="robonav/arm0/executor/stop: no reply"):
                viewer.stop(timeout_s=2.0)
        finally:
            viewer.close()


def test_an_oversized_request_is_refused_with_a_structured_error(operator: RobonavClient) -> None:
    path = np.zeros((2000, 7))  # 112 000 bytes of waypoints, over the configured 64 KiB
    answer = operator.execute(path, timeout_s=5.0)
    assert isinstance(answer, ErrorReply), answer
    assert answer.code == ErrorCode.PAYLOAD_TOO_LARGE.value
    assert answer.details["limit_bytes"] == REQUEST_LIMIT_BYTES
    assert answer.details["size_bytes"] > REQUEST_LIMIT_BYTES
    # The executor keeps serving: a small request right after is decoded and answered as usual.
    small = operator.execute(np.zeros((2, 7)), timeout_s=5.0)
    assert isinstance(small, ErrorReply) and small.code == ErrorCode.NO_JOINT_STATE.value


def test_an_unusable_zenoh_config_is_a_config_error(cell_dir: Path) -> None:
    (cell_dir / "broken.json5").write_text("{ transport: { link: { tls: 7 } } }", encoding="utf-8")
    for name in ("missing.json5", "broken.json5"):
        done = subprocess.run([sys.executable, "-m", "robonav.services.cli", "router", "--zenoh-config", name,
                               "--listen", f"tcp/127.0.0.1:{free_port()}"], cwd=cell_dir, capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 2, done.stderr
        assert f"{name}: key '<file>': not a usable Zenoh config" in done.stderr


def test_example_passwords_are_refused_outside_a_development_stack(cell_dir: Path) -> None:
    port = free_port()
    config = write_config(cell_dir, "refuse.yaml", zenoh={"connect": [f"tls/localhost:{port}"]})
    env = {k: v for k, v in os.environ.items() if k != DEV_STACK_ENV}
    for cmd in (["router", "--listen", f"tls/127.0.0.1:{port}", "--zenoh-config", "router-acl.json5"],
                ["serve", "planner", "--zenoh-config", "client-planner.json5"]):
        done = subprocess.run([sys.executable, "-m", "robonav.services.cli", *cmd, "--config", str(config)],
                              cwd=cell_dir, env=env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 2, done.stderr
        assert "example password" in done.stderr and DEV_STACK_ENV in done.stderr


def test_setup_cell_gives_each_identity_its_own_secrets(tmp_path: Path) -> None:
    secrets = tmp_path / "security"
    subprocess.run(["bash", str(SECURITY_DIR / "setup_cell.sh"), str(secrets)], check=True, capture_output=True)
    passwords = dict(line.split(":", 1) for line in (secrets / "router" / "credentials.txt").read_text().splitlines())
    assert set(passwords) == {"sim", "perception", "planner", "executor", "operator", "viewer", "health"}
    assert all(len(p) == 32 and not EXAMPLE_PASSWORD.match(p) for p in passwords.values())
    # Each identity's directory holds its own password and the CA certificate, nothing else secret;
    # only ca/ holds the CA's key.
    for directory in [d for d in secrets.iterdir() if d.name not in ("ca", "router")]:
        files = sorted(str(p.relative_to(directory)) for p in directory.rglob("*") if p.is_file())
        assert files == ["certs/ca.pem", f"client-{directory.name}.json5"], files
        text = (directory / f"client-{directory.name}.json5").read_text()
        assert [user for user, p in passwords.items() if p in text] == [directory.name]
    assert [p.relative_to(secrets) for p in secrets.rglob("ca.key")] == [Path("ca/ca.key")]
    # The cell starts without the development flag, and its identities log in.
    env = {k: v for k, v in os.environ.items() if k != DEV_STACK_ENV}
    with router(secrets / "router", "router-acl.json5", env) as port:
        endpoint = f"tls/localhost:{port}"
        with session(secrets / "sim", endpoint, "client-sim.json5") as a, \
                session(secrets / "viewer", endpoint, "client-viewer.json5") as b:
            assert a.info.zid() != b.info.zid()
        shutil.copy(SECURITY_DIR / "client-viewer.json5", secrets / "viewer" / "client-example.json5")
        refused(secrets / "viewer", endpoint, "client-example.json5")  # the example password is not the cell's
        # Its identities keep to their roles (the cell's own passwords, one directory each).
        assert forged_delivered(probe_roles(logins(secrets, endpoint))) == 0
