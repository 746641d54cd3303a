"""The committed JSON Schemas (docs/schema/) are the code's, every message validates against its
own, and the compatibility rule holds: a newer peer's added optional keys, listed in
`ignorable`, do not break this version, while typos and bad values still do."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path
from typing import Any

import jsonschema
import msgpack
import numpy as np
import pytest

from robonav.pipeline.wire.codec import Message, ProtocolError, unpack
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import (
    Clusters,
    ExecutorPath,
    JointState,
    PerceptionClearRequest,
    PerceptionClearResponse,
    PerceptionStatusRequest,
    PerceptionStatusResponse,
    PlanRequest,
    PointCloud,
    SceneRequest,
)
from robonav.pipeline.wire.schema import all_schemas, from_json, message_classes, nested_classes, to_json
from robonav.services.tools import schema as schema_tool

from ...conftest import REPO_ROOT

SCHEMA_DIR = REPO_ROOT / "docs" / "schema"


def _examples() -> list[Message]:
    # importlib mode: a sibling test module is loaded by path, not imported by name.
    spec = importlib.util.spec_from_file_location("wire_examples", Path(__file__).with_name("test_messages.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return list(module.EXAMPLES)


EXAMPLES = [*_examples(),
            Clusters(stamp=1.0, ids=np.array([0, 1], np.int32), centroids_m=np.zeros((2, 3), np.float32),
                     bbox_min_m=-np.ones((2, 3), np.float32), bbox_max_m=np.ones((2, 3), np.float32),
                     voxel_counts=np.array([4, 9], np.int32), labels=("crate", ""), seq=3),
            PerceptionClearRequest(), PerceptionClearResponse(cleared_voxels=12), PerceptionStatusRequest(),
            PerceptionStatusResponse(frames=10, published=9, dropped={"stale": 1}, occupied_voxels=100,
                                     stage_ms={"integrate": 3.5}, camera_frames={"cam0": 10}),
            ExecutorPath(stamp=2.0, trajectory_id="t1", joint_names=("a", "b"), path=np.zeros((3, 2)), duration_s=1.5)]


def _contained(value: Any) -> set[type]:
    """Types of the message and of every message nested in it."""
    found = {type(value)}
    if isinstance(value, Message):
        for f in dataclasses.fields(value):  # type: ignore[arg-type]
            found |= _contained(getattr(value, f.name))
    elif isinstance(value, tuple):
        for item in value:
            found |= _contained(item)
    return found


def test_the_committed_schemas_are_the_codes() -> None:
    problems = schema_tool.drift(SCHEMA_DIR)
    assert not problems, f"docs/schema differs from the message classes: {problems}; run `robonav schema --out docs/schema`"


def test_drift_is_found(tmp_path: Path) -> None:
    schema_tool.write(tmp_path)
    assert schema_tool.drift(tmp_path) == []
    (tmp_path / "JointState.schema.json").write_text("{}\n", encoding="utf-8")
    (tmp_path / "Old.schema.json").write_text("{}\n", encoding="utf-8")
    (tmp_path / "StopRequest.schema.json").unlink()
    assert schema_tool.drift(tmp_path) == ["missing StopRequest.schema.json", "extra Old.schema.json",
                                           "changed JointState.schema.json"]
    assert schema_tool.main(["--out", str(tmp_path), "--check"]) == 1
    assert schema_tool.main(["--out", str(tmp_path)]) == 0 and schema_tool.drift(tmp_path) == []


def test_every_message_class_has_a_valid_2020_12_schema_and_an_example() -> None:
    schemas = all_schemas()
    assert set(schemas) == {cls.__name__ for cls in message_classes()}
    for schema in schemas.values():
        jsonschema.Draft202012Validator.check_schema(schema)
    covered = set().union(*(_contained(m) for m in EXAMPLES))
    assert set(message_classes()) <= covered, set(message_classes()) - covered


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_every_encoded_message_validates_against_its_schema(message: Message) -> None:
    schema = all_schemas()[type(message).__name__]
    json_form = to_json(unpack(message.to_wire()))
    jsonschema.Draft202012Validator(schema).validate(json_form)
    # The JSON form goes back to the same msgpack map, and decodes to an equal message.
    back = msgpack.packb(from_json(json_form, schema), use_bin_type=True)
    assert back == message.to_wire()


def test_nested_messages_validate_without_v() -> None:
    schemas = all_schemas()
    seen: set[str] = set()
    for message in EXAMPLES:
        for value in _nested_values(message):
            if type(value) in nested_classes():
                jsonschema.Draft202012Validator(schemas[type(value).__name__]).validate(
                    to_json(unpack(msgpack.packb(value._fields_to_dict(), use_bin_type=True))))
                seen.add(type(value).__name__)
    assert seen == {cls.__name__ for cls in nested_classes()}


def _nested_values(value: Any) -> list[Any]:
    out = []
    if isinstance(value, Message):
        for f in dataclasses.fields(value):  # type: ignore[arg-type]
            inner = getattr(value, f.name)
            items = inner if isinstance(inner, tuple) else (inner,)
            for item in items:
                if isinstance(item, Message):
                    out += [item, *_nested_values(item)]
    return out


def test_the_schemas_refuse_what_the_decoder_refuses() -> None:
    validator = jsonschema.Draft202012Validator(all_schemas()["JointState"])
    good = to_json(unpack(JointState(stamp=1.0, names=("a",), position=np.zeros(1), velocity=np.zeros(1)).to_wire()))
    assert validator.is_valid(good)
    for bad in ({**good, "nmaes": ["a"]}, {**good, "stamp": "now"}, {k: v for k, v in good.items() if k != "names"},
                {**good, "v": 2}, {**good, "position": {**good["position"], "shape": [1, 1]}},
                {**good, "position": {**good["position"], "dtype": ">f8"}}):
        assert not validator.is_valid(bad), bad


def _newer(message: Message, **added: Any) -> dict[str, Any]:
    """`message` as a newer peer would send it, with optional keys this version does not know."""
    return {**message.to_dict(), **added, "ignorable": sorted(added)}


def test_a_newer_peers_added_optional_keys_are_ignored_when_listed() -> None:
    state = JointState(stamp=1.0, names=("a", "b"), position=np.zeros(2), velocity=np.ones(2))
    newer = _newer(state, effort=[0.5, 0.25], temperature_c={"a": 40.0})
    assert JointState.from_dict(newer).to_wire() == state.to_wire()
    # Also in the JSON form against this version's schema, and in nested maps.
    assert jsonschema.Draft202012Validator(all_schemas()["JointState"]).is_valid(to_json(newer))
    request = SceneRequest(operation="list").to_dict()
    cloud = PointCloud(stamp=1.0, camera_id="cam0", points=np.zeros((1, 3), np.float32)).to_dict()
    cloud["intrinsics"] = {"width": 2, "height": 2, "fx": 1.0, "fy": 1.0, "cx": 1.0, "cy": 1.0,
                           "distortion": [0.0] * 5, "ignorable": ["distortion"]}
    assert PointCloud.from_dict(cloud).intrinsics.width == 2
    add = SceneRequest.from_dict({**request, "operation": "add", "objects": [
        {"name": "b", "type": "box", "position_m": [0, 0, 0], "size_m": [1, 1, 1], "color_rgba": [1, 0, 0, 1],
         "ignorable": ["color_rgba"]}]})
    assert add.objects[0].size_m == (1, 1, 1)


def test_what_is_not_listed_or_is_bad_is_still_refused() -> None:
    plan = PlanRequest(goal_positions=np.zeros(7)).to_dict()
    with pytest.raises(ProtocolError) as typo:  # a typo is never silently ignored
        PlanRequest.from_dict({**plan, "planer_id": "rrt"})
    assert typo.value.code == ErrorCode.MALFORMED_MESSAGE and typo.value.details["key"] == "planer_id"
    with pytest.raises(ProtocolError) as unlisted:  # listing one key does not excuse another
        PlanRequest.from_dict({**plan, "new_key": 1, "planer_id": "rrt", "ignorable": ["new_key"]})
    assert unlisted.value.details["key"] == "planer_id"
    # A listed key this version knows is decoded and checked as always: listing it excuses nothing.
    for key, value, code in (("allowed_planning_time", float("nan"), ErrorCode.INVALID_REQUEST),
                             ("allowed_planning_time", "long", ErrorCode.MALFORMED_MESSAGE),
                             ("goal_positions", {"dtype": "<f8", "shape": [2, 2], "data": bytes(32)},
                              ErrorCode.INVALID_REQUEST)):
        with pytest.raises(ProtocolError) as exc:
            PlanRequest.from_dict({**plan, key: value, "ignorable": [key]})
        assert exc.value.code == code, (key, exc.value)
    for listed in ("planner_id", ["planner_id", 3], {"a": 1}):
        with pytest.raises(ProtocolError) as exc:
            PlanRequest.from_dict({**plan, "ignorable": listed})
        assert exc.value.code == ErrorCode.MALFORMED_MESSAGE and exc.value.details["key"] == "ignorable"
