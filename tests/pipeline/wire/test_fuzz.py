"""Garbage at every message's `from_wire`: only `ProtocolError` may come out, never anything else.

Random bytes, random msgpack values, valid messages with one value replaced, array maps with
wrong, negative or huge shapes, `v` of every type, and nesting bombs.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robonav.pipeline.wire.codec import MAX_DEPTH, Message, ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import ALL_MESSAGES, ExecuteRequest, JointState, PlanRequest


def _examples() -> list[Message]:
    # importlib mode: a sibling test module is loaded by path, not imported by name.
    spec = importlib.util.spec_from_file_location("wire_examples", Path(__file__).with_name("test_messages.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return list(module.EXAMPLES)


EXAMPLES = _examples()
FUZZ = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12), st.binary(max_size=24),
)
shapes = st.lists(st.one_of(st.integers(min_value=-(2**63), max_value=2**64 - 1), st.booleans(), st.floats(), st.text()),
                  max_size=5)
array_maps = st.fixed_dictionaries({
    "dtype": st.sampled_from(["<f4", "<f8", "<i4", "<i8", "<u1", ">f8", "|b1", "O", "<c16"]),
    "shape": st.one_of(shapes, scalars), "data": st.one_of(st.binary(max_size=64), scalars),
})
values = st.recursive(st.one_of(scalars, array_maps),
                      lambda children: st.one_of(st.lists(children, max_size=4),
                                                 st.dictionaries(st.text(max_size=8), children, max_size=4)),
                      max_leaves=20)


def _only_protocol_errors(cls: type[Message], payload: bytes) -> None:
    try:
        cls.from_wire(payload)
    except ProtocolError as exc:
        assert exc.code in ErrorCode
    # Anything else propagates and fails the test.


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.__name__)
@FUZZ
@given(payload=st.binary(max_size=256))
def test_random_bytes(cls: type[Message], payload: bytes) -> None:
    _only_protocol_errors(cls, payload)


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.__name__)
@FUZZ
@given(value=values)
def test_random_msgpack_values(cls: type[Message], value: Any) -> None:
    _only_protocol_errors(cls, msgpack.packb(value, use_bin_type=True))
    if isinstance(value, dict):
        _only_protocol_errors(cls, msgpack.packb({**value, "v": 1}, use_bin_type=True))


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda m: type(m).__name__)
@FUZZ
@given(data=st.data())
def test_valid_messages_with_one_value_replaced(example: Message, data: st.DataObject) -> None:
    obj = msgpack.unpackb(example.to_wire(), raw=False)
    key = data.draw(st.sampled_from(sorted(obj) + ["extra_key"]))
    obj[key] = data.draw(values)
    _only_protocol_errors(type(example), msgpack.packb(obj, use_bin_type=True))
    # ...and one level down, where a value is a map or a list of maps (nested messages, arrays).
    inner = obj.get(data.draw(st.sampled_from(sorted(obj))))
    targets = [inner] if isinstance(inner, dict) else [v for v in inner if isinstance(v, dict)] if isinstance(inner, list) else []
    if targets:
        target = data.draw(st.sampled_from(targets))
        target[data.draw(st.sampled_from(sorted(target) + ["extra_key"]))] = data.draw(values)
        _only_protocol_errors(type(example), msgpack.packb(obj, use_bin_type=True))


@pytest.mark.parametrize("version", [True, 1.0, "1", [1], None, 2, -1, 2**64 - 1])
def test_the_version_must_be_the_integer_one(version: object) -> None:
    obj = msgpack.unpackb(JointState(stamp=1.0, names=("a",), position=np.zeros(1), velocity=np.zeros(1)).to_wire())
    obj["v"] = version
    with pytest.raises(ProtocolError) as info:
        JointState.from_wire(msgpack.packb(obj))
    expected = ErrorCode.UNSUPPORTED_VERSION if isinstance(version, int) and not isinstance(version, bool) \
        else ErrorCode.MALFORMED_MESSAGE
    assert info.value.code is expected


@pytest.mark.parametrize("shape", [[-1, 7], [2**62, 2**62, 0], [2**32, 2**32], [2**64 - 1], [2**31 + 1, 0], [1] * 40])
def test_overflowing_or_negative_shapes_are_malformed_before_any_allocation(shape: list[int]) -> None:
    payload = msgpack.packb({"v": 1, "path": {"dtype": "<f8", "shape": shape, "data": b""}})
    with pytest.raises(ProtocolError) as info:
        ExecuteRequest.from_wire(payload)
    assert info.value.code is ErrorCode.MALFORMED_MESSAGE, info.value


def test_nesting_bombs_are_malformed() -> None:
    bomb: Any = "x"
    for _ in range(MAX_DEPTH + 1):
        bomb = [bomb]
    with pytest.raises(ProtocolError) as info:
        PlanRequest.from_wire(msgpack.packb({"v": 1, "request_id": bomb}))
    assert info.value.code is ErrorCode.MALFORMED_MESSAGE and "deeper" in info.value.message
    with pytest.raises(ProtocolError) as info:  # msgpack's own stack ends far deeper bombs
        PlanRequest.from_wire(b"\x91" * 100_000 + b"\xc0")
    assert info.value.code is ErrorCode.MALFORMED_MESSAGE


def test_typed_maps_check_their_entries() -> None:
    from robonav.pipeline.wire.messages import PerceptionStatusResponse

    good = {"v": 1, "frames": 1, "published": 1, "dropped": {"empty": 2}, "occupied_voxels": 0, "stage_ms": {"a": 1}}
    assert PerceptionStatusResponse.from_wire(msgpack.packb(good)).stage_ms == {"a": 1.0}
    for bad in ({"dropped": {"empty": "two"}}, {"dropped": {"empty": 1.5}}, {"stage_ms": {"a": [1]}}):
        with pytest.raises(ProtocolError) as info:
            PerceptionStatusResponse.from_wire(msgpack.packb(good | bad))
        assert info.value.code is ErrorCode.MALFORMED_MESSAGE
