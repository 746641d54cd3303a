"""The table store of the `robonav` processes: per-robot tables in files, next to the compile cache.

`$ROBONAV_TABLE_CACHE_DIR` (`off`: none), else `$XDG_CACHE_HOME/robonav/tables`, else
`~/.cache/robonav/tables`. Files live in a folder named by a hash of the core's source, so a
changed builder never reads a table an older one wrote; folders of other code untouched for
`STALE_AFTER_S` are removed. A file that cannot be read or written is a miss, logged once.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
import time
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

import robonav.pipeline
from robonav.pipeline.collision.spheres.table_store import TableStore, use_table_store

log = logging.getLogger("robonav.tables")

TABLE_CACHE_ENV = "ROBONAV_TABLE_CACHE_DIR"
"""Where per-robot tables are kept; `off` keeps none."""
STALE_AFTER_S = 30 * 24 * 3600.0
"""Folders of other code versions not used for this long are removed."""


def default_table_cache_dir() -> Path:
    """`$XDG_CACHE_HOME/robonav/tables`, else `~/.cache/robonav/tables` (the XDG base directory rules)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "robonav" / "tables"


def code_fingerprint() -> str:
    """A hash of every source file of the core (`pipeline/`), which builds the tables."""
    root = Path(robonav.pipeline.__file__).parent
    digest = hashlib.sha256()
    for file in sorted(root.rglob("*.py")):
        digest.update(str(file.relative_to(root)).encode())
        digest.update(file.read_bytes())
    return digest.hexdigest()[:16]


class DirectoryTableStore:
    """Tables as `.npz` files (no pickles) in `root/<code fingerprint>/`, written atomically."""

    def __init__(self, root: Path, fingerprint: str | None = None) -> None:
        self.root = Path(root).expanduser()
        self.folder = self.root / (fingerprint or code_fingerprint())
        self._warned = False

    def load(self, key: str) -> Mapping[str, np.ndarray] | None:
        path = self.folder / f"{key}.npz"
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
            os.utime(self.folder)  # in use: not stale
            return arrays
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
            self._warn(f"cannot read {path} ({error}); building it again")
            return None

    def save(self, key: str, arrays: Mapping[str, np.ndarray]) -> None:
        try:
            fresh = not self.folder.exists()
            self.folder.mkdir(parents=True, exist_ok=True)
            if fresh:
                self._remove_stale()
            # Another process may write the same key: each writes its own file, the last rename wins.
            with tempfile.NamedTemporaryFile(dir=self.folder, prefix=f".{key}.", suffix=".npz", delete=False) as file:
                try:
                    np.savez(file, **arrays)
                except BaseException:
                    os.unlink(file.name)
                    raise
            os.replace(file.name, self.folder / f"{key}.npz")
        except OSError as error:
            self._warn(f"cannot write tables into {self.folder} ({error}); they are built in each process")

    def _remove_stale(self) -> None:
        now = time.time()
        for other in self.root.iterdir():
            if other != self.folder and other.is_dir() and now - other.stat().st_mtime > STALE_AFTER_S:
                shutil.rmtree(other, ignore_errors=True)

    def _warn(self, message: str) -> None:
        if not self._warned:
            self._warned = True
            log.warning("%s", message)


def use_table_cache_dir() -> TableStore | None:
    """Install the table store of `$ROBONAV_TABLE_CACHE_DIR` or `default_table_cache_dir()` for
    this process (none for `off`); returns it. Processes started from this one inherit the choice."""
    setting = os.environ.get(TABLE_CACHE_ENV) or str(default_table_cache_dir())
    os.environ[TABLE_CACHE_ENV] = setting
    store = None if setting == "off" else DirectoryTableStore(Path(setting))
    use_table_store(store)
    return store
