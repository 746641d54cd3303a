"""`robonav calibrate collect|solve`: hand-eye calibration from the command line.

`collect` renders a dataset in the sim (`sim_collect.py`); `solve` calibrates a dataset folder
(from the sim or a real rig, `dataset.py`), prints the table of methods and writes the
camera extrinsics file perception reads (`extrinsics.py`). Exit codes: 0 done, 2 bad input
(with a message saying what to do).
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from robonav.calibration.board import BoardSpec
from robonav.calibration.dataset import Dataset, load_dataset
from robonav.calibration.hand_eye import CalibrationError
from robonav.calibration.report import format_table, report_dict
from robonav.calibration.sim_collect import CollectOptions, collect
from robonav.calibration.solve import detect_all, solve
from robonav.pipeline.camera import CameraExtrinsics
from robonav.pipeline.config import ConfigError
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import PoseSpec
from robonav.pipeline.types import FloatArray
from robonav.services.config import default_extrinsics_path, load_config, write_extrinsics

log = logging.getLogger("robonav.calibrate")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav calibrate", description="Hand-eye calibration.")
    commands = parser.add_subparsers(dest="command", required=True)
    c = commands.add_parser("collect", help="render a hand-eye dataset in the sim")
    c.add_argument("--out", required=True, type=Path, help="dataset folder to write")
    c.add_argument("--views", type=int, default=20)
    c.add_argument("--width", type=int, default=1280)
    c.add_argument("--height", type=int, default=960)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--setup", choices=("eye_to_hand", "eye_in_hand"), default="eye_to_hand",
                   help="eye_to_hand: board on the end effector, the configured camera fixed; "
                        "eye_in_hand: a wrist camera, the board on the floor")
    c.add_argument("--camera-id", default=None, help="camera of the config to calibrate (default: the first)")
    c.add_argument("--supersample", type=int, default=CollectOptions.supersample)
    c.add_argument("--noise", type=float, default=CollectOptions.noise_std, help="sensor noise, grey levels (1 sigma)")
    c.add_argument("--config", default=None, help="robonav YAML config (robot, cameras)")
    s = commands.add_parser("solve", help="calibrate a dataset folder and write the camera extrinsics")
    s.add_argument("dataset", type=Path)
    s.add_argument("--json", type=Path, default=None, help="write the table and result as JSON")
    s.add_argument("--extrinsics-out", type=Path, default=None,
                   help="extrinsics file to write (default: configs/calibration/<camera_id>.yaml)")
    s.add_argument("--no-write", action="store_true", help="do not write the extrinsics file")
    s.add_argument("--config", default=None, help="robonav YAML config (robot model, for views without base_from_ee)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        return run_collect(args) if args.command == "collect" else run_solve(args)
    except (CalibrationError, ConfigError, ValueError) as exc:
        log.error("error: %s", exc)
        return 2


def run_collect(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    cameras = {c.camera_id: c for c in cfg.cameras}
    camera_id = args.camera_id or cfg.cameras[0].camera_id
    if camera_id not in cameras:
        raise CalibrationError(f"no camera {camera_id!r} in the config (cameras: {sorted(cameras)})")
    options = CollectOptions(views=args.views, width=args.width, height=args.height, seed=args.seed, setup=args.setup,
                             supersample=args.supersample, noise_std=args.noise, board=BoardSpec())
    dataset = collect(cfg.robot, cameras[camera_id], options, args.out, progress=log.info)
    log.info("wrote %d views to %s", len(dataset.views), args.out)
    return 0


def end_effector_poses(dataset: Dataset, config_path: str | None) -> list[FloatArray]:
    """base_from_ee of every view: as written, or forward kinematics of its joint positions.

    A `config_path` given is read even when every view has its pose, so a wrong path is an
    error rather than silently unused."""
    robot_cfg = load_config(config_path).robot if config_path is not None else None
    if all(v.base_from_ee is not None for v in dataset.views):
        return [v.base_from_ee.matrix for v in dataset.views]  # type: ignore[union-attr]
    robot_cfg = robot_cfg if robot_cfg is not None else load_config(None).robot
    if tuple(robot_cfg.joint_names) != tuple(dataset.joint_names):
        raise CalibrationError(f"the dataset's joint_names {list(dataset.joint_names)} differ from the config's robot "
                               f"{list(robot_cfg.joint_names)}: pass --config with the robot the dataset was taken with")
    robot = RobotModel.from_config(robot_cfg)
    return [v.base_from_ee.matrix if v.base_from_ee is not None
            else robot.frame_pose(np.asarray(v.joint_positions), dataset.end_effector_link) for v in dataset.views]


def run_solve(args: argparse.Namespace) -> int:
    dataset = load_dataset(args.dataset)
    detections = detect_all(dataset, args.dataset, lambda path: cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    solution = solve(dataset, detections, end_effector_poses(dataset, args.config))
    report = report_dict(solution, dataset.camera_id)
    print(format_table(report), flush=True)
    if not args.no_write:
        pose = PoseSpec.from_matrix(solution.x)
        path = write_extrinsics(args.extrinsics_out or default_extrinsics_path(dataset.camera_id), CameraExtrinsics(
            camera_id=dataset.camera_id,
            parent_frame="world" if dataset.setup == "eye_to_hand" else dataset.end_effector_link,
            position_m=pose.position_m, quat_xyzw=pose.quat_xyzw, method=f"refined from {solution.seed_method}",
            reprojection_rms_px=solution.refinement.rms_px,
            calibrated_at=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")))
        report["extrinsics_file"] = str(path)
        print(f"wrote {path}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
