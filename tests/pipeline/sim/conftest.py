"""What the sim tests share."""

from __future__ import annotations

from pathlib import Path

import pytest

SPINNER_URDF = """<?xml version="1.0"?>
<robot name="spinner">
  <link name="foot"><collision><geometry><box size="0.2 0.2 0.1"/></geometry></collision></link>
  <link name="arm"><collision><origin xyz="0.15 0 0"/><geometry><box size="0.3 0.04 0.04"/></geometry></collision>
    <inertial><mass value="0.5"/><inertia ixx="0.0001" iyy="0.004" izz="0.004" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="slider"><collision><geometry><sphere radius="0.03"/></geometry></collision>
    <inertial><mass value="0.1"/><inertia ixx="0.0001" iyy="0.0001" izz="0.0001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="spin" type="continuous"><parent link="foot"/><child link="arm"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit effort="20" velocity="2"/></joint>
  <joint name="slide" type="prismatic"><parent link="arm"/><child link="slider"/><origin xyz="0.1 0 0"/>
    <axis xyz="1 0 0"/><limit lower="0.0" upper="0.2" effort="20" velocity="0.5"/></joint>
</robot>
"""


@pytest.fixture
def spinner_urdf(tmp_path: Path) -> Path:
    """A URDF of an arm turning without end (continuous) on a foot, a slider along it (prismatic)."""
    urdf = tmp_path / "spinner.urdf"
    urdf.write_text(SPINNER_URDF, encoding="utf-8")
    return urdf
