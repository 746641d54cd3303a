"""`robonav scene`: list and change the planner's collision objects (`planner/scene`) from a shell.

    robonav scene list [--json]
    robonav scene add box|sphere|cylinder|capsule|mesh NAME --position X Y Z [--quat X Y Z W]
                      [--size X Y Z | --radius R [--length L] | --mesh FILE [--scale S]]
                      [--attach LINK [--touch-links LINK ...] [--frame world|LINK]]
    robonav scene move NAME [--position X Y Z] [--quat X Y Z W]
    robonav scene remove NAME [NAME ...]
    robonav scene attach NAME [NAME ...] --link LINK [--touch-links LINK ...]
    robonav scene detach NAME [NAME ...]
    robonav scene clear

MoveIt's CollisionObject / AttachedCollisionObject operations, as `docs/protocol.md` (SceneRequest)
describes them. Every planner serving the cell answers (the scene is not a complete queryable),
so replicas stay equal; each answer is checked. Prints the scene after the change (a table, or
JSON with `--json`). Exit codes as `robonav plan`: 0 done, 1 a structured error from a planner,
2 a bad config or request, 3 no reply of the protocol.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np
import zenoh

from robonav.pipeline.config import ConfigError
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.messages import ErrorReply, SceneObjectSpec, SceneRequest, SceneResponse
from robonav.services.client import QueryFailed, reply_message
from robonav.services.common import load_cli_config, open_session
from robonav.services.keys import Keys
from robonav.services.tools.stop import EXIT_CONFIG, EXIT_FAILED, EXIT_NO_REPLY, EXIT_OK

SHAPES = ("box", "sphere", "cylinder", "capsule", "mesh")


def _common_options() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--timeout", type=float, default=10.0, help="longest wait for the planners' answers [s] "
                                                                     "(default %(default)s)")
    common.add_argument("--config", help="YAML config (default: the packaged default); its zenoh and cell keys are used")
    common.add_argument("--zenoh-config", help="Zenoh JSON5 config (TLS, login: client-operator.json5)")
    common.add_argument("--json", action="store_true", help="print the scene as JSON")
    return common


def build_parser() -> argparse.ArgumentParser:
    common = _common_options()
    parser = argparse.ArgumentParser(prog="robonav scene", description=__doc__.splitlines()[0])
    ops = parser.add_subparsers(dest="operation", metavar="OPERATION", required=True)
    ops.add_parser("list", parents=[common], help="print the scene", description="Print the planner's scene.")
    ops.add_parser("clear", parents=[common], help="remove every world and attached object",
                   description="Remove every world and attached object.")
    add = ops.add_parser("add", parents=[common], help="add (or replace) an object",
                         description="Add a world object, replacing one of the same name; with --attach, attach "
                                     "it to a robot link at once.")
    add.add_argument("shape", choices=SHAPES)
    add.add_argument("name")
    add.add_argument("--position", type=float, nargs=3, metavar=("X", "Y", "Z"), required=True,
                     help="origin in --frame [m]")
    add.add_argument("--quat", type=float, nargs=4, metavar=("X", "Y", "Z", "W"), help="orientation quat_xyzw "
                                                                                       "(default identity)")
    add.add_argument("--size", type=float, nargs=3, metavar=("X", "Y", "Z"), help="box: full side lengths [m]")
    add.add_argument("--radius", type=float, help="sphere, cylinder, capsule [m]")
    add.add_argument("--length", type=float, help="cylinder, capsule: along the local z axis [m]")
    add.add_argument("--mesh", metavar="FILE", help="mesh: a triangle mesh file (STL, OBJ, PLY, OFF; read by open3d)")
    add.add_argument("--scale", type=float, default=1.0, help="mesh: scale the file's vertices by this "
                                                              "(e.g. 0.001 for millimetres; default 1)")
    add.add_argument("--attach", metavar="LINK", help="attach the new object to this robot link")
    add.add_argument("--touch-links", nargs="+", default=None, metavar="LINK",
                     help="with --attach: links the object may touch besides LINK")
    add.add_argument("--frame", default="world", help="frame of --position/--quat: world (default), or with --attach "
                                                      "the attach link")
    move = ops.add_parser("move", parents=[common], help="set the pose of a world object",
                          description="Set the pose of a world object; what is not given is kept.")
    move.add_argument("name")
    move.add_argument("--position", type=float, nargs=3, metavar=("X", "Y", "Z"), help="new origin in world [m]")
    move.add_argument("--quat", type=float, nargs=4, metavar=("X", "Y", "Z", "W"), help="new orientation quat_xyzw")
    remove = ops.add_parser("remove", parents=[common], help="remove world or attached objects",
                            description="Remove world or attached objects by name.")
    remove.add_argument("names", nargs="+", metavar="NAME")
    attach = ops.add_parser("attach", parents=[common], help="attach existing objects to a robot link",
                            description="Attach world objects (where they are) to a robot link; objects already "
                                        "attached move to the new link.")
    attach.add_argument("names", nargs="+", metavar="NAME")
    attach.add_argument("--link", required=True, help="the robot link the objects move with, e.g. panda_hand")
    attach.add_argument("--touch-links", nargs="+", default=None, metavar="LINK",
                        help="links the objects may touch besides --link (e.g. the fingers)")
    detach = ops.add_parser("detach", parents=[common], help="detach objects: they stay where the robot holds them",
                            description="Detach attached objects; they become world objects where the robot holds them.")
    detach.add_argument("names", nargs="+", metavar="NAME")
    return parser


def read_mesh(path: str, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) [m], triangles (M, 3)) of a mesh file. Raises ValueError for a file
    open3d cannot read or one without triangles."""
    import open3d as o3d  # only the mesh case pays for the import

    mesh = o3d.io.read_triangle_mesh(path)
    vertices = np.asarray(mesh.vertices, dtype=float) * scale
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    if len(vertices) < 3 or len(triangles) < 1:
        raise ValueError(f"{path}: no triangle mesh read (a missing file, or a format open3d does not read)")
    return vertices, triangles


def scene_request(args: argparse.Namespace) -> SceneRequest:
    """The request the command line asks for. Raises ValueError (or ProtocolError) for a bad one."""
    op = args.operation
    touch = tuple(args.touch_links) if getattr(args, "touch_links", None) else None
    if op in ("list", "clear"):
        return SceneRequest(operation=op)
    if op in ("remove", "detach"):
        return SceneRequest(operation=op, names=tuple(args.names))
    if op == "attach":
        return SceneRequest(operation="attach", names=tuple(args.names), link=args.link, touch_links=touch)
    if op == "move":
        obj = SceneObjectSpec(name=args.name, position_m=None if args.position is None else tuple(args.position),
                              quat_xyzw=None if args.quat is None else tuple(args.quat))
        return SceneRequest(operation="move", objects=(obj,))
    shape: dict[str, Any] = {}
    if args.shape == "box":
        if args.size is None:
            raise ValueError("a box needs --size X Y Z")
        shape["size_m"] = tuple(args.size)
    elif args.shape == "mesh":
        if args.mesh is None:
            raise ValueError("a mesh needs --mesh FILE")
        shape["vertices_m"], shape["triangles"] = read_mesh(args.mesh, args.scale)
    else:
        if args.radius is None:
            raise ValueError(f"a {args.shape} needs --radius")
        shape["radius_m"] = args.radius
        if args.shape != "sphere":
            if args.length is None:
                raise ValueError(f"a {args.shape} needs --length")
            shape["length_m"] = args.length
    obj = SceneObjectSpec(name=args.name, type=args.shape, position_m=tuple(args.position),
                          quat_xyzw=None if args.quat is None else tuple(args.quat), frame_id=args.frame, **shape)
    if args.attach is None:
        if touch is not None or args.frame != "world":
            raise ValueError("--touch-links and a --frame other than world go with --attach")
        return SceneRequest(operation="add", objects=(obj,))
    return SceneRequest(operation="attach", objects=(obj,), link=args.attach, touch_links=touch)


def ask_planners(session: zenoh.Session, key: str, request: SceneRequest,
                 timeout_s: float) -> list[tuple[SceneResponse | ErrorReply, str | None]]:
    """Every planner's answer (replier zid) within `timeout_s`. Raises QueryFailed when none answered."""
    started = time.monotonic()
    answers: list[tuple[SceneResponse | ErrorReply, str | None]] = []
    failures: list[QueryFailed] = []
    for reply in session.get(key, payload=request.to_wire(), timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE):
        try:
            answers.append((reply_message(reply, key, SceneResponse, timeout_s, started),
                            str(reply.replier_id.zid) if reply.replier_id is not None else None))
        except QueryFailed as exc:
            failures.append(exc)
    if not answers:
        raise failures[0] if failures else QueryFailed(key, timeout_s, f"no planner answered within {timeout_s:g} s")
    return answers


def _table(response: SceneResponse) -> str:
    lines = [f"revision {response.revision}, {len(response.objects)} object{'s' if len(response.objects) != 1 else ''}"]
    for obj in response.objects:
        shape = {"size_m": obj.size_m, "radius_m": obj.radius_m, "length_m": obj.length_m, "vertices": obj.vertex_count}
        dims = " ".join(f"{k}={list(v) if isinstance(v, tuple) else v}" for k, v in shape.items() if v is not None)
        where = f"attached to {obj.attached_link}" if obj.attached_link else "world"
        touch = f" touch {list(obj.touch_links)}" if obj.touch_links else ""
        lines.append(f"  {obj.name:<16} {obj.type:<9} {where:<22} position {list(obj.position_m)} "
                     f"quat_xyzw {list(obj.quat_xyzw)} {dims}{touch}")
    return "\n".join(lines)


def _plain(response: SceneResponse | ErrorReply) -> dict[str, Any]:
    data = response.to_dict()
    data.pop("v", None)
    return data


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = load_cli_config(args.config, args.zenoh_config)
        zcfg = cfg.zenoh
    except (ConfigError, ValueError) as exc:
        print(f"robonav scene: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        request = scene_request(args)
    except (ValueError, ProtocolError) as exc:
        print(f"robonav scene: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        session = open_session(zcfg)
    except zenoh.ZError as exc:
        print(f"robonav scene: cannot reach the router at {', '.join(zcfg.connect)}: {exc}", file=sys.stderr)
        return EXIT_NO_REPLY
    with session:
        try:
            answers = ask_planners(session, Keys(cfg.cell).scene, request, args.timeout)
        except QueryFailed as exc:
            print(f"robonav scene: {exc}", file=sys.stderr)
            return EXIT_NO_REPLY
    errors = [(a, zid) for a, zid in answers if isinstance(a, ErrorReply)]
    if errors:
        for error, zid in errors:
            print(f"robonav scene: planner {zid}: {error.code}: {error.message}", file=sys.stderr)
        if args.json:
            print(json.dumps({"ok": False, "answers": [_plain(a) for a, _ in answers]}, indent=2))
        return EXIT_FAILED
    first = answers[0][0]
    assert isinstance(first, SceneResponse)
    if args.json:
        print(json.dumps({**_plain(first), "planners": len(answers)}, indent=2))
    else:
        print(_table(first) + (f"\n({len(answers)} planners answered)" if len(answers) > 1 else ""))
    return EXIT_OK
