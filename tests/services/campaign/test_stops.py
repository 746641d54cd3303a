"""Guard stops judged against the truth: the box where the sim lists it, voxels no object explains."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.scene import SceneObject
from robonav.pipeline.wire.messages import SceneObjectState
from robonav.services.campaign.stops import judge_guard_stop, stopped_by_fill_below, stopped_for_nothing, true_objects

TABLE = SceneObject("table", "box", (0.6, 0.0, 0.2), size_m=(0.6, 1.0, 0.4))
BOX = SceneObject("intruder", "box", (0.0, 0.0, 0.0), size_m=(0.1, 0.1, 0.1))


def listed(name: str, position_m: tuple[float, float, float]) -> SceneObjectState:
    return SceneObjectState(name=name, type="box", position_m=position_m, quat_xyzw=(0.0, 0.0, 0.0, 1.0), size_m=(0.1, 0.1, 0.1))


def test_the_intruder_counts_where_the_sim_lists_it_and_not_when_none_was_sent() -> None:
    objects = true_objects([TABLE], [listed("intruder", (0.5, 0.2, 1.0)), listed("table", (9.0, 9.0, 9.0))], BOX)
    assert [o.name for o in objects] == ["table", "intruder"] and objects[1].position_m == (0.5, 0.2, 1.0)
    assert objects[0] == TABLE  # the scene's own objects are the truth, not the list's copies
    assert true_objects([TABLE], [listed("intruder", (0.5, 0.2, 1.0))], None) == [TABLE]
    assert true_objects([TABLE], [], BOX) == [TABLE]  # removed meanwhile: no box


def test_a_stop_is_for_nothing_when_no_object_explains_any_blocking_voxel() -> None:
    box = BOX.with_pose(np.array([[1, 0, 0, 0.5], [0, 1, 0, 0.2], [0, 0, 1, 1.0], [0, 0, 0, 1.0]]))
    objects = [TABLE, box]
    on_box, under_box, in_air = [0.5, 0.2, 1.05], [0.5, 0.2, 0.7], [0.0, -0.5, 1.0]
    real = judge_guard_stop(np.array([on_box, under_box]), 0.02, objects, box_sliding=False)
    assert real == {"voxels": 2, "spurious": 1, "spurious_below_object": 1, "box_sliding": False,
                    "spurious_m": [under_box]}
    assert not stopped_for_nothing(real)
    column = judge_guard_stop(np.array([under_box]), 0.02, objects, box_sliding=False)
    assert stopped_for_nothing(column) and stopped_by_fill_below(column)
    # Under the box's surface voxels, which reach a voxel of noise past its side, is below it too.
    assert stopped_by_fill_below(judge_guard_stop(np.array([[0.57, 0.2, 0.7]]), 0.02, objects, box_sliding=False))
    noise = judge_guard_stop(np.array([under_box, in_air]), 0.02, objects, box_sliding=False)
    assert stopped_for_nothing(noise) and not stopped_by_fill_below(noise)
    # While the box slides its voxels lag the pose listed after the stop: not judged.
    assert not stopped_for_nothing(judge_guard_stop(np.array([in_air]), 0.02, objects, box_sliding=True))
    assert not stopped_for_nothing({"error": "TIMEOUT"}) and not stopped_for_nothing(judge_guard_stop(np.zeros((0, 3)), 0.02, objects, box_sliding=False))
