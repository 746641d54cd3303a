"""`robonav` command line: serve one service, bring all up, run the demo, or run a tool."""

from __future__ import annotations

import argparse
import hashlib
import importlib
import importlib.metadata
import importlib.util
import os
import sys
from pathlib import Path

SERVICE_MODULES = {
    "sim": "robonav.services.sim.node",
    "perception": "robonav.services.perception.node",
    "planner": "robonav.services.planner.node",
    "executor": "robonav.services.executor.node",
}

COMMANDS: dict[str, tuple[str, str]] = {
    # name: (module whose `main(argv) -> int` runs it, help)
    "up": ("robonav.services.stack.up", "run a Zenoh router and every service until Ctrl-C, restarting any that exits"),
    "status": ("robonav.services.stack.status", "which services are alive, their restarts and uptimes: "
                                                "`robonav status [--json]`"),
    "demo": ("robonav.services.stack.demo", "start everything, plan and execute the demo goals, print a JSON summary"),
    "bench": ("robonav.services.bench.cli", "benchmarks: `robonav bench plan --problems DIR` (MotionBenchMaker), "
                                        "`robonav bench executor`"),
    "robot": ("robonav.services.tools.robot", "robot files: `robonav robot init --urdf U [--srdf S] [--group G] "
                                             "[--tip LINK] [--package-path DIR] --out FILE`"),
    "plot": ("robonav.services.tools.plot", "plots: `robonav plot trajectory --json PATH_FILE -o out.png`"),
    "router": ("robonav.services.stack.router", "a Zenoh router for the services (TLS, authentication, access control "
                                          "from a Zenoh config): `robonav router [--listen tcp/0.0.0.0:7447]`"),
    "plan": ("robonav.services.tools.plan", "plan (and execute) from the shell: `robonav plan --goal Q... [--race] [--execute]`"),
    "stop": ("robonav.services.tools.stop", "stop the arm and wait until it rests: `robonav stop [--emergency]`"),
    "view": ("robonav.services.view.app", "a live 3D view in the browser; `--snapshot out.png` writes a picture"),
    "record": ("robonav.services.recording.record", "record Zenoh traffic into an MCAP file: `robonav record -o run.mcap [KEYEXPR ...]`"),
    "replay": ("robonav.services.recording.replay", "publish a recording back with its timing: `robonav replay run.mcap [--rate R] [--loop]`"),
    "calibrate": ("robonav.calibration.cli", "hand-eye calibration: `robonav calibrate collect --out DIR`, "
                                             "`robonav calibrate solve DIR`"),
    "campaign": ("robonav.services.campaign.run", "safety campaign on random scenes: `robonav campaign --scenes N --seed S "
                                              "[--json FILE]`"),
    "precompile": ("robonav.services.tools.precompile", "compile every numba kernel into the compile cache "
                                                     "(`make setup` and the Docker build run it)"),
    "config": ("robonav.services.tools.config_check", "check a config file (every error, with its line) or print "
                                                     "the effective config: `robonav config check|print [FILE]`"),
    "scene": ("robonav.services.tools.scene", "the planner's collision objects: `robonav scene add|move|remove|attach|"
                                             "detach|list|clear`"),
    "schema": ("robonav.services.tools.schema", "write the JSON Schema of every wire message: `robonav schema --out DIR`"),
}

NUMBA_CACHE_ENV = "NUMBA_CACHE_DIR"
"""Numba's own variable for where compiled kernels are cached; set, it overrides our default."""
KERNEL_TAG_PREFIX = "kernels-"


def default_numba_cache_dir() -> Path:
    """The compile cache when NUMBA_CACHE_DIR is unset: `$XDG_CACHE_HOME/robonav/numba`, else
    `~/.cache/robonav/numba` (the XDG base directory rules)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "robonav" / "numba"


def kernel_sources_tag(root: Path | None = None) -> str:
    """`kernels-` and a digest of every core module that defines numba kernels (their paths and
    contents), the folder of the compile cache that holds their compiled code.

    Numba checks a cached kernel against its own source file only: a kernel calling one of
    another file is loaded with that callee compiled in as it was, after the callee's file changed
    (numba's documented limitation). After an upgrade, a `git pull` or an edit, the services ran
    the old collision check inside the new edge loop until the cache was emptied by hand; under
    this tag they compile afresh whenever any kernel source changed.

    Args:
        root: The folder of the sources (default: the installed `robonav.pipeline`).
    """
    if root is None:
        spec = importlib.util.find_spec("robonav.pipeline")  # its location, without importing it
        if spec is None or not spec.submodule_search_locations:
            raise RuntimeError("robonav.pipeline is not installed")
        root = Path(next(iter(spec.submodule_search_locations)))
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        source = path.read_bytes()
        if b"njit" in source:
            digest.update(path.relative_to(root).as_posix().encode() + b"\0" + source + b"\0")
    return KERNEL_TAG_PREFIX + digest.hexdigest()[:16]


def use_numba_cache_dir() -> Path:
    """Point numba's on-disk cache at `kernel_sources_tag()` in NUMBA_CACHE_DIR, or in
    `default_numba_cache_dir()`; returns it (and leaves it in NUMBA_CACHE_DIR for child processes).

    Numba reads the variable once, when it is first imported, and by default caches next to
    each source file: inside the installed package, which may be read-only (a system install,
    a container) and, in a checkout, mixes build products into the tree. So every process that
    compiles calls this before anything imports numba: the `robonav` entry point, and the tests.
    The folders of other kernel sources are left in place (tens of MB each).

    Raises:
        RuntimeError: numba was imported before (the setting would not take effect).
    """
    if "numba" in sys.modules and not os.environ.get(NUMBA_CACHE_ENV):
        raise RuntimeError("numba was imported before its cache directory was set; call use_numba_cache_dir() first")
    path = Path(os.environ.get(NUMBA_CACHE_ENV) or default_numba_cache_dir()).expanduser()
    tag = kernel_sources_tag()
    if path.name != tag:  # a child process inherits the tagged folder
        path = path / tag
    os.environ[NUMBA_CACHE_ENV] = str(path)
    return path


def main(argv: list[str] | None = None) -> int:
    # Before numpy loads: on a 2-core machine shared by four services, OpenBLAS threads fight
    # each other (a 3 ms matrix product took 80 ms), so each process uses one BLAS thread.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    use_numba_cache_dir()  # before any command imports numba; services started by `up` inherit it
    from robonav.services.table_cache import use_table_cache_dir  # loads numpy: after the BLAS setting

    use_table_cache_dir()  # per-robot tables built once, then read by every process
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="robonav", description="Perception-to-plan pipeline for robot arms over Zenoh.",
                                     epilog="`robonav COMMAND --help` lists a command's own options.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    serve = sub.add_parser("serve", help="run one service: `robonav serve SERVICE [--help]`",
                           description="Run one service until SIGINT/SIGTERM; `robonav serve SERVICE --help` lists its options.")
    serve.add_argument("service", choices=sorted(SERVICE_MODULES))
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    # Only the command (and the service) is ours: everything after it, `--help` included, is the
    # command's own, so each command's parser answers its own `--help`.
    split = _command_end(argv)
    args = parser.parse_args(argv[:split])
    rest = argv[split:]
    if args.command == "serve":
        module = importlib.import_module(SERVICE_MODULES[args.service])
    else:
        module = importlib.import_module(COMMANDS[args.command][0])
    return int(module.main(rest))


def _command_end(argv: list[str]) -> int:
    """Index after `robonav`'s own part of `argv`: its options up to the command, then the
    command, and for `serve` the service name (when it is one)."""
    for i, arg in enumerate(argv):
        if arg.startswith("-"):
            continue
        if arg == "serve":  # without a service name `serve`'s own parser answers (its --help, or the error)
            return i + 2 if i + 1 < len(argv) and argv[i + 1] in SERVICE_MODULES else len(argv)
        return i + 1
    return len(argv)


def package_version() -> str:
    """The installed distribution's version (pyproject.toml's `version`)."""
    try:
        return importlib.metadata.version("robonav-arm")
    except importlib.metadata.PackageNotFoundError:  # run from a tree that was never installed
        return "unknown"


if __name__ == "__main__":
    sys.exit(main())
