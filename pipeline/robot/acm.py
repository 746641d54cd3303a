"""Allowed-collision matrix (ACM) generation by sampling, as MoveIt's setup assistant does.

A link pair is allowed (never checked for self-collision) when it is

- `adjacent`: parent and child in the kinematic tree (through links without geometry);
- `default`: in collision at the default state (every joint at 0, or mid-range when 0 is
  outside its limits, like MoveIt's `setToDefaultValues`);
- `always`: in collision in at least `always_fraction` of `n_samples` uniformly random
  in-limit states (MoveIt's `min_collision_fraction`, 0.95);
- `never`: in collision in none of those samples.

Pairs are classified in that order; a pair takes the first reason that applies. Sampling
skips pairs that are already adjacent or default. The checks are the collision world's
unpadded hulls (`CollisionWorld.link_pairs_in_collision`), the same shapes self-collision
checks use. "Never" is a statistical claim: a pair that collides in a thin slice of the
joint space can be missed; more samples make that less likely.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.types import FloatArray

AcmReason = Literal["adjacent", "default", "always", "never"]
ACM_REASONS: tuple[str, ...] = ("adjacent", "default", "always", "never")


@dataclass(frozen=True)
class AcmResult:
    """The generated matrix: allowed link pairs with why, plus the sampling statistics."""

    reasons: dict[tuple[str, str], AcmReason]
    """Allowed (sorted) link pair -> reason."""
    collision_counts: dict[tuple[str, str], int] = field(default_factory=dict)
    """Sampled pair -> number of the `n_samples` states it collided in."""
    n_samples: int = 0
    default_q: FloatArray | None = None
    """(dof,) the default state used [rad]."""

    @property
    def allowed_pairs(self) -> tuple[tuple[str, str], ...]:
        """Sorted allowed pairs, the form `RobotConfig.allowed_collision_pairs` takes."""
        return tuple(sorted(self.reasons))

    def pairs_with(self, reason: AcmReason) -> tuple[tuple[str, str], ...]:
        """Sorted allowed pairs of one reason."""
        return tuple(sorted(p for p, r in self.reasons.items() if r == reason))


def default_state_rad(lower_rad: FloatArray, upper_rad: FloatArray) -> FloatArray:
    """(dof,) 0 per joint, or the middle of its limits when 0 is outside them [rad]."""
    lower, upper = np.asarray(lower_rad, dtype=np.float64), np.asarray(upper_rad, dtype=np.float64)
    return np.where((lower <= 0.0) & (0.0 <= upper), 0.0, 0.5 * (lower + upper))


def generate_acm(
    world: CollisionWorld,
    *,
    rng: np.random.Generator,
    n_samples: int = 10000,
    always_fraction: float = 0.95,
    default_q: FloatArray | None = None,
) -> AcmResult:
    """Sample the robot's self-collisions and classify every pair of checked links.

    Args:
        world: A collision world of the robot; its own allowed pairs and obstacles are ignored.
        rng: Draws the random states (seed it for a reproducible matrix).
        n_samples: Number of uniformly random in-limit states, >= 1.
        always_fraction: A pair colliding in at least this fraction of the samples is `always`, in (0, 1].
        default_q: (dof,) default state [rad]; None takes `default_state_rad` of the joint limits.

    Returns:
        The allowed pairs with their reasons and the per-pair collision counts.

    Raises:
        ValueError: `n_samples` < 1 or `always_fraction` outside (0, 1].
    """
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    if not 0.0 < always_fraction <= 1.0:
        raise ValueError(f"always_fraction must be in (0, 1], got {always_fraction}")
    robot = world.robot
    links = robot.collision_link_names
    all_pairs = [tuple(sorted((a, b))) for i, a in enumerate(links) for b in links[i + 1:]]
    reasons: dict[tuple[str, str], AcmReason] = {p: "adjacent" for p in all_pairs if p in robot.adjacent_link_pairs}

    q0 = default_state_rad(robot.lower_limits_rad, robot.upper_limits_rad) if default_q is None else robot.validate_q(default_q, "default_q")
    remaining = [p for p in all_pairs if p not in reasons]
    for pair in world.link_pairs_in_collision(q0, remaining):
        reasons[pair] = "default"

    sampled = [p for p in all_pairs if p not in reasons]
    counts = dict.fromkeys(sampled, 0)
    states = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(n_samples, robot.dof))
    for q in states:
        for pair in world.link_pairs_in_collision(q, sampled):
            counts[pair] += 1
    for pair, count in counts.items():
        if count >= always_fraction * n_samples:
            reasons[pair] = "always"
        elif count == 0:
            reasons[pair] = "never"
    return AcmResult(reasons=reasons, collision_counts=counts, n_samples=n_samples, default_q=q0)
