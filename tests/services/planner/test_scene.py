"""The `planner/scene` service in process: a router, a node session and a client session on loopback."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import msgpack
import numpy as np
import pytest
import zenoh

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.codec import Message
from robonav.pipeline.wire.messages import ErrorReply, SceneObjectSpec, SceneRequest, SceneResponse
from robonav.services.client import reply_message
from robonav.services.common import guarded_queryable, open_session
from robonav.services.config import ZenohConfig
from robonav.services.keys import Keys
from robonav.services.planner.scene import PlanningScene

from ..conftest import wait_until_served

HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
KEY = Keys("arm0").scene
TETRA_VERTICES = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])
TETRA_TRIANGLES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def scene_service(panda: RobotModel) -> Iterator[tuple[PlanningScene, CollisionWorld, zenoh.Session]]:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    node_session = open_session(ZenohConfig(connect=(endpoint,)))
    world = CollisionWorld(panda)
    scene = PlanningScene(world, threading.Lock(), current_q=lambda: HOME)
    queryable = node_session.declare_queryable(KEY, guarded_queryable(scene.handle_scene, "planner"))
    client = open_session(ZenohConfig(connect=(endpoint,)))
    wait_until_served(client, KEY)
    yield scene, world, client
    queryable.undeclare()
    for s in (client, node_session, router):
        s.close()


def _ask(client: zenoh.Session, request: Message | bytes) -> SceneResponse | ErrorReply:
    payload = request if isinstance(request, bytes) else request.to_wire()
    started = time.monotonic()
    for reply in client.get(KEY, payload=payload, timeout=5.0):
        return reply_message(reply, KEY, SceneResponse, 5.0, started)
    raise AssertionError(f"no reply on {KEY}")


def _ok(client: zenoh.Session, request: Message | bytes) -> SceneResponse:
    reply = _ask(client, request)
    assert isinstance(reply, SceneResponse), reply
    return reply


def _error(client: zenoh.Session, request: Message | bytes, code: str) -> ErrorReply:
    reply = _ask(client, request)
    assert isinstance(reply, ErrorReply) and reply.code == code, reply
    return reply


def test_add_move_attach_detach_remove_through_queries(scene_service, panda: RobotModel) -> None:  # noqa: ANN001
    scene, world, client = scene_service
    hand = panda.frame_pose(HOME, "panda_hand")[:3, 3]
    assert _ok(client, SceneRequest(operation="list")).revision == 0

    table = SceneObjectSpec("table", "box", (0.5, 0.0, 0.1), size_m=(0.4, 0.6, 0.2))
    tetra = SceneObjectSpec("tetra", "mesh", (1.5, 0.0, 0.5), vertices_m=TETRA_VERTICES, triangles=TETRA_TRIANGLES)
    reply = _ok(client, SceneRequest(operation="add", objects=(table, tetra), request_id="r1"))
    assert reply.revision == 1 and reply.request_id == "r1"
    assert [(o.name, o.type, o.frame_id) for o in reply.objects] == [("table", "box", "world"), ("tetra", "mesh", "world")]
    assert reply.objects[1].vertex_count == 4
    assert world.object_names == ("table", "tetra") and not world.in_collision(HOME)

    # Same name replaces (MoveIt ADD): the table grows into the hand.
    tall = SceneObjectSpec("table", "box", (hand[0], hand[1], 0.1), size_m=(0.4, 0.6, 2 * hand[2] - 0.2 + 0.02))
    reply = _ok(client, SceneRequest(operation="add", objects=(tall,)))
    assert reply.revision == 2 and len(reply.objects) == 2 and world.in_collision(HOME)

    # MOVE changes the pose only.
    reply = _ok(client, SceneRequest(operation="move", objects=(SceneObjectSpec("table", position_m=(hand[0], hand[1], -1.0)),)))
    moved = next(o for o in reply.objects if o.name == "table")
    assert moved.position_m == (hand[0], hand[1], -1.0) and moved.size_m == tall.size_m
    assert not world.in_collision(HOME)

    # Attach a new box, posed in the hand frame; then the moved world mesh by name.
    held = SceneObjectSpec("held", "box", (0.0, 0.0, 0.16), size_m=(0.03, 0.03, 0.1), frame_id="panda_hand")
    reply = _ok(client, SceneRequest(operation="attach", objects=(held,), link="panda_hand",
                                     touch_links=("panda_leftfinger", "panda_rightfinger")))
    state = next(o for o in reply.objects if o.name == "held")
    assert state.attached_link == "panda_hand" and state.frame_id == "panda_hand"
    assert state.touch_links == ("panda_leftfinger", "panda_rightfinger")
    assert np.allclose(world.attached_world_from_object("held", HOME)[:3, 3], panda.frame_pose(HOME, "panda_hand")[:3, :3]
                       @ [0, 0, 0.16] + hand)
    assert not world.in_collision(HOME)

    # A table under the hand touches only the held box.
    bottom_z = world.attached_world_from_object("held", HOME)[2, 3] - 0.05
    thin = SceneObjectSpec("table", "box", (hand[0], hand[1], -1.0), size_m=(0.3, 0.3, 0.1))
    _ok(client, SceneRequest(operation="add", objects=(thin,)))
    _ok(client, SceneRequest(operation="move", objects=(SceneObjectSpec("table", position_m=(hand[0], hand[1], bottom_z - 0.03)),)))
    assert world.collisions(HOME) == [("held", "table")]

    # Detach leaves it in the world where the hand held it; remove drops it.
    reply = _ok(client, SceneRequest(operation="detach", names=("held",)))
    released = next(o for o in reply.objects if o.name == "held")
    assert released.attached_link is None and released.frame_id == "world"
    assert np.allclose(released.position_m, world.robot.frame_pose(HOME, "panda_hand")[:3, :3] @ [0, 0, 0.16] + hand)
    revision = reply.revision
    reply = _ok(client, SceneRequest(operation="remove", names=("held", "table")))
    assert reply.revision == revision + 1 and [o.name for o in reply.objects] == ["tetra"]

    # Attach an existing world object by name, at HOME from the joint-state provider.
    reply = _ok(client, SceneRequest(operation="attach", names=("tetra",), link="panda_link8"))
    assert [o.attached_link for o in reply.objects] == ["panda_link8"] and world.object_names == ()
    reply = _ok(client, SceneRequest(operation="clear"))
    assert reply.objects == () and world.attached_objects == () and scene.revision == reply.revision


def _raw(**fields: object) -> bytes:
    return msgpack.packb({"v": 1, **fields}, use_bin_type=True)


def test_malformed_requests_get_structured_errors_and_the_service_keeps_serving(scene_service) -> None:  # noqa: ANN001
    scene, world, client = scene_service
    _ok(client, SceneRequest(operation="add", objects=(SceneObjectSpec("box", "box", (2.0, 0.0, 0.0), size_m=(0.1, 0.1, 0.1)),)))
    before = scene.revision

    assert _error(client, b"\xc1", "MALFORMED_MESSAGE")
    assert _error(client, _raw(operation="explode"), "INVALID_REQUEST").details["key"] == "operation"
    assert _error(client, _raw(operation="add", objects=[{"name": "x", "colour": "red"}]),
                  "MALFORMED_MESSAGE").details["key"] == "objects[0].colour"
    assert _error(client, _raw(operation="add", objects=[{"name": "x", "type": "box", "position_m": [0, 0]}]),
                  "INVALID_REQUEST").details["key"] == "objects[0].position_m"
    assert _error(client, _raw(operation="add", objects=[{"name": "x", "type": "box", "position_m": [0.0, 0.0, float("nan")]}]),
                  "INVALID_REQUEST").details["key"] == "objects[0].position_m[2]"
    assert _error(client, SceneRequest(operation="add", objects=(SceneObjectSpec("x", "box", (0.0, 0.0, 0.0)),)),
                  "INVALID_REQUEST").details["key"] == "objects[0]"
    bad_mesh = SceneObjectSpec("m", "mesh", (0.0, 0.0, 0.0), vertices_m=TETRA_VERTICES, triangles=TETRA_TRIANGLES + 4)
    assert "outside" in _error(client, SceneRequest(operation="add", objects=(bad_mesh,)), "INVALID_REQUEST").message
    assert _error(client, SceneRequest(operation="remove", names=("ghost",)), "INVALID_REQUEST").details["name"] == "ghost"
    assert _error(client, _raw(operation="move", objects=[{"name": "box", "type": "sphere", "position_m": [0.0, 0.0, 0.0]}]),
                  "INVALID_REQUEST").details["key"] == "objects[0].type"
    assert _error(client, SceneRequest(operation="attach", names=("box",), link="no_link"),
                  "INVALID_REQUEST").details["key"] == "link"
    assert _error(client, SceneRequest(operation="attach", names=("box",), link="panda_hand", joint_positions=np.zeros(3)),
                  "INVALID_REQUEST").details["key"] == "joint_positions"
    assert _error(client, SceneRequest(operation="detach", names=("box",)), "INVALID_REQUEST").details["key"] == "names[0]"
    assert _error(client, _raw(operation="list", v=2), "UNSUPPORTED_VERSION")

    # Nothing above changed the scene, and the next good request is served.
    reply = _ok(client, SceneRequest(operation="list"))
    assert reply.revision == before and [o.name for o in reply.objects] == ["box"] and world.object_names == ("box",)
