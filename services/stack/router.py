"""`robonav router`: a Zenoh router from this package, so a deployment needs no other image.

It is the same Zenoh router `zenohd` runs (the router mode of the Zenoh library), configured
from the robonav YAML: it listens on `--listen` (default `zenoh.listen`, else the first
`zenoh.connect` endpoint, the one the services dial) and reads TLS, authentication and access
control from the Zenoh JSON5 file in `zenoh.config_file` or `--zenoh-config`. It holds the
liveliness tokens `alive/router` and `alive/router/<host>` so health checks can see it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import signal

import zenoh

from robonav.services.common import instance_name, parse_args_and_config, to_zenoh_config
from robonav.services.config import RobonavConfig, ZenohConfig
from robonav.services.keys import Keys
from robonav.services.signals import stop_on_signals

log = logging.getLogger("robonav.router")


def router_zenoh_config(cfg: RobonavConfig, listen: list[str] | None) -> ZenohConfig:
    """The router's Zenoh section: router mode, listening where the services connect unless told otherwise."""
    endpoints = tuple(listen) if listen else (cfg.zenoh.listen or cfg.zenoh.connect[:1])
    return dataclasses.replace(cfg.zenoh, mode="router", listen=endpoints, connect=())


def main(argv: list[str] | None = None) -> int:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--listen", action="append", metavar="ENDPOINT",
                     help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 or tls/0.0.0.0:7447 (repeatable)")
    pre.add_argument("--id", metavar="HEX", help="the router's Zenoh id (as zenohd --id); default: random")
    known, rest = pre.parse_known_args(argv)
    loaded = parse_args_and_config("robonav router", "Run a Zenoh router for the robonav services until Ctrl-C.", rest,
                                   parents=(pre,))
    if loaded is None:
        return 2
    _, cfg = loaded
    zcfg = router_zenoh_config(cfg, known.listen)
    stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
    try:
        native = to_zenoh_config(zcfg)
        if known.id is not None:
            native.insert_json5("id", json.dumps(known.id))
        session = zenoh.open(native)
    except zenoh.ZError as exc:  # e.g. the port is taken or a certificate cannot be read
        log.error("router: cannot start listening on %s: %s", ", ".join(zcfg.listen), exc)
        return 1
    keys = Keys(cfg.cell)
    tokens = [session.liveliness().declare_token(keys.alive("router")),
              session.liveliness().declare_token(keys.alive_instance("router", instance_name()))]
    log.info("router %s listening on %s%s", session.info.zid(), ", ".join(zcfg.listen),
             f" with {zcfg.config_file}" if zcfg.config_file else "")
    try:
        stop.wait()
    finally:
        for token in tokens:
            token.undeclare()
        session.close()
    log.info("router: stopped")
    return 0
