"""What stopped a campaign motion: the path guard's blocking voxels judged against the truth.

A guard stop is right when the new voxels on the path belong to something: a box sliding in, an
object a camera sees more of. Voxels that no true object explains, even allowing a voxel of noise
(`spurious_voxels`), stopped the arm for nothing; those straight below an object come from
perception's `fill_below_surfaces` (it assumes what it sees rests on solid matter, which the
campaign's box, placed in mid-air on the path, does not).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from robonav.pipeline.evaluation.map_accuracy import below_objects, noise_reach_m, spurious_voxels
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.transforms import make_transform
from robonav.pipeline.wire.messages import SceneObjectState

SPURIOUS_KEPT = 8
"""Spurious voxel centers a stop's record keeps, for a look at where they were."""


def true_objects(scene_objects: Sequence[SceneObject], listed: Sequence[SceneObjectState],
                 intruder: SceneObject | None) -> list[SceneObject]:
    """The scene's objects and, when one was sent, the intruder at the pose the sim lists for it."""
    objects = list(scene_objects)
    if intruder is not None:
        for state in listed:
            if state.name == intruder.name:
                objects.append(intruder.with_pose(make_transform(state.position_m, state.quat_xyzw)))
    return objects


def judge_guard_stop(blocking_m: npt.ArrayLike, voxel_m: float, objects: Sequence[SceneObject], *,
                     box_sliding: bool) -> dict[str, Any]:
    """A guard stop's record: its blocking voxels, how many no true object explains and how many
    of those lie below an object; `box_sliding` when it came before the intruder was due at rest
    (the box's voxels then lag the pose listed after the stop)."""
    blocking = np.asarray(blocking_m, dtype=np.float64).reshape(-1, 3)
    spurious = spurious_voxels(blocking, voxel_m, objects)
    # The columns hang below the object's surface voxels, which reach past its surface.
    below = below_objects(blocking[spurious], objects, noise_reach_m(voxel_m))
    return {"voxels": int(len(blocking)), "spurious": int(np.count_nonzero(spurious)),
            "spurious_below_object": int(np.count_nonzero(below)), "box_sliding": box_sliding,
            "spurious_m": np.round(blocking[spurious][:SPURIOUS_KEPT], 3).tolist()}


def stopped_for_nothing(stop: dict[str, Any]) -> bool:
    """Whether every voxel that blocked the path is one no true object explains (a settled scene)."""
    return not stop.get("box_sliding", False) and stop.get("voxels", 0) > 0 and stop.get("spurious") == stop["voxels"]


def stopped_by_fill_below(stop: dict[str, Any]) -> bool:
    """Whether a stop for nothing had every voxel straight below an object (`module docstring`)."""
    return stopped_for_nothing(stop) and stop.get("spurious_below_object") == stop["voxels"]
