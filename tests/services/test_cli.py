"""`robonav` follows the conventions operators expect: `--version`, a `--help` on every command
and subcommand that exits 0 and lists every option the command takes, `--log-level` with
choices, `--log-format json`."""

from __future__ import annotations

import json
import logging
import re
import subprocess
import sys
from pathlib import Path

import pytest

from robonav.services import cli
from robonav.services.common import JsonLogFormatter, setup_logging

SERVICES_ROOT = Path(cli.__file__).parent
CHOICES = re.compile(r"(?:^|\s)\{([\w,-]+)\}")
SUBCOMMAND_LINE = re.compile(r"^    ([a-z][\w-]*)(?=\s|$)", re.M)
OPTION_IN_SOURCE = re.compile(r"add_argument\(\s*\"(--[\w-]+)\"")
EXTRA_PATHS = [["view", "bench"]]
"""Subcommands a command dispatches itself, which its usage line does not show."""
EXPECTED_OPTIONS = {
    # What the issue named, and the options every service and client shares.
    ("up",): ["--view", "--view-port", "--config", "--zenoh-config", "--log-level", "--log-format"],
    ("router",): ["--listen", "--id", "--config", "--zenoh-config", "--log-level", "--log-format"],
    ("status",): ["--json", "--timeout", "--config", "--zenoh-config", "--log-level", "--log-format"],
    ("serve", "planner"): ["--scene-file", "--config", "--zenoh-config", "--log-level", "--log-format"],
    ("serve", "sim"): ["--config", "--zenoh-config", "--log-level", "--log-format"],
    ("stop",): ["--emergency", "--timeout", "--config", "--zenoh-config"],
    ("config", "check"): [],
    ("config", "print"): [],
    ("scene", "add"): ["--position", "--quat", "--size", "--radius", "--length", "--mesh", "--attach", "--touch-links"],
    ("scene", "attach"): ["--link", "--touch-links"],
    ("schema",): ["--out", "--check"],
}


def _help(path: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exit_info:
        cli.main([*path, "--help"])
    out = capsys.readouterr().out
    assert exit_info.value.code in (0, None), f"robonav {' '.join(path)} --help exited {exit_info.value.code}"
    assert out.startswith("usage: robonav"), out
    return out


def _walk(capsys: pytest.CaptureFixture[str]) -> dict[tuple[str, ...], str]:
    """Every command and subcommand's help, found from the usage lines (positional choices)."""
    helps: dict[tuple[str, ...], str] = {}
    todo: list[list[str]] = [[], *EXTRA_PATHS]
    while todo:
        path = todo.pop()
        if tuple(path) in helps:
            continue
        text = _help(path, capsys)
        if not text.startswith(" ".join(["usage: robonav", *path]) + " "):
            continue  # a positional choice that is no subcommand (`scene add box`): its parent's help again
        helps[tuple(path)] = text
        assert len(helps) < 200, "the walk over subcommands does not end"
        usage = text.split("\n\n")[0]
        for match in CHOICES.finditer(usage):
            todo += [[*path, choice] for choice in match.group(1).split(",")]
        # Subcommands under a metavar (`COMMAND`, `OPERATION`) are listed one per line, indented by 4.
        positional = text.partition("positional arguments:\n")[2].split("\n\n")[0]
        todo += [[*path, name] for name in SUBCOMMAND_LINE.findall(positional)]
    return helps


def test_every_command_has_a_help_that_exits_0_and_lists_every_option(capsys: pytest.CaptureFixture[str]) -> None:
    helps = _walk(capsys)
    commands = {path[0] for path in helps if path}
    assert commands == {"serve", *cli.COMMANDS}, commands
    assert all(re.search(rf"^    {name}\b", helps[()], re.M) for name in commands), helps[()]
    assert {p[1] for p in helps if p[:1] == ("serve",) and len(p) == 2} == set(cli.SERVICE_MODULES)
    for path, options in EXPECTED_OPTIONS.items():
        missing = [o for o in options if o not in helps[path]]
        assert not missing, f"robonav {' '.join(path)} --help does not list {missing}"
    # Whatever a command's own module declares, its help (or a subcommand's) lists: options parsed
    # before the main parser (a pre-parser) once went missing from `--help`.
    modules = {name: module for name, (module, _) in cli.COMMANDS.items()}
    modules.update({f"serve {name}": module for name, module in cli.SERVICE_MODULES.items()})
    for command, module in modules.items():
        source = Path(SERVICES_ROOT.parent, *module.split(".")[1:]).with_suffix(".py")
        if not source.is_file():  # robonav.calibration lives beside services
            source = SERVICES_ROOT.parent.parent / module.split(".")[1] / Path(*module.split(".")[2:]).with_suffix(".py")
        path = tuple(command.split())
        text = "\n".join(h for p, h in helps.items() if p[:len(path)] == path)
        declared = set(OPTION_IN_SOURCE.findall(source.read_text(encoding="utf-8")))
        missing = sorted(o for o in declared if not re.search(rf"{re.escape(o)}\b", text))
        assert not missing, f"robonav {command}: {source.name} declares {missing}, its --help does not list them"


def test_version_and_log_level_choices(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--version"])
    assert exit_info.value.code == 0
    assert re.fullmatch(r"robonav \d+\.\d+\.\d+\S*\n", capsys.readouterr().out)
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["status", "--log-level", "LOUD"])
    assert exit_info.value.code == 2
    assert "invalid choice: 'LOUD'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="log level"):
        setup_logging("LOUD")


def test_json_log_lines_are_one_object_each() -> None:
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        record = logging.LogRecord("robonav.test", logging.ERROR, __file__, 1, "failed: %s\nsecond line", ("x",),
                                   sys.exc_info())
    line = JsonLogFormatter().format(record)
    assert "\n" not in line
    entry = json.loads(line)
    assert entry["level"] == "ERROR" and entry["logger"] == "robonav.test"
    assert entry["message"] == "failed: x\nsecond line" and "RuntimeError: boom" in entry["exc"]
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", entry["ts"])


def test_a_command_logs_json_when_asked(tmp_path: Path) -> None:
    # A config error is logged by the command's logger: one JSON object per line on stderr.
    bad = tmp_path / "bad.yaml"
    bad.write_text("planer: {}\n", encoding="utf-8")
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "status", "--config", str(bad),
                          "--log-format", "json"], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    lines = [json.loads(line) for line in run.stderr.splitlines() if line.strip()]
    assert lines and all(e["level"] == "ERROR" for e in lines), run.stderr
    assert "unknown key" in lines[0]["message"]


def test_the_compile_cache_folder_follows_every_kernel_source(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Numba checks a cached kernel against its own file only: a kernel calling one of another file
    # would keep the old callee compiled in. Any kernel source changed, the folder changes.
    (tmp_path / "maps").mkdir()
    callee, caller, plain = tmp_path / "maps" / "callee.py", tmp_path / "caller.py", tmp_path / "plain.py"
    callee.write_text("@nb.njit\ndef f(x):\n    return x\n")
    caller.write_text("@nb.njit\ndef g(x):\n    return f(x)\n")
    plain.write_text("def h(x):\n    return x\n")
    tag = cli.kernel_sources_tag(tmp_path)
    assert tag.startswith(cli.KERNEL_TAG_PREFIX) and tag == cli.kernel_sources_tag(tmp_path)
    plain.write_text("def h(x):\n    return x + 1\n")
    assert cli.kernel_sources_tag(tmp_path) == tag  # no kernel in it
    callee.write_text("@nb.njit\ndef f(x):\n    return x + 1\n")
    changed = cli.kernel_sources_tag(tmp_path)
    assert changed != tag
    callee.rename(tmp_path / "callee.py")
    assert cli.kernel_sources_tag(tmp_path) not in (tag, changed)  # moved: another module
    # The installed sources' folder, under NUMBA_CACHE_DIR; a child process inherits it as it is.
    monkeypatch.setenv(cli.NUMBA_CACHE_ENV, str(tmp_path / "cache"))
    folder = cli.use_numba_cache_dir()
    assert folder == tmp_path / "cache" / cli.kernel_sources_tag()
    assert cli.use_numba_cache_dir() == folder
