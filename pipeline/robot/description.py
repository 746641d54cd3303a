"""A robot config derived from a URDF and (optionally) a MoveIt SRDF, as `robonav robot init` writes it.

What comes from where:

- planning joints: the SRDF group (its chains, joints, links and subgroups, MoveIt's rules), or
  without an SRDF the movable joints on the chain from the URDF's root to `tip`;
- position limits: the URDF's (the model reads them; nothing is copied); velocity limits: the
  URDF's `<limit velocity>`; acceleration and jerk: URDFs carry none, so they follow
  `ACCELERATION_PER_VELOCITY_PER_S` and `JERK_PER_ACCELERATION_PER_S` and are flagged for review;
- allowed-collision pairs: the SRDF's `<disable_collisions>`, or without an SRDF the sampled matrix
  of `acm.generate_acm` (adjacent, default, always and never in collision, as MoveIt's setup
  assistant does);
- home: the group's SRDF state named `home` (else `ready`), or every joint at 0 (mid-range where
  0 is outside its limits); the end-effector link: `tip`, else the chain's tip, else the SRDF
  end effector attached to the group, else the last link the group moves;
- joints outside the group: held at a value an SRDF state of another group gives (the first one
  listed), else 0 (mid-range where 0 is outside the limits); mimic joints follow their leader.

The world frame is the URDF's root link.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from robonav.pipeline.robot.config import CONTINUOUS_JOINT_RANGE_RAD, RobotConfig

ACCELERATION_PER_VELOCITY_PER_S = 4.0
"""Default acceleration limit = 4/s x the velocity limit: full speed in 0.25 s (the Panda's
datasheet ratios span 3.4-7.7/s). To be checked against the robot's datasheet."""
JERK_PER_ACCELERATION_PER_S = 500.0
"""Default jerk limit = 500/s x the acceleration limit (the Panda's datasheet ratio)."""
DEFAULT_VELOCITY_RAD_S = 1.0
"""Used (and flagged) when a URDF joint gives no positive velocity limit [rad/s or m/s]."""
HOME_STATE_NAMES = ("home", "ready")
MOVABLE_TYPES = ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class UrdfJoint:
    """One `<joint>` of a URDF: what robot init needs of it."""

    name: str
    type: str
    parent: str
    child: str
    lower: float | None = None
    upper: float | None = None
    velocity: float | None = None
    mimic: str | None = None


@dataclass(frozen=True)
class SrdfGroup:
    name: str
    chains: tuple[tuple[str, str], ...] = ()
    joints: tuple[str, ...] = ()
    links: tuple[str, ...] = ()
    subgroups: tuple[str, ...] = ()


@dataclass(frozen=True)
class SrdfDescription:
    """The parts of a MoveIt SRDF robot init uses."""

    groups: dict[str, SrdfGroup] = field(default_factory=dict)
    group_states: tuple[tuple[str, str, dict[str, float]], ...] = ()
    """(group, state name, joint -> value) in document order."""
    disabled_collisions: tuple[tuple[str, str, str], ...] = ()
    """(link1, link2, reason) in document order."""
    end_effectors: tuple[tuple[str, str, str], ...] = ()
    """(name, parent_link, parent_group or '') in document order."""


@dataclass(frozen=True)
class RobotDescription:
    """The derived config plus what a reader of the written file should know."""

    config: RobotConfig
    group: str
    notes: tuple[str, ...]
    """Points to review (e.g. derived limits), one line each."""
    pair_reasons: dict[tuple[str, str], str]
    """Allowed pair -> why (the SRDF's reason or the sampling's)."""


def read_urdf(urdf_path: Path) -> tuple[str, dict[str, UrdfJoint], tuple[str, ...]]:
    """Root link, joints by name (document order) and every link name of a URDF file.

    Raises:
        ValueError: unreadable XML, no links, or not exactly one root link.
    """
    try:
        root = ET.parse(urdf_path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise ValueError(f"{urdf_path}: cannot read the URDF: {exc}") from exc
    links = tuple(link.attrib["name"] for link in root.findall("link"))
    joints: dict[str, UrdfJoint] = {}
    for joint in root.findall("joint"):
        limit, mimic = joint.find("limit"), joint.find("mimic")

        def number(key: str, element: ET.Element | None = limit) -> float | None:
            return float(element.attrib[key]) if element is not None and key in element.attrib else None

        joints[joint.attrib["name"]] = UrdfJoint(
            joint.attrib["name"], joint.attrib.get("type", ""), joint.find("parent").attrib["link"],
            joint.find("child").attrib["link"], number("lower"), number("upper"), number("velocity"),
            mimic.attrib.get("joint") if mimic is not None else None)
    children = {j.child for j in joints.values()}
    roots = [link for link in links if link not in children]
    if len(roots) != 1:
        raise ValueError(f"{urdf_path}: expected one root link, found {roots or 'none'}")
    return roots[0], joints, links


def parse_srdf(srdf_path: Path) -> SrdfDescription:
    """Groups, group states, disabled collision pairs and end effectors of a MoveIt SRDF file.

    Raises:
        ValueError: unreadable XML.
    """
    try:
        root = ET.parse(srdf_path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise ValueError(f"{srdf_path}: cannot read the SRDF: {exc}") from exc
    groups = {}
    for g in root.findall("group"):
        groups[g.attrib["name"]] = SrdfGroup(
            g.attrib["name"],
            tuple((c.attrib["base_link"], c.attrib["tip_link"]) for c in g.findall("chain")),
            tuple(j.attrib["name"] for j in g.findall("joint")),
            tuple(link.attrib["name"] for link in g.findall("link")),
            tuple(s.attrib["name"] for s in g.findall("group")))
    states = tuple((s.attrib["group"], s.attrib["name"],
                    {j.attrib["name"]: float(j.attrib["value"].split()[0]) for j in s.findall("joint")})
                   for s in root.findall("group_state"))
    disabled = tuple((d.attrib["link1"], d.attrib["link2"], d.attrib.get("reason", ""))
                     for d in root.findall("disable_collisions"))
    effectors = tuple((e.attrib["name"], e.attrib["parent_link"], e.attrib.get("parent_group", ""))
                      for e in root.findall("end_effector"))
    return SrdfDescription(groups, states, disabled, effectors)


def chain_joint_names(joints: dict[str, UrdfJoint], base_link: str, tip_link: str) -> list[str]:
    """Every joint (fixed ones too) from `base_link` down to `tip_link`, top first.

    Raises:
        ValueError: `tip_link` does not hang below `base_link`.
    """
    parent_joint = {j.child: j for j in joints.values()}
    out = []
    link = tip_link
    while link != base_link:
        joint = parent_joint.get(link)
        if joint is None:
            raise ValueError(f"link '{tip_link}' does not hang below '{base_link}'")
        out.append(joint.name)
        link = joint.parent
    return out[::-1]


def group_joint_names(srdf: SrdfDescription, group: str, joints: dict[str, UrdfJoint]) -> list[str]:
    """Movable, non-mimic joints of an SRDF group in URDF order (MoveIt's rules: a chain brings its
    joints, a link its parent joint, subgroups theirs).

    Raises:
        ValueError: unknown group, or the group moves no joint.
    """
    if group not in srdf.groups:
        raise ValueError(f"SRDF has no group '{group}' (groups: {sorted(srdf.groups)})")
    names: set[str] = set()
    pending, seen = [group], set()
    parent_joint = {j.child: j.name for j in joints.values()}
    while pending:
        g = srdf.groups.get(pending.pop())
        if g is None or g.name in seen:
            continue
        seen.add(g.name)
        for base, tip in g.chains:
            names.update(chain_joint_names(joints, base, tip))
        names.update(g.joints)
        names.update(parent_joint[link] for link in g.links if link in parent_joint)
        pending.extend(g.subgroups)
    out = [n for n in joints if n in names and joints[n].type in MOVABLE_TYPES and joints[n].mimic is None]
    if not out:
        raise ValueError(f"SRDF group '{group}' moves no revolute, continuous or prismatic joint")
    return out


def describe_robot(
    urdf_path: Path,
    srdf: SrdfDescription | None = None,
    *,
    urdf_reference: str | None = None,
    group: str | None = None,
    tip_link: str | None = None,
    package_paths: tuple[str, ...] = (),
    sampled_acm: dict[tuple[str, str], str] | None = None,
    name: str | None = None,
) -> RobotDescription:
    """Derive the robot config (see the module doc for the rules).

    Args:
        urdf_path: The URDF file.
        srdf: The parsed SRDF, or None.
        urdf_reference: What the config's `urdf` says (e.g. a path relative to the robot file);
            None writes `urdf_path`.
        group: SRDF planning group; None takes the only group with a chain, else the first group.
        tip_link: End-effector link; required without an SRDF (the chain from the root to it plans).
        package_paths: Written to the config as they are.
        sampled_acm: Without an SRDF, the allowed pairs with their reasons (`acm.generate_acm`,
            which needs the model this function's config describes: the caller runs it and calls
            again); None leaves the pairs empty.
        name: Robot name; None takes the URDF's `<robot name>`.

    Raises:
        ValueError: an unknown group or link, or a chain that moves no joint.
    """
    root_link, joints, links = read_urdf(urdf_path)
    notes: list[str] = []
    chosen_group = ""
    if srdf is not None and srdf.groups:
        chained = [g.name for g in srdf.groups.values() if g.chains]
        chosen_group = group or (chained[0] if len(chained) == 1 else next(iter(srdf.groups)))
        joint_names = group_joint_names(srdf, chosen_group, joints)
    else:
        if tip_link is None:
            raise ValueError("without an SRDF, --tip LINK names the end of the chain to plan for")
        joint_names = [n for n in chain_joint_names(joints, root_link, tip_link)
                       if joints[n].type in MOVABLE_TYPES and joints[n].mimic is None]
        if not joint_names:
            raise ValueError(f"the chain from '{root_link}' to '{tip_link}' moves no joint")
    if tip_link is not None and tip_link not in links:
        raise ValueError(f"--tip '{tip_link}' is not a link of {urdf_path.name}")
    end_effector = tip_link or _end_effector(srdf, chosen_group, joints, joint_names)

    velocities = []
    for n in joint_names:
        v = joints[n].velocity
        if v is None or not v > 0:
            notes.append(f"{n}: the URDF gives no velocity limit; {DEFAULT_VELOCITY_RAD_S} used")
            v = DEFAULT_VELOCITY_RAD_S
        velocities.append(float(v))
    acceleration = [ACCELERATION_PER_VELOCITY_PER_S * v for v in velocities]
    jerk = [JERK_PER_ACCELERATION_PER_S * a for a in acceleration]
    notes.append(f"max_acceleration_rad_s2 = {ACCELERATION_PER_VELOCITY_PER_S:g}/s x velocity and max_jerk_rad_s3 = "
                 f"{JERK_PER_ACCELERATION_PER_S:g}/s x acceleration (URDFs carry neither): check the datasheet")
    notes.append("max_velocity_rad_s is the URDF's <limit velocity>: check it is the real robot's")

    states = srdf.group_states if srdf is not None else ()
    home_state = next((values for wanted in HOME_STATE_NAMES for g, s, values in states
                       if g == chosen_group and s == wanted), None)
    home = []
    for n in joint_names:
        value = home_state.get(n) if home_state is not None else None
        home.append(float(value) if value is not None else _default_position(joints[n]))
    if home_state is None:
        notes.append("home_position_rad: no SRDF state 'home' or 'ready' for the group; every joint at 0 "
                     "(mid-range where 0 is outside the limits)")

    fixed: dict[str, float] = {}
    for n, joint in joints.items():
        if n in joint_names or joint.type not in MOVABLE_TYPES or joint.mimic is not None:
            continue
        value = next((values[n] for g, _, values in states if g != chosen_group and n in values), None)
        fixed[n] = float(value) if value is not None else _default_position(joint)

    reasons: dict[tuple[str, str], str] = {}
    link_set = set(links)
    if srdf is not None and srdf.disabled_collisions:
        for a, b, why in srdf.disabled_collisions:
            if a in link_set and b in link_set and a != b:
                reasons[tuple(sorted((a, b)))] = why or "srdf"  # type: ignore[index]
    elif sampled_acm is not None:
        reasons = dict(sampled_acm)

    continuous = [n for n in joint_names if joints[n].type == "continuous"]
    if continuous:
        notes.append(f"continuous joints {continuous} are planned over {CONTINUOUS_JOINT_RANGE_RAD[0]:.4f}.."
                     f"{CONTINUOUS_JOINT_RANGE_RAD[1]:.4f} rad unless position_limits_rad names them")
    robot_name = name or ET.parse(urdf_path).getroot().attrib.get("name", "robot")
    config = RobotConfig(
        name=robot_name, urdf=urdf_reference if urdf_reference is not None else str(urdf_path),
        base_link=root_link, end_effector_link=end_effector, joint_names=tuple(joint_names),
        fixed_joint_positions=fixed, max_velocity_rad_s=tuple(velocities),
        max_acceleration_rad_s2=tuple(acceleration), max_jerk_rad_s3=tuple(jerk),
        home_position_rad=tuple(home), allowed_collision_pairs=tuple(sorted(reasons)),
        package_paths=tuple(package_paths),
    )
    return RobotDescription(config, chosen_group, tuple(notes), reasons)


def _end_effector(srdf: SrdfDescription | None, group: str, joints: dict[str, UrdfJoint],
                  joint_names: list[str]) -> str:
    if srdf is not None and group in srdf.groups:
        chains = srdf.groups[group].chains
        if chains:
            return chains[-1][1]
        for _, parent_link, parent_group in srdf.end_effectors:
            if parent_group == group:
                return parent_link
    return joints[joint_names[-1]].child


def _default_position(joint: UrdfJoint) -> float:
    """0, or the middle of the limits when 0 is outside them (MoveIt's default state)."""
    lower = joint.lower if joint.lower is not None else -math.inf
    upper = joint.upper if joint.upper is not None else math.inf
    if joint.type == "continuous" or lower <= 0.0 <= upper:
        return 0.0
    return 0.5 * (lower + upper)
