"""A secured process refuses the example passwords of `configs/security` unless told it is a development stack.

The example client configs and `credentials.txt` ship with placeholder passwords
(`example-<user>-password`) so the files work as they are in tests. A router or service whose
Zenoh config logs in with one (`transport/auth/usrpwd/password`) or accepts one (the router's
`dictionary_file`) does not start unless `ROBONAV_DEV_STACK=1` says that this is a development
stack; `configs/security/setup_cell.sh` writes a cell's own random passwords.
"""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path

import zenoh

from robonav.pipeline.config import ConfigError

log = logging.getLogger("robonav.secrets")

DEV_STACK_ENV = "ROBONAV_DEV_STACK"
"""Set to 1 to accept the example passwords (a development or test stack)."""
EXAMPLE_PASSWORD = re.compile(r"^example-[a-z0-9_-]*-password$")
"""The placeholder passwords of configs/security."""


def dev_stack() -> bool:
    return os.environ.get(DEV_STACK_ENV, "") == "1"


def example_password_users(zenoh_config_file: str | Path) -> list[str]:
    """Users whose password in this Zenoh config (its own login, or its credentials dictionary) is a placeholder.

    Raises:
        ConfigError: the config or its dictionary file cannot be read.
    """
    try:
        usrpwd = json.loads(zenoh.Config.from_file(str(zenoh_config_file)).get_json("transport/auth/usrpwd"))
    except (zenoh.ZError, ValueError) as exc:
        raise ConfigError(str(zenoh_config_file), "<file>", f"not a usable Zenoh config: {exc}") from exc
    users: list[str] = []
    if not isinstance(usrpwd, dict):
        return users
    if isinstance(usrpwd.get("password"), str) and EXAMPLE_PASSWORD.match(usrpwd["password"]):
        users.append(str(usrpwd.get("user")))
    dictionary = usrpwd.get("dictionary_file")
    if isinstance(dictionary, str):
        try:
            lines = Path(dictionary).read_text(encoding="utf-8").splitlines()
        except OSError as exc:  # relative to the working directory, as Zenoh reads it
            raise ConfigError(str(zenoh_config_file), "transport/auth/usrpwd/dictionary_file",
                              f"cannot read {dictionary}: {exc.strerror or exc}") from exc
        for line in lines:
            user, sep, password = line.strip().partition(":")
            if sep and EXAMPLE_PASSWORD.match(password):
                users.append(user)
    return users


def check_example_passwords(zenoh_config_file: str | Path | None) -> None:
    """Refuse a Zenoh config with placeholder passwords, unless `ROBONAV_DEV_STACK=1`.

    Raises:
        ConfigError: it holds example passwords and this is not a development stack.
    """
    if zenoh_config_file is None:
        return
    users = example_password_users(zenoh_config_file)
    if not users:
        return
    if dev_stack():
        log.warning("%s: example passwords for %s accepted: %s=1 (a development stack)", zenoh_config_file,
                    ", ".join(users), DEV_STACK_ENV)
        return
    raise ConfigError(str(zenoh_config_file), "transport/auth/usrpwd",
                      f"the example password of {', '.join(users)} is still in place: write the cell's own "
                      f"(configs/security/setup_cell.sh), or set {DEV_STACK_ENV}=1 for a development stack")
