"""Kinematic and collision model of a robot arm: Pinocchio forward kinematics plus URDF link geometry.

The base frame (`RobotConfig.base_link`) stands at `RobotConfig.world_from_base` in the world
(the identity by default). For a base rigidly attached to the URDF root, that pose is built into
the Pinocchio model itself: the placements of everything hanging from Pinocchio's universe are
premultiplied by world_from_root, so the model's root frame IS the world and every consumer of
the model (forward kinematics, the compiled lane kinematics, IK) works in the world without a
correction of its own. Joints outside the planning group are
locked at `RobotConfig.fixed_joint_positions` (0 when not given, or the mimicked joint's locked
value for a `<mimic>` joint) by reducing the Pinocchio model, so every configuration vector `q`
holds exactly the planning joints in `RobotConfig.joint_names` order.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pinocchio as pin

from robonav.pipeline.robot.config import CONTINUOUS_JOINT_RANGE_RAD, RobotConfig
from robonav.pipeline.robot.link_geometry import (
    LinkShape,
    convex_hull,
    find_package,
    package_search_paths,
    parse_collision_shapes,
)
from robonav.pipeline.robot.turns import nearest_turn_rad
from robonav.pipeline.types import FloatArray

PYBULLET_DATA_PREFIX = "pybullet_data:"


def resolve_urdf_path(urdf: str, package_paths: Sequence[str | Path] = ()) -> Path:
    """File of a `RobotConfig.urdf` value: `pybullet_data:<relative path>`, `package://NAME/<path>`
    (found like a mesh URI, through `package_paths` and `ROS_PACKAGE_PATH`) or a file path."""
    if urdf.startswith(PYBULLET_DATA_PREFIX):
        import pybullet_data  # imported lazily: only configs naming it need the package

        path = Path(pybullet_data.getDataPath()) / urdf[len(PYBULLET_DATA_PREFIX):]
    elif urdf.startswith("package://"):
        name, _, tail = urdf[len("package://"):].partition("/")
        package = find_package(name, package_search_paths(package_paths))
        if package is None:
            raise ValueError(f"robot.urdf '{urdf}': package '{name}' not found in robot.package_paths "
                             f"{list(package_paths)} or ROS_PACKAGE_PATH")
        path = package / tail
    else:
        path = Path(urdf)
    if not path.is_file():
        raise ValueError(f"robot.urdf '{urdf}' does not name a file (resolved to {path})")
    return path


class RobotModel:
    """Forward kinematics, limits and collision geometry of the planning joints of one robot.

    Build with `RobotModel.from_config`. Not thread-safe: FK reuses one Pinocchio data buffer.
    """

    def __init__(
        self,
        config: RobotConfig,
        model: pin.Model,
        q_index: np.ndarray,
        link_shapes: dict[str, list[LinkShape]],
        parent_link: dict[str, str],
        geometry_links: frozenset[str],
    ) -> None:
        """Prefer `from_config`; this constructor trusts its (already consistent) arguments."""
        self._config = config
        self._dof = len(config.joint_names)
        self._base_id = model.getFrameId(config.base_link, pin.BODY)
        # A base rigidly attached to the model root has a constant pose, so the world can be the
        # model's root: world_from_root goes into the model once instead of into every pose.
        self._root_is_world = model.frames[self._base_id].parentJoint == 0
        world_from_base = config.world_from_base.matrix
        if self._root_is_world:
            data = model.createData()
            pin.framesForwardKinematics(model, data, pin.neutral(model))
            world_from_root = world_from_base @ np.linalg.inv(data.oMf[self._base_id].homogeneous)
            if not np.allclose(world_from_root, np.eye(4), rtol=0.0, atol=1e-12):
                model = _rooted_in_world(model, world_from_root)
        elif not np.allclose(world_from_base, np.eye(4), rtol=0.0, atol=1e-12):
            raise ValueError(f"robot.world_from_base must be the identity when robot.base_link "
                             f"'{config.base_link}' moves with a joint (the world frame then follows that link)")
        self._model = model
        self._data = model.createData()
        self._q_index = q_index
        self._q_buffer = pin.neutral(model)
        self._link_shapes = link_shapes
        self._frame_ids = {name: model.getFrameId(name, pin.BODY) for name in link_shapes}
        self._frame_id_list = list(self._frame_ids.values())
        base_joint = model.frames[self._base_id].parentJoint
        self._static_links = tuple(name for name, fid in self._frame_ids.items()
                                   if model.frames[fid].parentJoint == base_joint)
        self._lower = np.array(model.lowerPositionLimit[q_index], dtype=np.float64)
        self._upper = np.array(model.upperPositionLimit[q_index], dtype=np.float64)
        for name, (lower, upper) in config.position_limits_rad.items():
            i = config.joint_names.index(name)
            self._lower[i], self._upper[i] = lower, upper
        self._link_hulls = {
            link: convex_hull(np.vstack([s.hull_vertices for s in shapes]))[0] for link, shapes in link_shapes.items()
        }
        self._adjacent = _adjacent_pairs(parent_link, frozenset(link_shapes), geometry_links)
        self._geometry_links = geometry_links
        self._continuous: frozenset[str] = frozenset()
        self._link_names: frozenset[str] = frozenset(parent_link) | frozenset(parent_link.values())
        for arr in (self._lower, self._upper, *self._link_hulls.values()):
            arr.setflags(write=False)

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> RobotModel:
        """Load the URDF a config names and build the model.

        Raises:
            ValueError: the URDF, a joint or link named in `cfg`, or a mesh cannot be found, or a
                planning joint is not a 1-DoF (revolute/continuous/prismatic) joint.
        """
        urdf_path = resolve_urdf_path(cfg.urdf, cfg.package_paths)
        try:
            root = ET.parse(urdf_path).getroot()
        except ET.ParseError as exc:
            raise ValueError(f"robot.urdf {urdf_path.name} is not valid XML: {exc}") from exc
        continuous = _continuous_as_revolute(root, cfg)
        full = pin.buildModelFromXML(ET.tostring(root, encoding="unicode"))
        link_names = frozenset(link.attrib["name"] for link in root.findall("link"))
        _check_names(full, cfg, urdf_path.name, root)
        model = _reduced_model(full, cfg, _locked_positions(root, cfg))
        q_index = np.array([model.joints[model.getJointId(n)].idx_q for n in cfg.joint_names], dtype=np.int64)

        shapes = parse_collision_shapes(urdf_path, cfg.package_paths)
        errors = []
        for i, link in enumerate(cfg.collision_links):
            if link not in shapes:
                errors.append(f"robot.collision_links[{i}] '{link}' has no collision geometry in {urdf_path.name}")
        for pair in cfg.allowed_collision_pairs:
            # A link without geometry cannot collide: MoveIt keeps such pairs too, so they are harmless.
            errors += [f"robot.allowed_collision_pairs names '{link}', which is not a link of {urdf_path.name}"
                       for link in pair if link not in link_names]
        if errors:
            raise ValueError("; ".join(errors))
        selected = {k: v for k, v in shapes.items() if not cfg.collision_links or k in cfg.collision_links}
        parent_link = {j.find("child").attrib["link"]: j.find("parent").attrib["link"] for j in root.findall("joint")}
        robot = cls(cfg, model, q_index, selected, parent_link, frozenset(shapes))
        robot._continuous = continuous
        robot._link_names = link_names
        return robot

    @property
    def config(self) -> RobotConfig:
        return self._config

    @property
    def continuous_joint_names(self) -> tuple[str, ...]:
        """Planning joints that are `continuous` in the URDF (planned over `CONTINUOUS_JOINT_RANGE_RAD`
        unless `position_limits_rad` names them)."""
        return tuple(n for n in self.joint_names if n in self._continuous)

    @property
    def continuous_mask(self) -> np.ndarray:
        """(dof,) bool: True for the planning joints that are `continuous` (their angles wrap, `turns.py`)."""
        return np.array([n in self._continuous for n in self.joint_names], dtype=bool)

    def nearest_turn_rad(self, q: FloatArray, reference_rad: FloatArray) -> FloatArray:
        """`q` (dof,) or (G, dof) with each continuous joint moved by whole turns to the angle
        nearest `reference_rad` (dof,) within its limits; other joints as given (`turns.py`)."""
        return nearest_turn_rad(q, reference_rad, self._lower, self._upper, self.continuous_mask)

    @property
    def link_names(self) -> frozenset[str]:
        """Every link of the URDF."""
        return self._link_names

    @property
    def geometry_link_names(self) -> frozenset[str]:
        """Links with collision geometry (checked or not)."""
        return self._geometry_links

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._config.joint_names

    @property
    def dof(self) -> int:
        return self._dof

    @property
    def lower_limits_rad(self) -> FloatArray:
        """(dof,) lower position limits: the URDF's or `config.position_limits_rad` [rad, or m for prismatic]."""
        return self._lower

    @property
    def upper_limits_rad(self) -> FloatArray:
        """(dof,) upper position limits: the URDF's or `config.position_limits_rad` [rad, or m for prismatic]."""
        return self._upper

    @property
    def velocity_limits(self) -> FloatArray:
        """(dof,) velocity limits from the config [rad/s]."""
        return np.array(self._config.max_velocity_rad_s, dtype=np.float64)

    @property
    def acceleration_limits(self) -> FloatArray:
        """(dof,) acceleration limits from the config [rad/s^2]."""
        return np.array(self._config.max_acceleration_rad_s2, dtype=np.float64)

    @property
    def jerk_limits(self) -> FloatArray:
        """(dof,) jerk limits from the config [rad/s^3]."""
        return np.array(self._config.max_jerk_rad_s3, dtype=np.float64)

    @property
    def home_position_rad(self) -> FloatArray:
        """(dof,) home configuration from the config [rad]."""
        return np.array(self._config.home_position_rad, dtype=np.float64)

    @property
    def collision_link_names(self) -> tuple[str, ...]:
        """Checked links with collision geometry, in URDF order."""
        return tuple(self._link_shapes)

    @property
    def static_link_names(self) -> tuple[str, ...]:
        """Checked links rigidly attached to the base (e.g. panda_link0): no planning joint moves them."""
        return self._static_links

    @property
    def link_collision_shapes(self) -> dict[str, list[LinkShape]]:
        """Checked link name -> its collision shapes (hulls in the link frame)."""
        return self._link_shapes

    @property
    def link_hull_vertices(self) -> dict[str, FloatArray]:
        """Checked link name -> (H, 3) convex hull of all its shapes, link frame [m]."""
        return self._link_hulls

    @property
    def adjacent_link_pairs(self) -> frozenset[tuple[str, str]]:
        """Sorted pairs of checked links joined in the kinematic tree (through geometry-less links)."""
        return self._adjacent

    def validate_q(self, q: FloatArray, label: str = "q") -> FloatArray:
        """`q` as a (dof,) float64 array.

        Raises:
            ValueError: wrong shape or a non-finite entry (the message names `label` and the index).
        """
        arr = np.asarray(q, dtype=np.float64)
        if arr.shape != (self._dof,):
            raise ValueError(
                f"{label} must have shape ({self.dof},) (one value per joint {list(self.joint_names)}), "
                f"got shape {arr.shape}"
            )
        # One dot product finds NaN and inf (planners call this per edge; np.isfinite().all()
        # costs three times as much); huge finite values that overflow it are looked at again.
        if not math.isfinite(arr.dot(arr)):
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                i = int(bad[0])
                raise ValueError(f"{label}[{i}] ({self.joint_names[i]}) must be finite, got {arr[i]}")
        return arr

    def check_joint_limits(self, q: FloatArray, tolerance_rad: float = 1e-9) -> list[str]:
        """Human-readable joint limit violations of `q` (empty when within limits)."""
        arr = self.validate_q(q)
        out = []
        for i, name in enumerate(self.joint_names):
            if arr[i] < self._lower[i] - tolerance_rad:
                out.append(f"{name} (index {i}) = {arr[i]:.4f} is below its lower limit {self._lower[i]:.4f}")
            elif arr[i] > self._upper[i] + tolerance_rad:
                out.append(f"{name} (index {i}) = {arr[i]:.4f} is above its upper limit {self._upper[i]:.4f}")
        return out

    def _forward(self, q: FloatArray) -> None:
        self._q_buffer[self._q_index] = q
        pin.framesForwardKinematics(self._model, self._data, self._q_buffer)

    def _world_from_root(self) -> FloatArray:
        """Only for a base below a planning joint: the world is the base frame at the last `_forward`."""
        return np.linalg.inv(self._data.oMf[self._base_id].homogeneous)

    def link_poses(self, q: FloatArray) -> dict[str, FloatArray]:
        """world_from_link (4, 4) of every checked link with collision geometry at `q` (dof,)."""
        self._forward(self.validate_q(q))
        root_from_frame = self._data.oMf  # Pinocchio: pose of each frame in its root (o)
        if self._root_is_world:
            # The common case (a fixed base) skips 11 matrix products per call.
            return {name: root_from_frame[fid].homogeneous for name, fid in self._frame_ids.items()}
        world_from_root = self._world_from_root()
        return {name: world_from_root @ root_from_frame[fid].homogeneous for name, fid in self._frame_ids.items()}

    def link_pose_stack(self, q: FloatArray) -> FloatArray:
        """world_from_link (L, 4, 4) of the checked links in `collision_link_names` order at `q` (dof,).

        The array form of `link_poses`, for callers that index links by position.
        """
        self._forward(self.validate_q(q))
        root_from_frame = self._data.oMf  # Pinocchio: pose of each frame in its root (o)
        stack = np.array([root_from_frame[fid].homogeneous for fid in self._frame_id_list]).reshape(-1, 4, 4)
        return stack if self._root_is_world else self._world_from_root() @ stack

    def frame_pose(self, q: FloatArray, link_name: str) -> FloatArray:
        """world_from_link (4, 4) of any link (or frame) `link_name` at `q` (dof,)."""
        if not self._model.existFrame(link_name):
            raise ValueError(f"link_name '{link_name}' is not a frame of robot '{self._config.name}'")
        self._forward(self.validate_q(q))
        root_from_frame = self._data.oMf[self._model.getFrameId(link_name)].homogeneous
        return root_from_frame if self._root_is_world else self._world_from_root() @ root_from_frame

    def link_poses_batch(self, qs: FloatArray) -> dict[str, FloatArray]:
        """world_from_link (M, 4, 4) of every checked link for each row of `qs` (M, dof)."""
        arr = np.asarray(qs, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != self.dof:
            raise ValueError(f"qs must have shape (M, {self.dof}), got shape {arr.shape}")
        out = {name: np.empty((arr.shape[0], 4, 4)) for name in self._frame_ids}
        for k in range(arr.shape[0]):
            for name, pose in self.link_poses(self.validate_q(arr[k], f"qs[{k}]")).items():
                out[name][k] = pose
        return out


def _rooted_in_world(model: pin.Model, world_from_root: FloatArray) -> pin.Model:
    """A copy of `model` whose root frame is the world: every joint and frame hanging from the
    universe is placed by `world_from_root` (4, 4) @ its own placement."""
    out = model.copy()
    world_from_root_se3 = pin.SE3(world_from_root)
    for j in range(1, out.njoints):
        if out.parents[j] == 0:
            out.jointPlacements[j] = world_from_root_se3 * out.jointPlacements[j]
    for f in range(1, len(out.frames)):  # frame 0 is the universe itself: it stays the world origin
        frame = out.frames[f]
        if frame.parentJoint == 0:
            frame.placement = world_from_root_se3 * frame.placement
            out.frames[f] = frame
    return out


def _check_names(full: pin.Model, cfg: RobotConfig, urdf_name: str, root: ET.Element) -> None:
    """Every joint and link the config names exists; all problems reported at once."""
    names = list(full.names)
    fixed = {j.attrib["name"] for j in root.findall("joint") if j.attrib.get("type") == "fixed"}
    errors = []
    for i, name in enumerate(cfg.joint_names):
        if name not in names:
            kind = "a fixed joint" if name in fixed else "not a joint"
            errors.append(f"robot.joint_names[{i}] '{name}' is {kind} of {urdf_name} (movable joints: {names[1:]})")
        elif full.joints[names.index(name)].nq != 1:
            errors.append(f"robot.joint_names[{i}] '{name}' is not a revolute, continuous or prismatic joint")
    for name, value in cfg.fixed_joint_positions.items():
        if name in fixed:
            # MoveIt group states list gripper joints a description may have welded (the UR5's
            # Robotiq fingers): at 0 that is the joint's only position, so it is accepted.
            if value != 0.0:
                errors.append(f"robot.fixed_joint_positions.{name} is {value}, but it is a fixed joint of {urdf_name} "
                              "(only 0 is possible)")
        elif name not in names or name in cfg.joint_names or full.joints[names.index(name)].nq != 1:
            errors.append(f"robot.fixed_joint_positions names '{name}', which is not a 1-DoF non-planning joint "
                          f"of {urdf_name}")
    for label, link in (("base_link", cfg.base_link), ("end_effector_link", cfg.end_effector_link)):
        if not full.existBodyName(link):
            errors.append(f"robot.{label} '{link}' is not a link of {urdf_name}")
    if errors:
        raise ValueError("; ".join(errors))


def _continuous_as_revolute(root: ET.Element, cfg: RobotConfig) -> frozenset[str]:
    """Turn every `continuous` joint of the URDF tree `root` into a bounded revolute one, in place.

    Pinocchio models a continuous joint as a unit complex number (nq = 2), which every
    configuration vector here (one value per joint) and the compiled kinematics cannot hold.
    Planned over `position_limits_rad` or `CONTINUOUS_JOINT_RANGE_RAD` (two turns each way),
    paths, interpolation and the executor stay linear in the angle; the planner wraps only a
    query's goals to the equivalent nearest the start (`turns.py`).

    Returns:
        Names of the joints changed.
    """
    changed = set()
    for joint in root.findall("joint"):
        if joint.attrib.get("type") != "continuous":
            continue
        name = joint.attrib["name"]
        lower, upper = cfg.position_limits_rad.get(name, CONTINUOUS_JOINT_RANGE_RAD)
        joint.set("type", "revolute")
        limit = joint.find("limit")
        if limit is None:
            limit = ET.SubElement(joint, "limit", {"effort": "0", "velocity": "0"})
        limit.set("lower", repr(float(lower)))
        limit.set("upper", repr(float(upper)))
        changed.add(name)
    return frozenset(changed)


def _reduced_model(full: pin.Model, cfg: RobotConfig, locked_q: dict[str, float]) -> pin.Model:
    """`full` with every non-planning joint locked at `locked_q` (0, or neutral, when absent)."""
    q_ref = pin.neutral(full)
    locked_ids = []
    for jid in range(1, full.njoints):
        name = full.names[jid]
        if name in cfg.joint_names:
            continue
        locked_ids.append(jid)
        if full.joints[jid].nq == 1:
            q_ref[full.joints[jid].idx_q] = locked_q.get(name, 0.0)
    # Locking (rather than carrying) the other joints keeps FK to the planning joints only;
    # Pinocchio does not clamp the locked values, so fingers may sit beyond their URDF limit.
    return pin.buildReducedModel(full, locked_ids, q_ref) if locked_ids else full


def _locked_positions(root: ET.Element, cfg: RobotConfig) -> dict[str, float]:
    """Configured positions of locked joints; an unconfigured `<mimic>` joint follows its leader."""
    out = dict(cfg.fixed_joint_positions)
    for joint in root.findall("joint"):
        mimic = joint.find("mimic")
        name = joint.attrib["name"]
        if mimic is None or name in out or mimic.attrib["joint"] not in out:
            continue
        multiplier = float(mimic.attrib.get("multiplier", 1.0))
        out[name] = multiplier * out[mimic.attrib["joint"]] + float(mimic.attrib.get("offset", 0.0))
    return out


def _adjacent_pairs(
    parent_link: dict[str, str], checked: frozenset[str], geometry_links: frozenset[str]
) -> frozenset[tuple[str, str]]:
    """Sorted pairs of checked links where one is the nearest ancestor with geometry of the other.

    Links without any collision geometry (e.g. panda_link8) are skipped, so panda_link7 and
    panda_hand count as adjacent, as in MoveIt's adjacency rule.
    """
    pairs: set[tuple[str, str]] = set()
    for link in checked:
        ancestor = parent_link.get(link)
        while ancestor is not None and ancestor not in geometry_links:
            ancestor = parent_link.get(ancestor)
        if ancestor is not None and ancestor in checked:
            a, b = sorted((link, ancestor))
            pairs.add((a, b))
    return frozenset(pairs)
