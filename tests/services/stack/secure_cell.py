"""Helpers of the security tests: a cell directory with the example configs, routers and services in it.

Real Zenoh over loopback: `robonav router` processes with the committed router configs,
service processes, in-process client sessions with the committed client configs, all run in
a directory where `gen_certs.sh` wrote fresh certificates (the configs name them relatively).
The example passwords are accepted through `ROBONAV_DEV_STACK=1` (a development stack).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from robonav.services.common import to_zenoh_config
from robonav.services.config import ZenohConfig
from robonav.services.stack.secrets import DEV_STACK_ENV

from ...conftest import REPO_ROOT
from ..conftest import free_port, write_config

SECURITY_DIR = REPO_ROOT / "configs" / "security"
START_TIMEOUT_S = 30.0
DEV_ENV = {DEV_STACK_ENV: "1"}


def make_cell_dir(directory: Path) -> Path:
    """The example configs and credentials beside freshly generated certificates (their relative paths)."""
    for path in SECURITY_DIR.iterdir():
        if path.suffix in (".json5", ".txt"):
            shutil.copy(path, directory / path.name)
    subprocess.run(["bash", str(SECURITY_DIR / "gen_certs.sh"), "certs"], cwd=directory, check=True,
                   capture_output=True)
    return directory


def wait_for_port(port: int, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"router exited with {proc.returncode}"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on port {port}")


@contextlib.contextmanager
def running(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """`robonav CMD` as a process in `cwd` (a development stack unless `env` says otherwise); stopped by its PID."""
    proc = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", *cmd, "--log-level", "WARNING"], cwd=cwd,
                            env={**os.environ, **(DEV_ENV if env is None else env)})
    try:
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def router(cell_dir: Path, zenoh_config: str, env: dict[str, str] | None = None) -> Iterator[int]:
    """`robonav router` with one of the example router configs, listening on a free TLS port."""
    port = free_port()
    config = write_config(cell_dir, f"router-{port}.yaml", zenoh={"connect": [f"tls/localhost:{port}"]})
    with running(["router", "--config", str(config), "--zenoh-config", zenoh_config,
                  "--listen", f"tls/127.0.0.1:{port}"], cell_dir, env) as proc:
        wait_for_port(port, proc)
        yield port


def session(cell_dir: Path, endpoint: str, zenoh_config: str | None, *, connect_timeout_ms: int = 5000) -> zenoh.Session:
    cfg = ZenohConfig(connect=(endpoint,), config_file=zenoh_config)
    with contextlib.chdir(cell_dir):  # the example configs name certificates relative to their directory
        zcfg = to_zenoh_config(cfg)
        zcfg.insert_json5("connect/timeout_ms", str(connect_timeout_ms))
        return zenoh.open(zcfg)


def refused(cell_dir: Path, endpoint: str, zenoh_config: str | None) -> None:
    """Opening a session fails (Zenoh retries a refused handshake until its connect timeout)."""
    with pytest.raises(zenoh.ZError):
        session(cell_dir, endpoint, zenoh_config, connect_timeout_ms=1000)
