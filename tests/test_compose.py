"""The compose files mount no secret a container does not need (read from the files; `docker/test.sh`
checks the running containers' mounts where an engine runs)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from .conftest import REPO_ROOT

DOCKER = REPO_ROOT / "docker"
SERVICES = ("router", "sim", "perception", "planner", "executor")
CLIENT_OF = {"router": "client-health.json5", "sim": "client-sim.json5", "perception": "client-perception.json5",
             "planner": "client-planner.json5", "executor": "client-executor.json5"}


def _load(name: str) -> dict:
    return yaml.safe_load((DOCKER / name).read_text(encoding="utf-8"))


def _volumes(service: dict) -> list[str]:
    return list(service.get("volumes", []))


def test_the_plain_stack_mounts_the_yaml_alone() -> None:
    compose = _load("compose.yaml")
    assert set(compose["services"]) == set(SERVICES)
    for name, service in compose["services"].items():
        binds = [v for v in _volumes(service) if not v.startswith("numba-cache:")]
        assert binds == ["${ROBONAV_CONFIG_DIR:-../configs}/${ROBONAV_CONFIG:-default.yaml}:/etc/robonav/robonav.yaml:ro"], \
            (name, binds)
        command = service["command"]
        assert command[command.index("--config") + 1] == "/etc/robonav/robonav.yaml"


def test_each_secured_container_mounts_its_own_identity_only() -> None:
    secure = _load("compose.secure.yaml")
    assert set(secure["services"]) == set(SERVICES)
    for name, service in secure["services"].items():
        volumes = _volumes(service)
        assert len(volumes) == 1, (name, volumes)
        source, target, mode = volumes[0].rsplit(":", 2)
        assert source.startswith("${ROBONAV_SECURITY_DIR:?") and source.endswith(f"}}/{name}"), source
        assert (target, mode) == ("/etc/robonav/security", "ro")
        assert service["working_dir"] == target
        words = service["command"] + service.get("healthcheck", {}).get("test", [])
        clients = [w for w in words if w.startswith("client-")]
        assert set(clients) == {CLIENT_OF[name]}, (name, clients)
        assert service["environment"]["ROBONAV_DEV_STACK"] == "${ROBONAV_DEV_STACK:-0}"


def test_setup_cell_writes_what_each_container_mounts(tmp_path: Path) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("setup_cell.sh needs openssl")
    security = tmp_path / "security"
    subprocess.run(["bash", str(REPO_ROOT / "configs" / "security" / "setup_cell.sh"), str(security)], check=True,
                   capture_output=True)
    secure = _load("compose.secure.yaml")
    for name, service in secure["services"].items():
        directory = security / name
        for word in service["command"] + service.get("healthcheck", {}).get("test", []):
            if word.endswith(".json5"):
                assert (directory / word).is_file(), f"{name} runs with {word}, which setup_cell.sh does not write"
        secrets = [p.name for p in directory.rglob("*") if p.suffix == ".key" or p.name == "credentials.txt"
                   or p.name.startswith("client-")]
        expected = {"router": ["client-health.json5", "credentials.txt", "router.key"]}.get(name, [CLIENT_OF[name]])
        assert sorted(secrets) == expected, (name, secrets)
    if shutil.which("docker-compose") is not None:  # the engine's own reading of the files
        (tmp_path / "robonav.yaml").write_text("cell: arm0\n", encoding="utf-8")
        env = dict(os.environ, ROBONAV_CONFIG_DIR=str(tmp_path), ROBONAV_CONFIG="robonav.yaml",
                   ROBONAV_SECURITY_DIR=str(security))
        done = subprocess.run(["docker-compose", "-f", "compose.yaml", "-f", "compose.secure.yaml", "config"], cwd=DOCKER,
                              env=env, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        merged = yaml.safe_load(done.stdout)
        for name, service in merged["services"].items():
            sources = [v.split(":")[0] for v in service["volumes"] if v.startswith("/")]
            assert sources == [str(tmp_path / "robonav.yaml"), str(security / name)], (name, sources)
