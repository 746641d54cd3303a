"""`robonav bench KIND`: plan (MotionBenchMaker), executor, perception, record, faults, wire.

Each kind lives in its own module with an `add_parser(kinds)` and a `main(args)`; `robonav view
bench` is `bench/view.py`, reached through `robonav view`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from robonav.services.bench import executor, perception, plan, record, wire
from robonav.services.bench.faults import run as faults

KINDS = {"plan": plan, "executor": executor, "perception": perception, "record": record, "faults": faults, "wire": wire}


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav bench", description="Benchmarks over third-party problem sets "
                                     "and the live services.")
    kinds = parser.add_subparsers(dest="kind", required=True)
    for module in KINDS.values():
        module.add_parser(kinds)
    return parser.parse_args(list(argv))


def main(argv: list[str] | None = None) -> int:
    """Entry point of `robonav bench`; returns the exit code (2 on bad input)."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    return KINDS[args.kind].main(args)
