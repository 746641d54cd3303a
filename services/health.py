"""Container health check: does this container's service hold its Zenoh liveliness token?

    python -m robonav.services.health [SERVICE] [--config FILE] [--zenoh-config FILE] [--instance NAME]

One image runs every service, so by default the check reads which service runs, and with
which config, from the container's main process (PID 1: `robonav serve <service> ...` or
`robonav router ...`). It then connects like that service and asks for the liveliness token
`robonav/<cell>/alive/<service>/<instance>` (instance: this container's id, else the host name),
so each replica of a scaled service is checked on its own. Exit 0: alive; 1: not alive or
unreachable; 2: bad arguments or config.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path

import zenoh

from robonav.pipeline.config import ConfigError
from robonav.services.common import instance_name, open_session, to_zenoh_config
from robonav.services.config import load_config
from robonav.services.keys import Keys

log = logging.getLogger("robonav.health")


def service_from_cmdline(cmdline: list[str]) -> tuple[str, list[str]] | None:
    """(service, its remaining arguments) from a `robonav serve X ...` or `robonav router ...` command line."""
    for i, word in enumerate(cmdline):
        if word == "serve" and i + 1 < len(cmdline):
            return cmdline[i + 1], cmdline[i + 2:]
        if word == "router":
            return "router", cmdline[i + 1:]
    return None


def _pid1_cmdline() -> list[str]:
    try:
        raw = Path("/proc/1/cmdline").read_bytes()
    except OSError:
        return []
    return [part.decode(errors="replace") for part in raw.split(b"\0") if part]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m robonav.services.health", description=__doc__.splitlines()[0])
    parser.add_argument("service", nargs="?", help="default: the service PID 1 runs")
    parser.add_argument("--config", help="default: the --config of PID 1, else the packaged default")
    parser.add_argument("--zenoh-config", help="default: the --zenoh-config of PID 1")
    parser.add_argument("--instance", help="default: this container's id, else the host name")
    parser.add_argument("--timeout", type=float, default=3.0, help="liveliness query timeout [s]")
    args = parser.parse_args(argv)
    found = service_from_cmdline(_pid1_cmdline())
    if args.service is None and found is None:
        parser.error("no SERVICE given and PID 1 is not `robonav serve <service>` or `robonav router`")
    if found is not None and args.service in (None, found[0]):
        # Options not given here are the service's own (an explicit one wins, e.g. a router's
        # health check logging in with a client's credentials).
        args.service = found[0]
        inherited, _ = _service_options().parse_known_args(found[1])
        args.config = args.config or inherited.config
        args.zenoh_config = args.zenoh_config or inherited.zenoh_config
    return args


def _service_options() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--config")
    parser.add_argument("--zenoh-config")
    return parser


def is_alive(session: zenoh.Session, key: str, timeout_s: float) -> bool:
    return any(reply.ok is not None for reply in session.liveliness().get(key, timeout=timeout_s))


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args = parse_args(argv)
    try:
        cfg = load_config(args.config)
        zcfg = cfg.zenoh
        if args.zenoh_config:
            zcfg = dataclasses.replace(zcfg, config_file=args.zenoh_config)
        if zcfg.mode == "router":  # a router's own config: dial where it listens
            zcfg = dataclasses.replace(zcfg, mode="client", connect=zcfg.listen or zcfg.connect, listen=())
        to_zenoh_config(zcfg)
    except ConfigError as exc:
        log.error("%s", exc)
        return 2
    key = Keys(cfg.cell).alive_instance(args.service, args.instance or instance_name())
    try:
        with open_session(zcfg) as session:
            alive = is_alive(session, key, args.timeout)
    except zenoh.ZError as exc:
        print(f"unhealthy: cannot reach the router at {', '.join(zcfg.connect)}: {exc}", file=sys.stderr)
        return 1
    if not alive:
        print(f"unhealthy: no liveliness token {key}", file=sys.stderr)
        return 1
    print(f"healthy: {key}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
