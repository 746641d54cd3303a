"""Forward kinematics of the collision links compiled with numba, derived from the Pinocchio model.

Pinocchio stays the source of truth: `LinkKinematics.from_robot` reads the joint placements,
joint types and axes, the parent structure and the collision-link frame placements out of the
reduced model `RobotModel` already built, so both always describe the same robot. The compiled
form exists because the sphere broad phase (`pipeline/broad_phase.py`) needs link poses inside
one numba call per state or edge: a Python round trip to Pinocchio (`link_pose_stack`) costs
about 10 us per state, more than the whole compiled sphere check.

Several states go through at once as the lanes of the innermost array axis
(`forward_joints_lanes`): each joint's frame is a row-major rotation (9) and a translation (3)
per lane, so compiled callers place joint-frame points without building 4x4 matrices, and one
state is a single lane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import pinocchio as pin

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, IntArray

REVOLUTE = 0
PRISMATIC = 1

_AXIS_OF_SHORTNAME: dict[str, tuple[int, tuple[float, float, float]]] = {
    "JointModelRX": (REVOLUTE, (1.0, 0.0, 0.0)),
    "JointModelRY": (REVOLUTE, (0.0, 1.0, 0.0)),
    "JointModelRZ": (REVOLUTE, (0.0, 0.0, 1.0)),
    "JointModelPX": (PRISMATIC, (1.0, 0.0, 0.0)),
    "JointModelPY": (PRISMATIC, (0.0, 1.0, 0.0)),
    "JointModelPZ": (PRISMATIC, (0.0, 0.0, 1.0)),
}


@dataclass(frozen=True)
class LinkKinematics:
    """The kinematic tree of a `RobotModel` as flat arrays for compiled forward kinematics.

    Joint 0 is Pinocchio's universe (identity pose); joints are ordered so a parent comes before
    its children (Pinocchio guarantees this). All arrays are float64/int64, C-contiguous.

    Attributes:
        parent: (J,) parent joint index of each joint; parent[0] = 0.
        parent_from_joint_rotation: (J, 3, 3) rotation of the joint placement at q = 0.
        parent_from_joint_translation_m: (J, 3) translation of the joint placement [m].
        joint_type: (J,) REVOLUTE or PRISMATIC (joint 0: unused).
        joint_axis: (J, 3) unit axis in the joint frame.
        q_slot: (J,) index of the joint's value in a configuration vector q (dof,) in
            `RobotModel.joint_names` order; -1 for joint 0.
        link_joint: (L,) joint each collision link hangs from, `collision_link_names` order.
        joint_from_link_rotation: (L, 3, 3) frame placement of each collision link.
        joint_from_link_translation_m: (L, 3) [m].
        base_joint: Joint the base link (world frame) hangs from.
        joint_from_base_rotation: (3, 3) frame placement of the base link.
        joint_from_base_translation_m: (3,) [m].

    For a fixed base the model's root frame is the world (`RobotModel` builds world_from_root,
    `RobotConfig.world_from_base` included, into the joint placements), so joint 0 is the
    identity. For a base link below a planning joint world_from_root is the inverse of the base
    link's pose and is recomputed per state (it costs one 3x3 product).
    """

    parent: IntArray
    parent_from_joint_rotation: FloatArray
    parent_from_joint_translation_m: FloatArray
    joint_type: IntArray
    joint_axis: FloatArray
    q_slot: IntArray
    link_joint: IntArray
    joint_from_link_rotation: FloatArray
    joint_from_link_translation_m: FloatArray
    base_joint: int
    joint_from_base_rotation: FloatArray
    joint_from_base_translation_m: FloatArray

    @classmethod
    def from_robot(cls, robot: RobotModel) -> LinkKinematics:
        """Extract the arrays from the robot's reduced Pinocchio model.

        Raises:
            ValueError: a joint of the reduced model is not a 1-DoF revolute or prismatic joint.
        """
        model: pin.Model = robot._model  # noqa: SLF001 (the model is the source of truth)
        q_index = np.asarray(robot._q_index, dtype=np.int64)  # noqa: SLF001
        slot_of_model_q = {int(model_q): config_slot for config_slot, model_q in enumerate(q_index)}
        n_joints = model.njoints
        parent = np.zeros(n_joints, dtype=np.int64)
        rotation = np.tile(np.eye(3), (n_joints, 1, 1))
        translation = np.zeros((n_joints, 3))
        joint_type = np.zeros(n_joints, dtype=np.int64)
        axis = np.zeros((n_joints, 3))
        q_slot = np.full(n_joints, -1, dtype=np.int64)
        for j in range(1, n_joints):
            joint = model.joints[j]
            name = joint.shortname()
            if name in _AXIS_OF_SHORTNAME:
                kind, unit = _AXIS_OF_SHORTNAME[name]
                axis[j] = unit
            elif name in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
                kind = REVOLUTE if "Revolute" in name else PRISMATIC
                axis[j] = np.asarray(joint.extract().axis, dtype=np.float64)
                axis[j] /= np.linalg.norm(axis[j])
            else:
                raise ValueError(f"joint '{model.names[j]}' is a {name}; compiled kinematics supports only "
                                 "1-DoF revolute and prismatic joints")
            if joint.idx_q not in slot_of_model_q:
                raise ValueError(f"joint '{model.names[j]}' is not a planning joint of the reduced model")
            joint_type[j] = kind
            q_slot[j] = slot_of_model_q[joint.idx_q]
            parent[j] = model.parents[j]
            placement = model.jointPlacements[j]
            rotation[j] = placement.rotation
            translation[j] = placement.translation
        link_ids = list(robot._frame_id_list)  # noqa: SLF001 (collision_link_names order)
        frames = [model.frames[fid] for fid in link_ids]
        base = model.frames[robot._base_id]  # noqa: SLF001
        return cls(
            parent=parent,
            parent_from_joint_rotation=np.ascontiguousarray(rotation),
            parent_from_joint_translation_m=translation,
            joint_type=joint_type,
            joint_axis=axis,
            q_slot=q_slot,
            link_joint=np.array([f.parentJoint for f in frames], dtype=np.int64),
            joint_from_link_rotation=np.array([f.placement.rotation for f in frames]).reshape(-1, 3, 3),
            joint_from_link_translation_m=np.array([f.placement.translation for f in frames]).reshape(-1, 3),
            base_joint=int(base.parentJoint),
            joint_from_base_rotation=np.array(base.placement.rotation, dtype=np.float64),
            joint_from_base_translation_m=np.array(base.placement.translation, dtype=np.float64),
        )

    @property
    def link_count(self) -> int:
        return int(self.link_joint.shape[0])

    @property
    def dof(self) -> int:
        return int(np.max(self.q_slot)) + 1

    def link_pose_stack(self, q: FloatArray) -> FloatArray:
        """world_from_link (L, 4, 4) of the collision links at `q` (dof,); the compiled twin of
        `RobotModel.link_pose_stack` (for tests and callers outside compiled code)."""
        return self.link_poses_batch(np.asarray(q, dtype=np.float64).reshape(1, -1))[0]

    def link_poses_batch(self, qs: FloatArray) -> FloatArray:
        """world_from_link (M, L, 4, 4) of the collision links for each row of `qs` (M, dof),
        the M states as the lanes of one `forward_joints_lanes` pass."""
        arr = np.ascontiguousarray(qs, dtype=np.float64)
        dof = self.dof
        if arr.ndim != 2 or arr.shape[1] != dof:
            raise ValueError(f"qs must have shape (M, {dof}), got shape {arr.shape}")
        out = np.zeros((arr.shape[0], self.link_count, 4, 4))
        _link_poses(arr, *self.lane_arrays(), self.link_joint, self.joint_from_link_rotation,
                    self.joint_from_link_translation_m, out)
        return out

    def lane_arrays(self) -> tuple:
        """The arguments `forward_joints_lanes` takes after the lane inputs, in order (computed
        once: every `link_pose_stack` call passes them).

        Per joint, 33 coefficients: A, B, C (each a row-major 3x3), t (3,) and d (3,), such that
        parent_from_joint(q) has rotation A + sin(q) B + (1 - cos(q)) C and translation t for a
        revolute joint (Rodrigues' formula premultiplied by the placement), rotation A and
        translation t + q d for a prismatic one. Joint 0, the model's root, is the world
        (identity) when the base link hangs from the universe, so every frame comes out in the
        world frame directly; below a planning joint the compiled pass moves frames into the world.
        """
        if "_lane_arrays" in self.__dict__:
            return self.__dict__["_lane_arrays"]
        n_joints = self.parent.shape[0]
        coefficients = np.zeros((n_joints, 33))
        for j in range(1, n_joints):
            placement = self.parent_from_joint_rotation[j]
            ax, ay, az = self.joint_axis[j]
            skew = np.array([[0.0, -az, ay], [az, 0.0, -ax], [-ay, ax, 0.0]])
            coefficients[j, 0:9] = placement.ravel()
            if self.joint_type[j] == REVOLUTE:
                coefficients[j, 9:18] = (placement @ skew).ravel()
                coefficients[j, 18:27] = (placement @ skew @ skew).ravel()
            else:
                coefficients[j, 30:33] = placement @ self.joint_axis[j]
            coefficients[j, 27:30] = self.parent_from_joint_translation_m[j]
        coefficients[0, 0:9] = np.eye(3).ravel()
        joint_from_base = np.concatenate([self.joint_from_base_rotation.ravel(), self.joint_from_base_translation_m])
        arrays = (self.parent, self.joint_type, self.q_slot, coefficients, self.base_joint, joint_from_base)
        self.__dict__["_lane_arrays"] = arrays  # a frozen dataclass: the cache bypasses __setattr__
        return arrays

    def new_lane_frames(self, lanes: int) -> FloatArray:
        """Output buffer (J, 12, lanes) of `forward_joints_lanes`."""
        return np.zeros((self.parent.shape[0], 12, lanes))

    def joint_poses_lanes(self, qs: FloatArray) -> FloatArray:
        """world_from_joint (M, J, 4, 4) for each row of `qs` (M, dof), by `forward_joints_lanes`
        (for tests: the lane kinematics against Pinocchio)."""
        arr = np.ascontiguousarray(qs, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != self.dof:
            raise ValueError(f"qs must have shape (M, {self.dof}), got shape {arr.shape}")
        count = arr.shape[0]
        frames = self.new_lane_frames(count)
        q_lanes = np.ascontiguousarray(arr.T)
        forward_joints_lanes(count, np.cos(q_lanes), np.sin(q_lanes), q_lanes, *self.lane_arrays(), frames)
        out = np.zeros((count, frames.shape[0], 4, 4))
        out[:, :, :3, :3] = frames[:, :9, :].transpose(2, 0, 1).reshape(count, -1, 3, 3)
        out[:, :, :3, 3] = frames[:, 9:, :].transpose(2, 0, 1)
        out[:, :, 3, 3] = 1.0
        return out


@nb.njit(cache=True, nogil=True, inline="always")
def forward_joints_lanes(
    n: int,
    cos_lanes: FloatArray,
    sin_lanes: FloatArray,
    q_lanes: FloatArray,
    parent: IntArray,
    joint_type: IntArray,
    q_slot: IntArray,
    coefficients: FloatArray,
    base_joint: int,
    joint_from_base: FloatArray,
    frames: FloatArray,
) -> None:  # pragma: no cover (compiled)
    """Compiled forward kinematics of n states at once: world_from_joint of every joint.

    States are lanes of the innermost axis, so each joint's arithmetic is one loop over the
    lanes that the compiler turns into SIMD instructions (VAMP's idea: several states per
    instruction instead of one); the sphere broad phase places its spheres straight from these
    joint frames, with the link placements folded into the sphere centers.

    Args:
        n: Lanes in use (<= frames.shape[2]).
        cos_lanes: (dof, >= n) cos(q) per joint slot and lane.
        sin_lanes: (dof, >= n) sin(q).
        q_lanes: (dof, >= n) q itself (read by prismatic joints) [rad or m].
        parent ... joint_from_base: `LinkKinematics.lane_arrays()`.
        frames: (J, 12, >= n) output: per joint a row-major rotation (9) and a translation (3).
    """
    n_joints = parent.shape[0]
    for r in range(9):
        value = coefficients[0, r]
        for w in range(n):
            frames[0, r, w] = value
    for r in range(3):
        value = coefficients[0, 27 + r]
        for w in range(n):
            frames[0, 9 + r, w] = value
    for j in range(1, n_joints):
        p, slot = parent[j], q_slot[j]
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = (coefficients[j, 0], coefficients[j, 1], coefficients[j, 2],
                                                       coefficients[j, 3], coefficients[j, 4], coefficients[j, 5],
                                                       coefficients[j, 6], coefficients[j, 7], coefficients[j, 8])
        tx, ty, tz = coefficients[j, 27], coefficients[j, 28], coefficients[j, 29]
        if joint_type[j] == REVOLUTE:
            b00, b01, b02, b10, b11, b12, b20, b21, b22 = (coefficients[j, 9], coefficients[j, 10], coefficients[j, 11],
                                                           coefficients[j, 12], coefficients[j, 13], coefficients[j, 14],
                                                           coefficients[j, 15], coefficients[j, 16], coefficients[j, 17])
            c00, c01, c02, c10, c11, c12, c20, c21, c22 = (coefficients[j, 18], coefficients[j, 19], coefficients[j, 20],
                                                           coefficients[j, 21], coefficients[j, 22], coefficients[j, 23],
                                                           coefficients[j, 24], coefficients[j, 25], coefficients[j, 26])
            for w in range(n):
                s, v = sin_lanes[slot, w], 1.0 - cos_lanes[slot, w]
                m00, m01, m02 = a00 + s * b00 + v * c00, a01 + s * b01 + v * c01, a02 + s * b02 + v * c02
                m10, m11, m12 = a10 + s * b10 + v * c10, a11 + s * b11 + v * c11, a12 + s * b12 + v * c12
                m20, m21, m22 = a20 + s * b20 + v * c20, a21 + s * b21 + v * c21, a22 + s * b22 + v * c22
                _compose_lane(frames, p, j, w, m00, m01, m02, m10, m11, m12, m20, m21, m22, tx, ty, tz)
        else:
            dx, dy, dz = coefficients[j, 30], coefficients[j, 31], coefficients[j, 32]
            for w in range(n):
                value = q_lanes[slot, w]
                _compose_lane(frames, p, j, w, a00, a01, a02, a10, a11, a12, a20, a21, a22,
                              tx + dx * value, ty + dy * value, tz + dz * value)
    if base_joint != 0:
        # The world frame hangs below a planning joint: world_from_root = inverse(root_from_base)
        # differs per lane, and every frame is moved into the world frame after the pass above.
        base, inv, frame = np.empty(12), np.empty(12), np.empty(12)
        for w in range(n):
            for r in range(3):
                for c in range(3):
                    base[3 * r + c] = (frames[base_joint, 3 * r, w] * joint_from_base[c]
                                       + frames[base_joint, 3 * r + 1, w] * joint_from_base[3 + c]
                                       + frames[base_joint, 3 * r + 2, w] * joint_from_base[6 + c])
                base[9 + r] = (frames[base_joint, 9 + r, w] + frames[base_joint, 3 * r, w] * joint_from_base[9]
                               + frames[base_joint, 3 * r + 1, w] * joint_from_base[10]
                               + frames[base_joint, 3 * r + 2, w] * joint_from_base[11])
            # inverse: rotation transposed, translation -R^T t
            for r in range(3):
                for c in range(3):
                    inv[3 * r + c] = base[3 * c + r]
            for r in range(3):
                inv[9 + r] = -(inv[3 * r] * base[9] + inv[3 * r + 1] * base[10] + inv[3 * r + 2] * base[11])
            for j in range(1, n_joints):
                for k in range(12):
                    frame[k] = frames[j, k, w]
                for r in range(3):
                    for c in range(3):
                        frames[j, 3 * r + c, w] = (inv[3 * r] * frame[c] + inv[3 * r + 1] * frame[3 + c]
                                                   + inv[3 * r + 2] * frame[6 + c])
                    frames[j, 9 + r, w] = (inv[9 + r] + inv[3 * r] * frame[9] + inv[3 * r + 1] * frame[10]
                                           + inv[3 * r + 2] * frame[11])
            for k in range(12):
                frames[0, k, w] = inv[k]


@nb.njit(cache=True, inline="always")
def _compose_lane(frames: FloatArray, p: int, j: int, w: int, m00: float, m01: float, m02: float, m10: float,
                  m11: float, m12: float, m20: float, m21: float, m22: float, tx: float, ty: float,
                  tz: float) -> None:  # pragma: no cover (compiled)
    """frames[j, :, w] = frames[p, :, w] @ [m | t] (p < j, so the output aliases no input)."""
    p00, p01, p02 = frames[p, 0, w], frames[p, 1, w], frames[p, 2, w]
    p10, p11, p12 = frames[p, 3, w], frames[p, 4, w], frames[p, 5, w]
    p20, p21, p22 = frames[p, 6, w], frames[p, 7, w], frames[p, 8, w]
    frames[j, 0, w] = p00 * m00 + p01 * m10 + p02 * m20
    frames[j, 1, w] = p00 * m01 + p01 * m11 + p02 * m21
    frames[j, 2, w] = p00 * m02 + p01 * m12 + p02 * m22
    frames[j, 3, w] = p10 * m00 + p11 * m10 + p12 * m20
    frames[j, 4, w] = p10 * m01 + p11 * m11 + p12 * m21
    frames[j, 5, w] = p10 * m02 + p11 * m12 + p12 * m22
    frames[j, 6, w] = p20 * m00 + p21 * m10 + p22 * m20
    frames[j, 7, w] = p20 * m01 + p21 * m11 + p22 * m21
    frames[j, 8, w] = p20 * m02 + p21 * m12 + p22 * m22
    frames[j, 9, w] = frames[p, 9, w] + p00 * tx + p01 * ty + p02 * tz
    frames[j, 10, w] = frames[p, 10, w] + p10 * tx + p11 * ty + p12 * tz
    frames[j, 11, w] = frames[p, 11, w] + p20 * tx + p21 * ty + p22 * tz


@nb.njit(cache=True, inline="always")
def link_pose_from_lane(frames: FloatArray, j: int, li: int, rotation: FloatArray, translation: FloatArray,
                        out: FloatArray, row: int, w: int) -> None:  # pragma: no cover (compiled)
    """out[row] = world_from_link (4, 4) of collision link li, hanging from joint j, in lane w."""
    for r in range(3):
        f0, f1, f2 = frames[j, 3 * r, w], frames[j, 3 * r + 1, w], frames[j, 3 * r + 2, w]
        for c in range(3):
            out[row, r, c] = f0 * rotation[li, 0, c] + f1 * rotation[li, 1, c] + f2 * rotation[li, 2, c]
        out[row, r, 3] = frames[j, 9 + r, w] + f0 * translation[li, 0] + f1 * translation[li, 1] + f2 * translation[li, 2]
        out[row, 3, r] = 0.0
    out[row, 3, 3] = 1.0


@nb.njit(cache=True, nogil=True)
def _link_poses(qs: FloatArray, parent: IntArray, joint_type: IntArray, q_slot: IntArray, coefficients: FloatArray,
                base_joint: int, joint_from_base: FloatArray, link_joint: IntArray, joint_from_link_rotation: FloatArray,
                joint_from_link_translation: FloatArray, out: FloatArray) -> None:  # pragma: no cover (compiled)
    count, dof = qs.shape
    cos_lanes, sin_lanes, q_lanes = np.empty((dof, count)), np.empty((dof, count)), np.empty((dof, count))
    for w in range(count):
        for j in range(dof):
            value = qs[w, j]
            cos_lanes[j, w], sin_lanes[j, w], q_lanes[j, w] = np.cos(value), np.sin(value), value
    frames = np.empty((parent.shape[0], 12, count))
    forward_joints_lanes(count, cos_lanes, sin_lanes, q_lanes, parent, joint_type, q_slot, coefficients, base_joint,
                         joint_from_base, frames)
    for w in range(count):
        for li in range(link_joint.shape[0]):
            link_pose_from_lane(frames, link_joint[li], li, joint_from_link_rotation, joint_from_link_translation,
                                out[w], li, w)
