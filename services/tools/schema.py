"""`robonav schema`: write the JSON Schema (2020-12) of every wire message, derived from the code.

    robonav schema --out DIR            write DIR/<Message>.schema.json for every message (docs/schema/)
    robonav schema --out DIR --check    exit 1 when DIR differs from the code (a file changed, missing or extra)

The schemas describe each message's JSON form (msgpack bin as base64; docs/protocol.md), from
which code generators for other languages (quicktype, datamodel-code-generator, typify) build
client types.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from robonav.pipeline.wire.schema import all_schemas

SUFFIX = ".schema.json"


def render(schema: dict[str, Any]) -> str:
    """The file text of one schema: stable, so that a diff shows only what changed."""
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


def expected_files() -> dict[str, str]:
    """File name -> text of every schema file."""
    return {f"{name}{SUFFIX}": render(schema) for name, schema in all_schemas().items()}


def drift(directory: Path) -> list[str]:
    """What differs between `directory` and the code: 'changed X', 'missing X', 'extra X'."""
    expected = expected_files()
    present = {p.name for p in directory.glob(f"*{SUFFIX}")} if directory.is_dir() else set()
    problems = [f"missing {name}" for name in sorted(set(expected) - present)]
    problems += [f"extra {name}" for name in sorted(present - set(expected))]
    problems += [f"changed {name}" for name in sorted(present & set(expected))
                 if (directory / name).read_text(encoding="utf-8") != expected[name]]
    return problems


def write(directory: Path) -> list[Path]:
    """Write every schema into `directory` (created if needed) and remove schema files of messages
    that no longer exist; returns the files written."""
    directory.mkdir(parents=True, exist_ok=True)
    expected = expected_files()
    for stale in directory.glob(f"*{SUFFIX}"):
        if stale.name not in expected:
            stale.unlink()
    written = []
    for name, text in expected.items():
        path = directory / name
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robonav schema", description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, metavar="DIR", help="directory of the schema files (the repository "
                                                                    "keeps them in docs/schema)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when DIR differs from the code")
    args = parser.parse_args(argv)
    directory = Path(args.out)
    if args.check:
        problems = drift(directory)
        for problem in problems:
            print(f"{directory}: {problem}", file=sys.stderr)
        if problems:
            print("run `robonav schema --out DIR` to update the schemas", file=sys.stderr)
        return 1 if problems else 0
    written = write(directory)
    print(f"wrote {len(written)} schemas to {directory}")
    return 0
