"""`robonav config`: check a config file, or print the config a service would run with.

    robonav config check FILE [FILE ...]   every error of each file, one per line: FILE:LINE: key 'k': message
    robonav config print [FILE]            the effective config as YAML, every default filled in

`check` exits 0 when every file is good, 1 when one has errors. `print` exits 2 on a bad config
(after listing its errors); its output is itself a valid config that loads to the same values.
"""

from __future__ import annotations

import argparse
import sys

import yaml

from robonav.services.config import check_config, config_to_mapping, default_config_path

EXIT_OK = 0
EXIT_ERRORS = 1
EXIT_BAD_CONFIG = 2


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav config", description=__doc__.splitlines()[0])
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    check = actions.add_parser("check", help="report every error of config files, with file and line",
                               description="Report every error of each config file at once, as FILE:LINE: key 'k': "
                                           "message; exit 0 when all are good, 1 otherwise.")
    check.add_argument("files", nargs="+", metavar="FILE", help="YAML config file")
    show = actions.add_parser("print", help="print the effective config (defaults filled in) as YAML",
                              description="Print the config a service would run with: the file's values and every "
                                          "default, as YAML that loads back to the same config.")
    show.add_argument("file", nargs="?", metavar="FILE", help="YAML config file (default: the packaged default)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.action == "check":
        code = EXIT_OK
        for file in args.files:
            _, issues = check_config(file)
            for issue in issues:
                print(issue)
            if issues:
                code = EXIT_ERRORS
                print(f"{file}: {len(issues)} error{'s' if len(issues) > 1 else ''}", file=sys.stderr)
            else:
                print(f"{file}: ok", file=sys.stderr)
        return code
    cfg, issues = check_config(args.file if args.file is not None else default_config_path())
    if cfg is None:
        for issue in issues:
            print(issue, file=sys.stderr)
        return EXIT_BAD_CONFIG
    sys.stdout.write(yaml.safe_dump(config_to_mapping(cfg), sort_keys=False, default_flow_style=None, width=120))
    return EXIT_OK
