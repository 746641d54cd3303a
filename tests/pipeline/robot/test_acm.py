"""Allowed-collision matrix generation by sampling, checked against MotionBenchMaker's Panda ACM."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.acm import default_state_rad, generate_acm
from robonav.pipeline.robot.model import RobotModel

from ...conftest import MBM_DIR

MBM_BOX = MBM_DIR / "box.json"
"""The shared MotionBenchMaker data next to the repository (or where ROBONAV_MBM_DIR points)."""
N_SAMPLES = 1000
"""Far fewer than the default 10000, to keep the test fast; see the report for the full figures."""


@pytest.fixture(scope="module")
def panda_acm(panda: RobotModel):  # noqa: ANN201
    return generate_acm(CollisionWorld(panda), rng=np.random.default_rng(0), n_samples=N_SAMPLES)


def test_default_state_is_zero_or_mid_range() -> None:
    q = default_state_rad(np.array([-1.0, -3.0, 0.5]), np.array([1.0, -1.0, 2.5]))
    assert np.allclose(q, [0.0, -2.0, 1.5])


def test_every_pair_is_classified_consistently(panda: RobotModel, panda_acm) -> None:  # noqa: ANN001
    links = panda.collision_link_names
    all_pairs = {tuple(sorted((a, b))) for i, a in enumerate(links) for b in links[i + 1:]}
    assert set(panda_acm.reasons) <= all_pairs
    assert set(panda_acm.pairs_with("adjacent")) == set(panda.adjacent_link_pairs)
    for pair, count in panda_acm.collision_counts.items():
        reason = panda_acm.reasons.get(pair)
        assert (reason == "never") == (count == 0), pair
        assert (reason == "always") == (count >= 0.95 * N_SAMPLES), pair
    # Default-state pairs really collide at the default state.
    world = CollisionWorld(panda)
    default_pairs = list(panda_acm.pairs_with("default"))
    assert world.link_pairs_in_collision(panda_acm.default_q, default_pairs) == default_pairs


def test_same_seed_same_matrix(panda: RobotModel, panda_acm) -> None:  # noqa: ANN001
    again = generate_acm(CollisionWorld(panda), rng=np.random.default_rng(0), n_samples=N_SAMPLES)
    assert again.reasons == panda_acm.reasons and again.collision_counts == panda_acm.collision_counts


@pytest.mark.skipif(not MBM_BOX.is_file(), reason="shared MBM benchmark not present")
def test_matches_motionbenchmaker_panda_acm(panda: RobotModel, panda_acm) -> None:  # noqa: ANN001
    mbm = {tuple(p) for p in json.loads(MBM_BOX.read_text())["self_collision"]["allowed_pairs"]}
    assert len(mbm) == 34
    ours = set(panda_acm.allowed_pairs)
    # Every adjacent MBM pair is found, as adjacent.
    for pair in mbm & panda.adjacent_link_pairs:
        assert panda_acm.reasons[pair] == "adjacent", pair
    assert len(mbm & panda.adjacent_link_pairs) == 10
    # Our hulls are convex (larger than MoveIt's meshes), so a few pairs differ either way.
    assert len(ours & mbm) >= 32
    assert len(ours ^ mbm) <= 6


def test_rejects_bad_arguments(panda: RobotModel) -> None:
    world = CollisionWorld(panda)
    with pytest.raises(ValueError, match="n_samples"):
        generate_acm(world, rng=np.random.default_rng(0), n_samples=0)
    with pytest.raises(ValueError, match="always_fraction"):
        generate_acm(world, rng=np.random.default_rng(0), always_fraction=1.5)
