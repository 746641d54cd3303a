"""The `robonav` processes' table store: files per code version, written atomically, and every
failure a logged miss, never an error."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.collision.spheres import sphere_model
from robonav.pipeline.collision.spheres.broad_phase import SphereBroadPhase
from robonav.pipeline.collision.spheres.table_store import use_table_store
from robonav.pipeline.robot.model import RobotModel
from robonav.services.table_cache import (
    STALE_AFTER_S,
    TABLE_CACHE_ENV,
    DirectoryTableStore,
    code_fingerprint,
    use_table_cache_dir,
)

from ..conftest import PANDA_TEST_CONFIG


@pytest.fixture
def no_store_after() -> Iterator[None]:
    previous = use_table_store(None)
    try:
        yield
    finally:
        use_table_store(previous)


def test_arrays_come_back_with_their_dtype_shape_and_nothing_else(tmp_path: Path) -> None:
    store = DirectoryTableStore(tmp_path, "v1")
    arrays = {"gap_m": np.linspace(0, 1, 12).reshape(3, 4), "slot": np.array([[-1, 2]], dtype=np.int64)}
    assert store.load("pair-tables-x") is None
    store.save("pair-tables-x", arrays)
    back = store.load("pair-tables-x")
    assert back is not None and set(back) == set(arrays)
    for name, array in arrays.items():
        assert back[name].dtype == array.dtype and back[name].shape == array.shape
        np.testing.assert_array_equal(back[name], array)
    assert [p.name for p in (tmp_path / "v1").iterdir()] == ["pair-tables-x.npz"]  # no temporary file left
    assert DirectoryTableStore(tmp_path, "v2").load("pair-tables-x") is None  # other code, other folder


def test_a_damaged_file_is_a_miss_logged_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    store = DirectoryTableStore(tmp_path, "v1")
    (tmp_path / "v1").mkdir()
    for key in ("a", "b"):
        (tmp_path / "v1" / f"{key}.npz").write_bytes(b"PK\x03\x04 not a zip")
    with caplog.at_level(logging.WARNING, logger="robonav.tables"):
        assert store.load("a") is None and store.load("b") is None
    assert len(caplog.records) == 1 and "a.npz" in caplog.text and "building it again" in caplog.text
    store.save("a", {"x": np.ones(2)})
    loaded = store.load("a")
    assert loaded is not None and loaded["x"].tolist() == [1.0, 1.0]


def test_a_folder_that_cannot_be_written_is_a_logged_miss(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    (tmp_path / "file").write_text("a file where the folder should be")
    store = DirectoryTableStore(tmp_path / "file", "v1")
    with caplog.at_level(logging.WARNING, logger="robonav.tables"):
        store.save("a", {"x": np.ones(2)})
    assert store.load("a") is None and "cannot write tables" in caplog.text


def test_folders_of_other_code_are_removed_when_stale(tmp_path: Path) -> None:
    old, recent = tmp_path / "old", tmp_path / "recent"
    for folder in (old, recent):
        folder.mkdir()
        (folder / "t.npz").write_bytes(b"")
    long_ago = time.time() - STALE_AFTER_S - 60
    os.utime(old, (long_ago, long_ago))
    DirectoryTableStore(tmp_path, "new").save("t", {"x": np.zeros(1)})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new", "recent"]


def test_the_fingerprint_is_the_core_source(tmp_path: Path) -> None:
    assert code_fingerprint() == code_fingerprint() and len(code_fingerprint()) == 16
    assert DirectoryTableStore(tmp_path).folder == tmp_path / code_fingerprint()


def test_the_setting_is_inherited_and_off_keeps_none(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                     no_store_after: None) -> None:
    monkeypatch.setenv(TABLE_CACHE_ENV, "off")
    assert use_table_cache_dir() is None
    monkeypatch.setenv(TABLE_CACHE_ENV, str(tmp_path))
    store = use_table_cache_dir()
    assert isinstance(store, DirectoryTableStore) and store.root == tmp_path
    monkeypatch.delenv(TABLE_CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    store = use_table_cache_dir()
    assert isinstance(store, DirectoryTableStore) and store.root == tmp_path / "xdg" / "robonav" / "tables"
    assert os.environ[TABLE_CACHE_ENV] == str(tmp_path / "xdg" / "robonav" / "tables")  # for processes it starts


def test_a_new_process_plans_with_the_tables_from_files_as_the_first_did(tmp_path: Path, no_store_after: None) -> None:
    use_table_store(DirectoryTableStore(tmp_path, "v1"))
    sphere_model._cover_cached.cache_clear()
    robot = RobotModel.from_config(PANDA_TEST_CONFIG)
    built = SphereBroadPhase(robot, padding_m=0.01)
    assert len(list((tmp_path / "v1").glob("*.npz"))) == 3
    sphere_model._cover_cached.cache_clear()
    loaded = SphereBroadPhase(RobotModel.from_config(PANDA_TEST_CONFIG), padding_m=0.01)
    for a, b in ((built._pair_tables.gap_m, loaded._pair_tables.gap_m), (built._planes.plane_joint, loaded._planes.plane_joint),
                 (built.sphere_model.radii_m, loaded.sphere_model.radii_m)):
        assert a.flags.writeable == b.flags.writeable
        np.testing.assert_array_equal(a, b)
    states = np.random.default_rng(9).uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(200, robot.dof))
    assert [built.self_suspect(q) for q in states] == [loaded.self_suspect(q) for q in states]
