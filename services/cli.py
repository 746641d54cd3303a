"""`robonav` command line: serve one service, bring all up, run the demo, or run a benchmark."""

from __future__ import annotations

import argparse
import os
import sys

SERVICE_MODULES = {
    "sim": "robonav.services.sim",
    "perception": "robonav.services.perception",
    "planner": "robonav.services.planner",
    "executor": "robonav.services.executor",
}


def main(argv: list[str] | None = None) -> int:
    # Before numpy loads: on a 2-core machine shared by four services, OpenBLAS threads fight
    # each other (a 3 ms matrix product took 80 ms), so each process uses one BLAS thread.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="robonav", description="Perception-to-plan pipeline for robot arms over Zenoh.")
    sub = parser.add_subparsers(dest="command", required=True)
    serve = sub.add_parser("serve", help="run one service", add_help=False)
    serve.add_argument("service", choices=sorted(SERVICE_MODULES))
    sub.add_parser("up", help="run a Zenoh router and every service until Ctrl-C", add_help=False)
    sub.add_parser("demo", help="start everything, plan and execute the demo goals, print a JSON summary", add_help=False)
    sub.add_parser("bench", help="benchmarks: `robonav bench plan --problems DIR` (MotionBenchMaker)", add_help=False)
    sub.add_parser("plot", help="plots: `robonav plot trajectory --json PATH_FILE -o out.png`", add_help=False)
    args, rest = parser.parse_known_args(argv)
    if args.command == "serve":
        import importlib

        module = importlib.import_module(SERVICE_MODULES[args.service])
        return int(module.main(rest))
    if args.command == "up":
        from robonav.services.up import main as up_main

        return up_main(rest)
    if args.command == "plot":
        from robonav.services.plot import main as plot_main

        return plot_main(rest)
    if args.command == "bench":
        from robonav.services.bench import main as bench_main

        return bench_main(rest)
    from robonav.services.demo import main as demo_main

    return demo_main(rest)


if __name__ == "__main__":
    sys.exit(main())
