"""Scene objects between the wire and the core: `SceneObjectSpec` -> `SceneObject` -> `SceneObjectState`.

Shared by the planner's `planner/scene` and the sim's `sim/objects`, so both take and report
objects the same way and refuse a bad one with the same INVALID_REQUEST naming its key.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from robonav.pipeline.scene import SceneObject
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import SceneObjectSpec, SceneObjectState

T = TypeVar("T")


def invalid_request(message: str, key: str, **details: object) -> ProtocolError:
    """An INVALID_REQUEST error naming the offending request `key`."""
    return ProtocolError(ErrorCode.INVALID_REQUEST, message, {"key": key, **details})


def checked(build: Callable[[], T], key: str) -> T:
    """Run a constructor; its ValueError becomes INVALID_REQUEST naming `key`."""
    try:
        return build()
    except ProtocolError:
        raise
    except ValueError as exc:
        raise invalid_request(str(exc), key) from exc


def scene_object(spec: SceneObjectSpec, key: str) -> SceneObject:
    """A complete object spec (type and position given) as a SceneObject."""
    if spec.type is None or spec.position_m is None:
        raise invalid_request(f"object '{spec.name}' needs type and position_m", key)
    return checked(lambda: SceneObject(
        name=spec.name, type=spec.type, position_m=spec.position_m,  # type: ignore[arg-type]
        quat_xyzw=spec.quat_xyzw or (0.0, 0.0, 0.0, 1.0), size_m=spec.size_m,  # type: ignore[arg-type]
        radius_m=spec.radius_m, length_m=spec.length_m, vertices_m=spec.vertices_m, triangles=spec.triangles,
    ), key)


def object_state(obj: SceneObject) -> SceneObjectState:
    """What a reply reports of an object (meshes by vertex count)."""
    return SceneObjectState(
        name=obj.name, type=obj.type, position_m=tuple(float(v) for v in obj.position_m),
        quat_xyzw=tuple(float(v) for v in obj.quat_xyzw), size_m=obj.size_m, radius_m=obj.radius_m,
        length_m=obj.length_m, vertex_count=None if obj.vertices_m is None else int(len(obj.vertices_m)),
    )


def object_spec(obj: SceneObject) -> SceneObjectSpec:
    """The wire form of a core object (for clients that send scenes)."""
    return SceneObjectSpec(name=obj.name, type=obj.type, position_m=tuple(obj.position_m),
                           quat_xyzw=tuple(obj.quat_xyzw), size_m=obj.size_m, radius_m=obj.radius_m,
                           length_m=obj.length_m, vertices_m=obj.vertices_m, triangles=obj.triangles)
