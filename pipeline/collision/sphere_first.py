"""Checks the sphere model decides alone where it can: the planner's fast, conservative mode.

A state whose covering spheres touch nothing is free (the spheres contain the padded hulls);
where they touch something, FCL decides only near the query's start and goals (`exact`), and
elsewhere the state counts as blocked. `CollisionWorld` mixes these in.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, StateValidFn

if TYPE_CHECKING:  # the world these methods run on
    from robonav.pipeline.collision.world import CollisionWorld

SELF_OVERFLAG_PROBES = 64
"""Random states `sphere_self_overflag` measures on (seeded, so the figure is reproducible)."""
_self_overflag: weakref.WeakKeyDictionary[RobotModel, float] = weakref.WeakKeyDictionary()


class SphereFirstChecks:
    """Sphere-first validity of `CollisionWorld`."""

    @property
    def spheres_usable(self: CollisionWorld) -> bool:
        """Whether `state_free_by_spheres` / `motion_free_by_spheres` use the sphere model (else
        they are `in_collision` / `motion_valid`)."""
        return self._broad_phase_usable()

    def sphere_self_overflag(self: CollisionWorld) -> float:
        """Share of self-collision-free random states at which the spheres of a self-collision
        pair touch anyway (0 when the sphere model is not used). Measured once per robot.

        Near 1 when a config checks a pair whose spheres always touch although the hulls do not
        (e.g. open fingers not allowed to touch): every state is then suspect, and the
        sphere-first search can find nothing."""
        if not self._broad_phase_usable():
            return 0.0
        cached = _self_overflag.get(self._robot)
        if cached is None:
            rng = np.random.default_rng(0)
            robot = self._robot
            states = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(SELF_OVERFLAG_PROBES, robot.dof))
            pairs = self.self_collision_pairs
            free = [q for q in states if not self.link_pairs_in_collision(q, pairs)]
            cached = sum(self._broad_phase.self_suspect(q) for q in free) / max(len(free), 1)
            _self_overflag[self._robot] = cached
        return cached

    def state_free_by_spheres(self: CollisionWorld, q: FloatArray, exact: StateValidFn) -> bool:
        """Conservative validity of `q`: free when its spheres touch nothing; when they do, FCL
        decides only if `exact(q)`, else the state counts as in collision.

        Sound (a state it calls free is FCL-free) and, away from where `exact` holds, FCL-free:
        the planner's fast mode, which gives up states the spheres over-cover for speed."""
        if not self._broad_phase_usable():
            return not self.in_collision(q)
        q = self._robot.validate_q(q)
        anchors, radius_sq = self.tier_anchors
        if anchors is None:
            return not self._broad_phase.state_suspect(q) or self._suspect_free(q, exact, -1)
        # The tier and the spheres in one compiled call: as a Python step the tier cost a third
        # of the check.
        suspect, tier = self._broad_phase.state_suspect_tiered(q, anchors, radius_sq)
        return not suspect or self._suspect_free(q, exact, tier)

    def _suspect_free(self: CollisionWorld, q: FloatArray, exact: StateValidFn, tier: int) -> bool:
        """A state the broad phase flagged at its own clearance tier `tier`: free where `exact`
        and FCL finds it free."""
        return bool(exact(q)) and not self._check(q, first_only=True, tier=tier)

    def motion_free_by_spheres(self: CollisionWorld, q_a: FloatArray, q_b: FloatArray, resolution_rad: float,
                               exact: StateValidFn) -> bool:
        """`motion_valid` at the same states, each judged as by `state_free_by_spheres`."""
        if not self._broad_phase_usable():
            return self.motion_valid(q_a, q_b, resolution_rad)
        return self._suspects_free(self._robot.validate_q(q_a, "q_a"), self._robot.validate_q(q_b, "q_b"),
                                   resolution_rad, exact)

    def _suspects_free(self: CollisionWorld, a: FloatArray, b: FloatArray, resolution_rad: float,
                       exact: StateValidFn, checked_rad: float = 0.0) -> bool:
        """The edge's broad-phase suspects, each checked at its own clearance tier, in
        `motion_valid` order, are each either asked of FCL (where `exact`) and free, or none
        exist. One suspect is found and tried alone first because a blocked edge's suspect usually
        is a collision; which one is found changes what is asked of FCL first, not the answer."""
        anchors, radius_sq = self.tier_anchors
        edge = self._broad_phase.edge_suspects
        first, tiers, steps = edge(a, b, resolution_rad, first_only=True, anchors=anchors, anchor_radius_sq=radius_sq,
                                   checked_rad=checked_rad)
        if first.size == 0:
            return True
        if not self._suspect_free(a + (b - a) * (first[0] / steps), exact, -1 if tiers is None else int(tiers[0])):
            return False
        suspects, tiers, _ = edge(a, b, resolution_rad, anchors=anchors, anchor_radius_sq=radius_sq,
                                  checked_rad=checked_rad)
        for i in range(1, suspects.size):
            if not self._suspect_free(a + (b - a) * (suspects[i] / steps), exact, -1 if tiers is None else int(tiers[i])):
                return False
        return True
