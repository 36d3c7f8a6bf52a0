"""The simulated UR5e + RG2 inside one pybullet client: loading, joint control, gripper width.

The arm (urdf/ur5e.urdf) and the gripper (urdf/rg2.urdf) are separate files,
as the real cell has two separate devices; they are joined at load time with
a fixed joint at the flange, so pybullet sees one rigid multibody and the
gripper cannot sag on a soft constraint.
"""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pybullet as p

from sim_cell import kinematics

__all__ = ["SimRobot", "URDF_DIR", "merged_urdf_text", "READY_JOINTS", "GRIPPER_TCP_OFFSET"]

URDF_DIR = Path(__file__).resolve().parent / "urdf"
ARM_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
              "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
FINGER_JOINTS = ("finger_left_joint", "finger_right_joint")
# Elbow up, wrist pointing down: the configuration the arm keeps over the table.
READY_JOINTS = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])
# Flange to the fingertip centre in urdf/rg2.urdf (tcp_joint).
GRIPPER_TCP_OFFSET = (0.0, 0.0, 0.20)
ARM_FORCE = np.array([330.0, 330.0, 150.0, 56.0, 56.0, 56.0])  # N m, motor limits of the joint servos
ARM_POSITION_GAIN = 0.35
FINGER_SPEED = 0.11  # m/s per finger
# m/s the RG2's opening changes at (its 110 mm stroke in about 1 s; datasheet: 38-127 mm/s): the time a gripper
# move takes on the cell's clock, in the simulator and the emulated RG2 alike, however fast the simulated
# fingers themselves travel
RG2_STROKE_SPEED = 0.110
FINGER_COUPLING_FORCE = 400.0  # N the linkage holds the fingers symmetric with (10x the grip force)


def merged_urdf_text() -> str:
    """ur5e.urdf with rg2.urdf attached at the flange by a fixed joint."""
    arm = ET.parse(URDF_DIR / "ur5e.urdf").getroot()
    gripper = ET.parse(URDF_DIR / "rg2.urdf").getroot()
    for material in gripper.findall("material"):
        arm.append(material)
    for element in gripper:
        if element.tag in ("link", "joint"):
            arm.append(element)
    mount = ET.SubElement(arm, "joint", {"name": "flange_gripper_joint", "type": "fixed"})
    ET.SubElement(mount, "parent", {"link": "flange"})
    ET.SubElement(mount, "child", {"link": "gripper_base"})
    ET.SubElement(mount, "origin", {"xyz": "0 0 0", "rpy": "0 0 0"})
    arm.set("name", "ur5e_rg2")
    return ET.tostring(arm, encoding="unicode")


class SimRobot:
    """Handles to the arm and gripper joints of one loaded robot."""

    def __init__(self, client: int, base_z: float = 0.0):
        self.client = client
        fd, path = tempfile.mkstemp(suffix=".urdf", prefix="ur5e_rg2_")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(merged_urdf_text())
            self.body = p.loadURDF(path, basePosition=(0.0, 0.0, base_z), useFixedBase=True,
                                   flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client)
        finally:
            os.unlink(path)
        names = {}
        links = {}
        for j in range(p.getNumJoints(self.body, physicsClientId=client)):
            info = p.getJointInfo(self.body, j, physicsClientId=client)
            names[info[1].decode()] = j
            links[info[12].decode()] = j
        self.arm_joints = [names[n] for n in ARM_JOINTS]
        self.finger_joints = [names[n] for n in FINGER_JOINTS]
        self.finger_links = [links["finger_left"], links["finger_right"]]
        self.tcp_link = links["tcp"]
        self.gripper_links = {links[n] for n in ("gripper_base", "finger_left", "finger_right", "tcp")}
        self.base_z = base_z
        self._finger_force = 40.0
        self._finger_target = 0.0
        # Joints are driven only by the explicit motors below; no default velocity motors.
        for j in self.arm_joints + self.finger_joints:
            p.changeDynamics(self.body, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                             physicsClientId=client)
        for link in self.finger_links:
            p.changeDynamics(self.body, link, lateralFriction=1.2, spinningFriction=0.003,
                             frictionAnchor=True, physicsClientId=client)
        # The RG2 drives both fingers through one linkage, so they open and close symmetrically about the
        # TCP.  Two independent force-limited fingers squeezing a block are balanced only in force: the
        # fingers and the block drift together along the closing axis under any sideways carry until one
        # finger sits on its stop (a carried block ended 15 mm off the TCP, held by one finger).
        gear = p.createConstraint(self.body, self.finger_links[0], self.body, self.finger_links[1], p.JOINT_GEAR,
                                  [1, 0, 0], [0, 0, 0], [0, 0, 0], physicsClientId=client)
        p.changeConstraint(gear, gearRatio=-1.0, maxForce=FINGER_COUPLING_FORCE, erp=0.2, physicsClientId=client)

    # ------------------------------------------------------------------ state
    def joints(self) -> np.ndarray:
        states = p.getJointStates(self.body, self.arm_joints, physicsClientId=self.client)
        return np.array([s[0] for s in states])

    def tcp_pose(self, tcp_offset: np.ndarray) -> np.ndarray:
        """TCP pose in the base frame from the joint angles (exact DH kinematics)."""
        flange = kinematics.forward(self.joints())
        flange[2, 3] += self.base_z
        out = flange.copy()
        out[:3, 3] = flange[:3, 3] + flange[:3, :3] @ tcp_offset
        return out

    def width(self) -> float:
        """Distance between the finger pads in metres."""
        states = p.getJointStates(self.body, self.finger_joints, physicsClientId=self.client)
        return float(max(states[0][0], 0.0) + max(states[1][0], 0.0))

    def finger_speed(self) -> float:
        states = p.getJointStates(self.body, self.finger_joints, physicsClientId=self.client)
        return float(max(abs(states[0][1]), abs(states[1][1])))

    # ------------------------------------------------------------------ commands
    def teleport(self, q: np.ndarray, width: float | None = None) -> None:
        """Put the arm at ``q`` at rest (used for the initial pose and for free moves)."""
        for j, v in zip(self.arm_joints, q):
            p.resetJointState(self.body, j, float(v), 0.0, physicsClientId=self.client)
        if width is not None:
            for j in self.finger_joints:
                p.resetJointState(self.body, j, width / 2.0, 0.0, physicsClientId=self.client)
            self._finger_target = width / 2.0
        self.command_arm(q)
        self.command_gripper(self._finger_target * 2.0, self._finger_force)

    def set_fingers(self, width: float, force: float) -> None:
        """Put the fingers at ``width`` at rest and hold them there (nothing in between them)."""
        half = min(max(width / 2.0, 0.0), 0.055)
        for j in self.finger_joints:
            p.resetJointState(self.body, j, half, 0.0, physicsClientId=self.client)
        self.command_gripper(width, force)

    def command_arm(self, q: np.ndarray, qd: np.ndarray | None = None) -> None:
        if qd is None:
            qd = np.zeros(6)
        p.setJointMotorControlArray(self.body, self.arm_joints, p.POSITION_CONTROL,
                                    targetPositions=[float(v) for v in q],
                                    targetVelocities=[float(v) for v in qd],
                                    forces=ARM_FORCE.tolist(),
                                    positionGains=[ARM_POSITION_GAIN] * 6,
                                    velocityGains=[1.0] * 6,
                                    physicsClientId=self.client)

    def command_gripper(self, width: float, force: float) -> None:
        """Drive both fingers towards ``width`` (m between pads) pushing with at most ``force`` (N)."""
        self._finger_target = min(max(width / 2.0, 0.0), 0.055)
        self._finger_force = force
        for j in self.finger_joints:
            p.setJointMotorControl2(self.body, j, p.POSITION_CONTROL, targetPosition=self._finger_target,
                                    force=force, maxVelocity=FINGER_SPEED, positionGain=0.2,
                                    physicsClientId=self.client)

    def finger_target_width(self) -> float:
        return 2.0 * self._finger_target
