"""`robonav robot init`: write a robot file from a URDF (and a MoveIt SRDF).

    robonav robot init --urdf U [--srdf S] [--group G] [--tip LINK] [--package-path DIR ...]
                       [--acm-samples N] [--seed S] --out FILE

The rules deciding each value are in `pipeline/robot/description.py`. The file is a YAML mapping
of robot keys (`RobotConfig`), commented where a value was derived rather than read, with paths
relative to the file's folder; `robonav bench plan --robot FILE`, and a config's `robot:` section
(the same keys), take it. The written file is loaded back (model and collision world built, home
checked) before the command reports success. Exit code 0 on success, 2 on bad input.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.acm import generate_acm
from robonav.pipeline.robot.description import RobotDescription, describe_robot, parse_srdf
from robonav.pipeline.robot.model import RobotModel
from robonav.services.config import load_robot_file

DEFAULT_ACM_SAMPLES = 10000
"""MoveIt setup assistant's default sample count for the collision matrix."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="robonav robot", description="robot description tools")
    sub = parser.add_subparsers(dest="action", required=True)
    init = sub.add_parser("init", help="write a robot file from a URDF (+ SRDF)")
    init.add_argument("--urdf", type=Path, required=True, help="the robot's URDF")
    init.add_argument("--srdf", type=Path, default=None, help="its MoveIt SRDF (groups, states, disabled collisions)")
    init.add_argument("--group", default=None, help="SRDF planning group (default: the group with a chain)")
    init.add_argument("--tip", default=None, help="end-effector link (without an SRDF: the end of the planned chain)")
    init.add_argument("--package-path", dest="package_paths", type=Path, action="append", default=[],
                      help="folder holding the ROS packages package:// URIs name (repeatable)")
    init.add_argument("--acm-samples", type=int, default=DEFAULT_ACM_SAMPLES,
                      help="without an SRDF: random states sampled for the allowed-collision matrix")
    init.add_argument("--seed", type=int, default=0, help="seed of that sampling")
    init.add_argument("--name", default=None, help="robot name (default: the URDF's)")
    init.add_argument("--out", type=Path, required=True, help="robot file to write (YAML)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        description = init_robot_file(args.urdf, args.out, srdf=args.srdf, group=args.group, tip_link=args.tip,
                                      package_paths=args.package_paths, acm_samples=args.acm_samples,
                                      seed=args.seed, name=args.name)
    except (OSError, ValueError) as exc:
        print(f"robonav robot init: {exc}", file=sys.stderr)
        return 2
    cfg = description.config
    print(f"wrote {args.out}: robot '{cfg.name}', {len(cfg.joint_names)} joints {list(cfg.joint_names)}, "
          f"end effector {cfg.end_effector_link}, {len(cfg.allowed_collision_pairs)} allowed pairs")
    for note in description.notes:
        print(f"  check: {note}")
    return 0


def init_robot_file(urdf: Path, out: Path, *, srdf: Path | None = None, group: str | None = None,
                    tip_link: str | None = None, package_paths: list[Path] | None = None,
                    acm_samples: int = DEFAULT_ACM_SAMPLES, seed: int = 0, name: str | None = None) -> RobotDescription:
    """Derive, write and load back a robot file.

    Raises:
        ValueError: a file cannot be read, a group or link is unknown, or the written file
            does not load (the message says why).
    """
    if acm_samples < 1:
        raise ValueError(f"--acm-samples must be >= 1, got {acm_samples}")
    # Absolute but with symlinks kept: a description reached through a link (a shared folder
    # beside the repository) stays referenced through it.
    urdf_abs = Path(os.path.abspath(urdf))
    if not urdf_abs.is_file():
        raise ValueError(f"--urdf {urdf} is not a file")
    out_dir = Path(os.path.abspath(out)).parent
    packages_abs = [Path(os.path.abspath(p)) for p in (package_paths or [])]
    urdf_ref = _relative(urdf_abs, out_dir)
    package_refs = tuple(_relative(p, out_dir) for p in packages_abs)
    parsed_srdf = parse_srdf(srdf) if srdf is not None else None
    description = describe_robot(urdf_abs, parsed_srdf, urdf_reference=str(urdf_abs), group=group, tip_link=tip_link,
                                 package_paths=tuple(str(p) for p in packages_abs), name=name)
    if parsed_srdf is None or not parsed_srdf.disabled_collisions:
        world = CollisionWorld(RobotModel.from_config(description.config), padding_m=0.0)
        acm = generate_acm(world, rng=np.random.default_rng(seed), n_samples=acm_samples)
        sampled = dict(acm.reasons)
        description = describe_robot(urdf_abs, parsed_srdf, urdf_reference=str(urdf_abs), group=group,
                                     tip_link=tip_link, package_paths=tuple(str(p) for p in packages_abs),
                                     sampled_acm=sampled, name=name)
    out.parent.mkdir(parents=True, exist_ok=True)
    acm_origin = ("the SRDF's <disable_collisions>" if parsed_srdf is not None and parsed_srdf.disabled_collisions
                  else f"sampling {acm_samples} states (seed {seed}): adjacent, default, always or never in collision")
    out.write_text(robot_file_text(description, urdf_ref, package_refs,
                                   sources={"urdf": str(urdf), "srdf": str(srdf) if srdf else None, "acm": acm_origin}),
                   encoding="utf-8")
    loaded = load_robot_file(out)
    robot = RobotModel.from_config(loaded)
    problems = robot.check_joint_limits(robot.home_position_rad)
    if problems:
        raise ValueError(f"{out}: home_position_rad is outside the joint limits: {'; '.join(problems)}")
    return description


def robot_file_text(description: RobotDescription, urdf_ref: str, package_refs: tuple[str, ...],
                    sources: dict[str, Any]) -> str:
    """The robot file: one key per line group, comments on where each value came from."""
    cfg = description.config
    srdf = sources.get("srdf")
    lines = [
        f"# Robot file written by `robonav robot init` from {Path(sources['urdf']).name}"
        + (f" and {Path(srdf).name}" + (f" (group '{description.group}')" if description.group else "") if srdf else "")
        + ".",
        "# Keys are RobotConfig's (pipeline/robot/config.py); units SI (m, s, rad). Paths are relative to this file.",
        "# Review the lines marked CHECK before running a real robot.",
        f"name: {cfg.name}",
        f"urdf: {_quoted(urdf_ref)}",
    ]
    if package_refs:
        lines.append(f"package_paths: [{', '.join(_quoted(p) for p in package_refs)}]")
    lines += [
        f"base_link: {cfg.base_link}            # the URDF's root link",
        "world_from_base: {position_m: [0.0, 0.0, 0.0], quat_xyzw: [0.0, 0.0, 0.0, 1.0]}   # where base_link stands "
        "in the world",
        f"end_effector_link: {cfg.end_effector_link}",
        f"joint_names: [{', '.join(cfg.joint_names)}]",
        "# Position limits are read from the URDF by the model (override with position_limits_rad).",
        f"max_velocity_rad_s: {_floats(cfg.max_velocity_rad_s)}   # CHECK: the URDF's <limit velocity>",
        f"max_acceleration_rad_s2: {_floats(cfg.max_acceleration_rad_s2)}   # CHECK: derived, 4/s x velocity",
        f"max_jerk_rad_s3: {_floats(cfg.max_jerk_rad_s3)}   # CHECK: derived, 500/s x acceleration",
        f"home_position_rad: {_floats(cfg.home_position_rad)}",
        "padding_m: 0.01",
    ]
    if cfg.fixed_joint_positions:
        lines.append("# Joints outside the planning group, held here (an SRDF state of their group, else 0).")
        lines.append("fixed_joint_positions:")
        lines += [f"  {n}: {_float(v)}" for n, v in cfg.fixed_joint_positions.items()]
    if cfg.allowed_collision_pairs:
        origin = sources.get("acm") or "the config"
        lines.append(f"# Allowed-collision matrix from {origin}: these pairs are never checked.")
        lines.append("allowed_collision_pairs:")
        lines += [f"  - [{a}, {b}]   # {description.pair_reasons[(a, b)]}" for a, b in cfg.allowed_collision_pairs]
    for note in description.notes:
        lines.append(f"# CHECK: {note}")
    return "\n".join(lines) + "\n"


def _relative(path: Path, start: Path) -> str:
    try:
        return os.path.relpath(path, start)
    except ValueError:  # another drive (Windows): keep it absolute
        return str(path)


def _quoted(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _float(value: float) -> str:
    return repr(round(float(value), 6))


def _floats(values: tuple[float, ...]) -> str:
    return "[" + ", ".join(_float(v) for v in values) + "]"


if __name__ == "__main__":
    sys.exit(main())
