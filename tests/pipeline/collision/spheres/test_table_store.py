"""Per-robot tables through a `TableStore`: saved once, read back exactly as built, keyed on what
their builders read, and a damaged entry is built again."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping

import numpy as np
import pytest

from robonav.pipeline.collision.spheres import sphere_model
from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.spheres.table_store import WRITEABLE_KEY, stored, table_key, use_table_store
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import PoseSpec

from ....conftest import PANDA_TEST_CONFIG


class DictStore:
    """Keeps arrays in memory, as a directory of files would between processes (copies both ways)."""

    def __init__(self) -> None:
        self.tables: dict[str, dict[str, np.ndarray]] = {}
        self.loads: list[str] = []

    def load(self, key: str) -> Mapping[str, np.ndarray] | None:
        self.loads.append(key)
        table = self.tables.get(key)
        return None if table is None else {name: array.copy() for name, array in table.items()}

    def save(self, key: str, arrays: Mapping[str, np.ndarray]) -> None:
        self.tables[key] = {name: np.array(array) for name, array in arrays.items()}


@pytest.fixture
def store() -> Iterator[DictStore]:
    store = DictStore()
    previous = use_table_store(store)
    try:
        yield store
    finally:
        use_table_store(previous)


def _fresh_broad_phase(config: RobotConfig) -> SphereBroadPhase:
    """As a new process builds it: a new model (the in-process caches are per model) and no cached covers."""
    sphere_model._cover_cached.cache_clear()
    return SphereBroadPhase(RobotModel.from_config(config), padding_m=0.01)


def _assert_same_arrays(built: object, loaded: object) -> None:
    for field in dataclasses.fields(built):  # type: ignore[arg-type]
        a, b = getattr(built, field.name), getattr(loaded, field.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape and a.flags.writeable == b.flags.writeable, field.name
            assert a.flags.c_contiguous == b.flags.c_contiguous, field.name
            np.testing.assert_array_equal(a, b, err_msg=field.name)


def test_a_second_process_reads_the_tables_the_first_built_and_answers_the_same(store: DictStore) -> None:
    built = _fresh_broad_phase(PANDA_TEST_CONFIG)
    assert sorted(key.split("-")[0] for key in store.tables) == ["pair", "separating", "spheres"]
    saved = dict(store.tables)
    loaded = _fresh_broad_phase(PANDA_TEST_CONFIG)
    assert store.tables == saved  # nothing built again
    assert len(store.loads) == 6 and all(key in saved for key in store.loads[3:])
    _assert_same_arrays(built._pair_tables, loaded._pair_tables)
    _assert_same_arrays(built._planes, loaded._planes)
    _assert_same_arrays(built.sphere_model, loaded.sphere_model)
    for a, b in zip(built.sphere_model.covers, loaded.sphere_model.covers, strict=True):
        assert dataclasses.astuple(a)[2:] == dataclasses.astuple(b)[2:]
        np.testing.assert_array_equal(a.centers_m, b.centers_m)
        np.testing.assert_array_equal(a.radii_m, b.radii_m)
    rng = np.random.default_rng(4)
    robot = RobotModel.from_config(PANDA_TEST_CONFIG)
    states = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(300, robot.dof))
    assert [built.self_suspect(q) for q in states] == [loaded.self_suspect(q) for q in states]
    assert any(built.self_suspect(q) for q in states) and not all(built.self_suspect(q) for q in states)


def test_a_robot_that_differs_in_what_a_builder_reads_gets_its_own_tables(store: DictStore) -> None:
    _fresh_broad_phase(PANDA_TEST_CONFIG)
    first = set(store.tables)
    # Other limits: the same spheres, other gap tables and planes (their sampled states differ).
    narrower = dataclasses.replace(PANDA_TEST_CONFIG, position_limits_rad={"panda_joint4": (-2.5, -0.5)})
    _fresh_broad_phase(narrower)
    added = set(store.tables) - first
    assert sorted(key.split("-")[0] for key in added) == ["pair", "separating"]


def test_a_robot_standing_elsewhere_gets_its_own_tables_that_answer_the_same(store: DictStore) -> None:
    at_origin = _fresh_broad_phase(PANDA_TEST_CONFIG)
    first = set(store.tables)
    # The pose is built into the kinematics the gap tables and planes hold the base's spheres in:
    # a moved robot must not read the tables of the robot at the origin (nor the other way round).
    moved_config = dataclasses.replace(
        PANDA_TEST_CONFIG, world_from_base=PoseSpec((1.0, -0.5, 0.2), (0.0, 0.6, 0.0, 0.8)))
    moved = _fresh_broad_phase(moved_config)
    added = set(store.tables) - first
    assert sorted(key.split("-")[0] for key in added) == ["pair", "separating"]  # the link-frame spheres are shared
    # Self-collision does not depend on where the robot stands.
    robot = RobotModel.from_config(PANDA_TEST_CONFIG)
    states = np.random.default_rng(8).uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(300, robot.dof))
    suspects = [at_origin.self_suspect(q) for q in states]
    assert suspects == [moved.self_suspect(q) for q in states]
    assert any(suspects) and not all(suspects)


def test_a_damaged_entry_is_built_again_and_replaced(store: DictStore) -> None:
    key = table_key("test", np.arange(3), 0.5)
    build = lambda: {"a": np.arange(4.0)}  # noqa: E731
    same = lambda arrays: dict(arrays)  # noqa: E731
    assert stored(key, build, same, lambda arrays: {"a": arrays["a"]})["a"].tolist() == [0, 1, 2, 3]
    store.tables[key] = {"b": np.zeros(2), WRITEABLE_KEY: np.array([True])}  # a field of another layout
    value = stored(key, build, same, lambda arrays: {"a": arrays["a"]})
    assert value["a"].tolist() == [0, 1, 2, 3] and set(store.tables[key]) == {"a", WRITEABLE_KEY}


def test_keys_follow_values_dtypes_and_shapes() -> None:
    base = table_key("k", np.zeros((2, 3)), 1.0, "x", None, (1, 2))
    assert base == table_key("k", np.zeros((2, 3)), 1.0, "x", None, (1, 2))
    others = [table_key("k", np.zeros((3, 2)), 1.0, "x", None, (1, 2)),
              table_key("k", np.zeros((2, 3), dtype=np.float32), 1.0, "x", None, (1, 2)),
              table_key("k", np.zeros((2, 3)), 1.5, "x", None, (1, 2)),
              table_key("k", np.zeros((2, 3)), 1.0, "x", None, (2, 1)),
              table_key("j", np.zeros((2, 3)), 1.0, "x", None, (1, 2))]
    assert len({base, *others}) == 6
    with pytest.raises(TypeError):
        table_key("k", object())
