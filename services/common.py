"""What every service shares: the Zenoh session, signal handling, structured query replies."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import re
import signal
import socket
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import zenoh
import zenoh.ext

from robonav.pipeline.config import ConfigError
from robonav.pipeline.wire.codec import SCHEMA_VERSION, Message, ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import ErrorReply
from robonav.services.config import LimitsConfig, RobonavConfig, ZenohConfig, load_config
from robonav.services.keys import Keys
from robonav.services.signals import stop_on_signals
from robonav.services.stack.secrets import check_example_passwords

log = logging.getLogger("robonav")
M = TypeVar("M", bound=Message)

RECONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}
"""How often a client retries its router after losing it. Zenoh's default backs off to 4 s, so a
router that came back after a long outage was found up to 4 s late; one TCP connect a second to
the router's address costs nothing."""
ROUTER_WAIT_ATTEMPT_S = 1.0
"""A service waiting for its router tries to connect for this long at a time, then checks for a stop."""


def to_zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    """Translate our strict Zenoh section into a `zenoh.Config`, over its `config_file` if any.

    Raises:
        ConfigError: the Zenoh config file is missing or not a valid Zenoh config.
    """
    if cfg.config_file is None:
        zcfg = zenoh.Config()
    else:
        try:
            zcfg = zenoh.Config.from_file(cfg.config_file)
        except zenoh.ZError as exc:
            raise ConfigError(cfg.config_file, "<file>", f"not a usable Zenoh config: {exc}") from exc
    zcfg.insert_json5("mode", json.dumps(cfg.mode))
    zcfg.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    # Latched topics (zenoh-ext advanced publishers with a cache) need timestamped samples.
    zcfg.insert_json5("timestamping/enabled", "true")
    if cfg.mode == "router":
        zcfg.insert_json5("listen/endpoints", json.dumps(list(cfg.listen or cfg.connect)))
        zcfg.insert_json5("connect/endpoints", json.dumps([]))
    else:
        zcfg.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        zcfg.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
        # A session that lost its router reconnects on its own (queryables, subscribers and
        # liveliness tokens are declared again); only the retry period is ours. A Zenoh config
        # file that sets it wins.
        if zcfg.get_json("connect/retry") == "null":
            zcfg.insert_json5("connect/retry", json.dumps(RECONNECT_RETRY))
    return zcfg


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    """A session for a client: in client mode it fails at once when the router does not answer."""
    return zenoh.open(to_zenoh_config(cfg))


def open_session_waiting(cfg: ZenohConfig, stop: threading.Event, name: str) -> zenoh.Session | None:
    """A service's session: in client mode it waits for the router as long as it takes, as a ROS
    node waits for its master, so start order does not matter. None when `stop` was set first.

    Each attempt lasts `ROUTER_WAIT_ATTEMPT_S` (a signal is handled between attempts); the wait is
    logged at once and then every 30 s with Zenoh's reason.
    """
    logged_at: float | None = None
    while True:
        zcfg = to_zenoh_config(cfg)
        if cfg.mode == "client" and zcfg.get_json("connect/timeout_ms") == "null":
            zcfg.insert_json5("connect/timeout_ms", json.dumps(int(ROUTER_WAIT_ATTEMPT_S * 1000)))
        try:
            session = zenoh.open(zcfg)
        except zenoh.ZError as exc:
            if cfg.mode != "client":
                raise
            now = time.monotonic()
            if logged_at is None or now - logged_at >= 30.0:
                logged_at = now
                log.warning("%s: waiting for the router at %s (%s)", name, ", ".join(cfg.connect),
                            str(exc).split(" at ")[0])
            if stop.wait(0.1):
                return None
            continue
        if logged_at is not None:
            log.info("%s: connected to the router", name)
        return session


def declare_latched_publisher(session: zenoh.Session, key: str) -> zenoh.ext.AdvancedPublisher:
    """A publisher whose last sample late subscribers still get, like a latched ROS topic.

    Its samples carry sequence numbers (zenoh-ext sample-miss detection, without heartbeats),
    so an advanced subscriber such as `robonav record` counts the ones lost on the way."""
    return zenoh.ext.declare_advanced_publisher(session, key, cache=zenoh.ext.CacheConfig(max_samples=1),
                                                sample_miss_detection=zenoh.ext.MissDetectionConfig(),
                                                publisher_detection=True)


def declare_latched_subscriber(session: zenoh.Session, key: str,
                               callback: Callable[[zenoh.Sample], None]) -> zenoh.ext.AdvancedSubscriber:
    """Subscribes and also fetches the cached last sample of every latched publisher, even late ones."""
    return zenoh.ext.declare_advanced_subscriber(session, key, callback,
                                                 history=zenoh.ext.HistoryConfig(detect_late_publishers=True))


def reply_ok(query: zenoh.Query, message: Message) -> None:
    query.reply(query.key_expr, message.to_wire())


def reply_error(query: zenoh.Query, code: ErrorCode, message: str, details: dict[str, Any] | None = None) -> None:
    log.warning("%s: %s %s", query.key_expr, code.value, message)
    query.reply_err(ErrorReply.from_error(ProtocolError(code, message, details)).to_wire())


def answer_query(query: zenoh.Query, handler: Callable[[zenoh.Query], None], name: str) -> None:
    """Run `handler` on `query`: any exception becomes a structured error reply, and the query
    ends (its final reply goes out) when this returns.

    Zenoh finishes a query only when the `Query` object is dropped, and Python drops it only
    when nothing refers to it any more. Numba's first compile inside a handler kept exceptions
    whose tracebacks reach the handler's frame, and so the query, in reference cycles that
    only a full garbage collection frees: the reply was sent, but a client with Zenoh's default
    consolidation holds a reply until the query ends, and got Zenoh's "Timeout" error instead.
    Dropping the query here ends it when the handler is done, whatever still refers to it.
    """
    try:
        handler(query)
    except ProtocolError as exc:
        _reply_error_safely(query, exc.code, exc.message, exc.details, name)
        _release_frames(exc)
    except Exception as exc:  # a service never dies on input; the error is logged and answered
        log.exception("%s: unexpected error", name)
        _reply_error_safely(query, ErrorCode.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}", None, name)
        _release_frames(exc)
    finally:
        query.drop()


def _release_frames(exc: BaseException) -> None:
    """Clear the locals of the frames an answered error's traceback holds. Those frames hold
    the request's arrays and timed trajectories (ruckig and OMPL objects), and a reference cycle
    through them would keep them until a full garbage collection, or past the interpreter's
    end, where the bindings report them as leaked."""
    traceback.clear_frames(exc.__traceback__)


def _reply_error_safely(query: zenoh.Query, code: ErrorCode, message: str, details: dict[str, Any] | None,
                        name: str) -> None:
    try:
        reply_error(query, code, message, details)
    except Exception:
        log.exception("%s: could not send the error reply", name)


def guarded_queryable(handler: Callable[[zenoh.Query], None], name: str) -> Callable[[zenoh.Query], None]:
    """Wrap a short query handler (it runs on Zenoh's callback thread): any exception becomes
    a structured error, never a dead service, and the query ends when the handler returns.
    Handlers that take long go through `RequestWorkers` instead."""

    def wrapped(query: zenoh.Query) -> None:
        answer_query(query, handler, name)

    return wrapped


def guarded_subscriber(handler: Callable[[zenoh.Sample], None], name: str) -> Callable[[zenoh.Sample], None]:
    """Wrap a subscriber callback: bad samples (oversized ones before decoding, see
    `check_publication_size`) are counted and logged once per kind, never raised."""
    seen: dict[str, int] = {}

    def wrapped(sample: zenoh.Sample) -> None:
        try:
            check_publication_size(sample)
            handler(sample)
        except Exception as exc:
            kind = exc.code.value if isinstance(exc, ProtocolError) else type(exc).__name__
            seen[kind] = seen.get(kind, 0) + 1
            if seen[kind] == 1:
                log.warning("%s: dropped a sample on %s (%s: %s); further ones of this kind are counted silently",
                            name, sample.key_expr, kind, exc)

    wrapped.dropped = seen  # type: ignore[attr-defined]
    return wrapped


# Every service decodes its requests here, so the size limit lives here too: one per process,
# set from the config by `run_service` before any queryable is declared.
_max_request_bytes = LimitsConfig().max_request_bytes


_max_publication_bytes = LimitsConfig().max_publication_bytes


def set_max_request_bytes(limit: int) -> None:
    global _max_request_bytes
    _max_request_bytes = limit


def set_max_publication_bytes(limit: int) -> None:
    global _max_publication_bytes
    _max_publication_bytes = limit


def check_publication_size(sample: zenoh.Sample) -> None:
    """Raise PAYLOAD_TOO_LARGE for a sample above `limits.max_publication_bytes`, before anything decodes it.

    Raises:
        ProtocolError: PAYLOAD_TOO_LARGE.
    """
    size = len(sample.payload)
    if size > _max_publication_bytes:
        raise ProtocolError(ErrorCode.PAYLOAD_TOO_LARGE,
                            f"sample on {sample.key_expr} is {size} bytes, more than this service accepts "
                            f"({_max_publication_bytes})", {"size_bytes": size, "limit_bytes": _max_publication_bytes})


def decode_request(query: zenoh.Query, cls: type[M]) -> M:
    """The query's request; an empty payload means every key at its default (`{v: 1}`).

    Raises:
        ProtocolError: PAYLOAD_TOO_LARGE above `limits.max_request_bytes` (checked before decoding),
            or any decoding error.
    """
    size = len(query.payload) if query.payload is not None else 0
    if size > _max_request_bytes:
        raise ProtocolError(ErrorCode.PAYLOAD_TOO_LARGE,
                            f"request payload is {size} bytes, more than this service accepts ({_max_request_bytes})",
                            {"size_bytes": size, "limit_bytes": _max_request_bytes})
    payload = query.payload.to_bytes() if query.payload is not None else b""
    return cls.from_wire(payload) if payload else cls.from_dict({"v": SCHEMA_VERSION})


_CONTAINER_ID = re.compile(r"/containers/(?:storage/overlay-containers/)?([0-9a-f]{64})/")


def instance_name() -> str:
    """This process's instance name in liveliness keys: its container's id, else the host name.

    Replicas of one service differ only by container, and with host networking every
    container has the host's name; the engine bind-mounts each container's own
    `/etc/hostname` from a path holding its id, which every process inside can read.
    """
    try:
        match = _CONTAINER_ID.search(Path("/proc/self/mountinfo").read_text(encoding="utf-8", errors="replace"))
    except OSError:
        match = None
    return match.group(1)[:12] if match else socket.gethostname()


LOG_LEVELS: tuple[str, ...] = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
LOG_FORMATS: tuple[str, ...] = ("text", "json")
LOG_FORMAT_ENV = "ROBONAV_LOG_FORMAT"
"""`--log-format`'s default; `setup_logging` sets it, so the processes a command starts
(`robonav up`'s services, the executor's setpoint stream) log the same way."""
TEXT_LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class JsonLogFormatter(logging.Formatter):
    """One JSON object per line (`ts`, `level`, `logger`, `message`, `pid`, and `exc` with a
    traceback), what container log collectors (journald, Loki, CloudWatch) parse without rules."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname, "logger": record.name, "message": record.getMessage(), "pid": record.process,
        }
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, ensure_ascii=False, default=str)


def add_logging_arguments(parser: argparse.ArgumentParser, default_level: str = "INFO") -> None:
    """`--log-level` (one of LOG_LEVELS, any case) and `--log-format text|json` on a command's parser."""
    parser.add_argument("--log-level", default=default_level, type=str.upper, choices=LOG_LEVELS,
                        help=f"log threshold (default {default_level})")
    parser.add_argument("--log-format", default=os.environ.get(LOG_FORMAT_ENV) if os.environ.get(LOG_FORMAT_ENV)
                        in LOG_FORMATS else "text", choices=LOG_FORMATS,
                        help=f"text lines, or one JSON object per line for containers (default: ${LOG_FORMAT_ENV} or text)")


def setup_logging(level: str = "INFO", log_format: str = "text") -> None:
    """Configure the root logger; raises ValueError for a level or format that is not one of
    LOG_LEVELS / LOG_FORMATS (argparse's choices catch them first on the command line)."""
    if level.upper() not in LOG_LEVELS:
        raise ValueError(f"log level must be one of {list(LOG_LEVELS)}, got {level!r}")
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {list(LOG_FORMATS)}, got {log_format!r}")
    handler = logging.StreamHandler()
    handler.setFormatter(JsonLogFormatter() if log_format == "json" else logging.Formatter(TEXT_LOG_FORMAT))
    logging.basicConfig(level=getattr(logging, level.upper()), handlers=[handler])
    os.environ[LOG_FORMAT_ENV] = log_format


class Node:
    """A service's state while its session is open; `close` undeclares what it declared."""

    def close(self) -> None:  # pragma: no cover - trivial default
        pass

    def spin(self, stop: threading.Event) -> None:
        """Block until `stop` is set; services with their own loop override this."""
        stop.wait()


def load_cli_config(config_path: str | None, zenoh_config_path: str | None) -> RobonavConfig:
    """A command's config: `--config` (None: the packaged default) with `--zenoh-config`, when
    given, over `zenoh.config_file`; the Zenoh file is read now, so a bad one is a config error
    here and not a crash when the session opens.

    Raises:
        ConfigError: a bad config or Zenoh config file.
    """
    cfg = load_config(config_path)
    if zenoh_config_path is not None:
        cfg = dataclasses.replace(cfg, zenoh=dataclasses.replace(cfg.zenoh, config_file=zenoh_config_path))
    to_zenoh_config(cfg.zenoh)
    return cfg


def parse_args_and_config(prog: str, description: str, argv: list[str] | None,
                          parents: tuple[argparse.ArgumentParser, ...] = (),
                          ) -> tuple[argparse.Namespace, RobonavConfig] | None:
    """Parse `--config`, `--zenoh-config`, `--log-level` and `--log-format` (and the options of
    `parents`, so `--help` lists them too), set up logging, load the config.

    Returns None after logging the error when the config is bad (callers exit with code 2).
    """
    parser = argparse.ArgumentParser(prog=prog, description=description, parents=list(parents))
    parser.add_argument("--config", help="YAML config file (default: the packaged configs/default.yaml)")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh JSON5 config for this process (TLS, credentials); overrides zenoh.config_file")
    add_logging_arguments(parser)
    args = parser.parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    try:
        cfg = load_cli_config(args.config, args.zenoh_config)
        check_example_passwords(cfg.zenoh.config_file)
        return args, cfg
    except ConfigError as exc:
        log.error("%s", exc)
        return None


def run_service(name: str, argv: list[str] | None, build: Callable[[RobonavConfig, zenoh.Session], Node],
                parents: tuple[argparse.ArgumentParser, ...] = ()) -> int:
    """parse → config → session → build node → liveliness token → spin → teardown.

    Exit codes: 0 after a clean stop (SIGINT/SIGTERM), 2 for a bad config.
    """
    loaded = parse_args_and_config(f"robonav serve {name}", f"Run the {name} service.", argv, parents)
    if loaded is None:
        return 2
    _, cfg = loaded
    stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
    set_max_request_bytes(cfg.limits.max_request_bytes)
    set_max_publication_bytes(cfg.limits.max_publication_bytes)
    session = open_session_waiting(cfg.zenoh, stop, name)
    if session is None:
        log.info("%s: stopped before the router answered", name)
        return 0
    with session:
        node = build(cfg, session)
        keys = Keys(cfg.cell)
        # The per-instance token tells replicas of one service apart (a container's health check).
        tokens = [session.liveliness().declare_token(keys.alive(name)),
                  session.liveliness().declare_token(keys.alive_instance(name, instance_name()))]
        log.info("%s: serving under robonav/%s", name, cfg.cell)
        try:
            node.spin(stop)
        finally:
            for token in tokens:
                token.undeclare()
            node.close()
    log.info("%s: stopped", name)
    return 0
