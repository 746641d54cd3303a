"""Per-robot tables kept between processes: what a planner builds at start-up from the robot's
collision meshes (sphere cover, self-pair gap tables, separating planes) is the same every time
for the same robot and code, and costs ~18 s for the UR5 with its gripper on a 2-core machine.

The core does no file I/O: a service installs a `TableStore` (`use_table_store`; the `robonav`
entry point installs a directory of files) and the builders ask it first. Each table is stored
under a key hashed from everything its builder reads (arrays, parameters), so a robot whose
meshes, limits or spheres differ gets its own tables; the store adds a fingerprint of the code
that builds them. Without a store, everything is built in the process, as before.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable, Mapping
from typing import Any, Protocol, TypeVar

import numpy as np

T = TypeVar("T")

WRITEABLE_KEY = "__writeable__"
"""Array of the stored arrays' writeable flags, in the order of their names (numba compiles one
specialisation per writability: a loaded table must look exactly like a built one)."""


class TableStore(Protocol):
    """Where tables live between processes; every failure is a miss, never an error."""

    def load(self, key: str) -> Mapping[str, np.ndarray] | None:
        """The arrays saved under `key`, or None."""
        ...

    def save(self, key: str, arrays: Mapping[str, np.ndarray]) -> None:
        """Keep `arrays` under `key` (best effort)."""
        ...


_store: TableStore | None = None


def use_table_store(store: TableStore | None) -> TableStore | None:
    """Install `store` for this process (None: build everything in the process); returns the previous one."""
    global _store
    previous, _store = _store, store
    return previous


def table_key(kind: str, *parts: Any) -> str:
    """`kind` and a SHA-256 of `parts` (arrays with their dtype and shape, numbers, strings,
    None, sequences and dataclasses of those, recursively)."""
    digest = hashlib.sha256(kind.encode())
    _feed(digest, parts)
    return f"{kind}-{digest.hexdigest()[:32]}"


def _feed(digest: Any, part: Any) -> None:
    if isinstance(part, np.ndarray):
        array = np.ascontiguousarray(part)
        digest.update(f"a{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    elif dataclasses.is_dataclass(part) and not isinstance(part, type):
        digest.update(f"d{type(part).__name__}".encode())
        for field in dataclasses.fields(part):
            digest.update(field.name.encode())
            _feed(digest, getattr(part, field.name))
    elif isinstance(part, (list, tuple)):
        digest.update(f"s{len(part)}".encode())
        for item in part:
            _feed(digest, item)
    elif part is None or isinstance(part, (bool, int, float, str, np.generic)):
        digest.update(f"v{type(part).__name__}:{part!r};".encode())
    else:
        raise TypeError(f"cannot key a table on a {type(part).__name__}")


def stored(key: str, build: Callable[[], T], to_arrays: Callable[[T], dict[str, np.ndarray]],
           from_arrays: Callable[[Mapping[str, np.ndarray]], T]) -> T:
    """The table under `key` from the installed store, else `build()` (then saved there)."""
    store = _store
    if store is None:
        return build()
    arrays = store.load(key)
    if arrays is not None:
        try:
            return from_arrays(_with_flags(arrays))
        except (KeyError, ValueError, TypeError, IndexError):
            pass  # a file of another layout under the same key: built again and replaced
    value = build()
    saved = to_arrays(value)
    flags = np.array([bool(np.asarray(saved[name]).flags.writeable) for name in sorted(saved)], dtype=np.bool_)
    store.save(key, {**saved, WRITEABLE_KEY: flags})
    return value


def _with_flags(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    names = sorted(name for name in arrays if name != WRITEABLE_KEY)
    flags = np.asarray(arrays[WRITEABLE_KEY], dtype=np.bool_)
    if flags.shape != (len(names),):
        raise ValueError("writeable flags do not match the arrays")
    out = {}
    for name, writeable in zip(names, flags):
        array = np.array(arrays[name])  # an own, C-ordered copy, as the builders return
        array.setflags(write=bool(writeable))
        out[name] = array
    return out


def dataclass_to_arrays(value: Any) -> dict[str, np.ndarray]:
    """The fields of a dataclass whose every field is an array."""
    return {field.name: getattr(value, field.name) for field in dataclasses.fields(value)}


def dataclass_from_arrays(cls: type[T]) -> Callable[[Mapping[str, np.ndarray]], T]:
    """The inverse of `dataclass_to_arrays` for `cls`."""
    def from_arrays(arrays: Mapping[str, np.ndarray]) -> T:
        return cls(**{field.name: arrays[field.name] for field in dataclasses.fields(cls)})  # type: ignore[arg-type]
    return from_arrays
