"""Jerk-limited braking from a moving joint state to rest (ruckig velocity interface)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import ruckig

from robonav.pipeline.trajectory.trajectory import JointTrajectory, TrajectoryLimits, validate_joint_vector


def stop_trajectory(
    q: npt.ArrayLike,
    qd: npt.ArrayLike,
    qdd: npt.ArrayLike,
    *,
    max_velocity: npt.ArrayLike,
    max_acceleration: npt.ArrayLike,
    max_jerk: npt.ArrayLike,
    synchronize: bool = False,
) -> JointTrajectory:
    """Bring every joint to zero velocity and acceleration within its limits (ruckig velocity control).

    Without `synchronize` each joint brakes on its own time-optimal profile: the shortest
    stopping distance per joint (the emergency stop). With it all joints come to rest at the
    same instant (`Synchronization.Time`), which keeps the motion closer to its direction
    (the normal stop). Either way the arm may leave the planned path while braking, by at
    most each joint's own stopping distance. The trajectory starts exactly
    at (q, qd, qdd), so it can replace a running trajectory at any instant; a state above
    the limits is first braked back inside them (ruckig handles that).

    Args:
        q: (n,) current joint positions [rad or m].
        qd: (n,) current joint velocities.
        qdd: (n,) current joint accelerations.
        max_velocity: (n,) joint velocity limits, > 0 (ruckig needs them even for braking).
        max_acceleration: (n,) joint acceleration limits, > 0.
        max_jerk: (n,) joint jerk limits, > 0.
        synchronize: All joints reach rest together.

    Returns:
        A trajectory ending at rest; duration 0 if the state is already at rest.

    Raises:
        ValueError: malformed state or limits.
    """
    q_arr = np.asarray(q, dtype=np.float64)
    if q_arr.ndim != 1 or q_arr.shape[0] < 1:
        raise ValueError(f"q must have shape (n,) with n >= 1, got {q_arr.shape}")
    dof = q_arr.shape[0]
    q_arr = validate_joint_vector(q_arr, "q", dof)
    qd_arr = validate_joint_vector(qd, "qd", dof)
    qdd_arr = validate_joint_vector(qdd, "qdd", dof)

    otg = ruckig.Ruckig(dof)
    inp = ruckig.InputParameter(dof)
    inp.control_interface = ruckig.ControlInterface.Velocity
    inp.synchronization = ruckig.Synchronization.Time if synchronize else ruckig.Synchronization.No
    inp.current_position = q_arr.tolist()
    inp.current_velocity = qd_arr.tolist()
    inp.current_acceleration = qdd_arr.tolist()
    inp.target_velocity = [0.0] * dof
    inp.target_acceleration = [0.0] * dof
    limits = TrajectoryLimits(validate_joint_vector(max_velocity, "max_velocity", dof, positive=True),
                              validate_joint_vector(max_acceleration, "max_acceleration", dof, positive=True),
                              validate_joint_vector(max_jerk, "max_jerk", dof, positive=True))
    inp.max_velocity = limits.velocity.tolist()
    inp.max_acceleration = limits.acceleration.tolist()
    inp.max_jerk = limits.jerk.tolist()
    trajectory = ruckig.Trajectory(dof)
    failure = f"ruckig failed to compute a stop from qd={qd_arr.tolist()}, qdd={qdd_arr.tolist()}"
    try:
        result = otg.calculate(inp, trajectory)
    except ruckig.RuckigError as exc:  # the python binding raises on most failures
        raise RuntimeError(failure) from exc
    if result not in (ruckig.Result.Working, ruckig.Result.Finished):
        raise RuntimeError(f"{failure}: {result}")
    return JointTrajectory.from_ruckig(trajectory, limits=limits)
