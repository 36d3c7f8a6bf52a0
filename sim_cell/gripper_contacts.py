"""What the simulated gripper touches, squeezes, presses on and holds, read from pybullet's contact points.

Plan execution asks these questions every control tick: whether a free span may be jumped (the gripper
touches nothing it does not carry), what moves with the gripper (objects squeezed between both pads),
whether to stop the arm (force on the gripper and how deep what it presses on sinks in), and what a
width measurement found in the gripper.  They only read the world; the cell acts on the answers.
"""

from __future__ import annotations

import pybullet as p

from sim_cell.robot import SimRobot

SIDE_CONTACT_NZ = 0.5       # |vertical part| of a pad contact normal below which it is a side (gripping) contact


class GripperContacts:
    """Contact queries about one cell's gripper; ``objects_by_body`` is the cell's own dict of objects."""

    def __init__(self, client: int, robot: SimRobot, objects_by_body: dict, table: int):
        self._client = client
        self._robot = robot
        self._objects = objects_by_body
        self._table = table

    def between_pads(self) -> set[int]:
        """Objects squeezed between the finger pads right now (gripped, whether or not measured yet):
        touched by both pads through side contacts.  Closed fingers pressing on a top face (a shift)
        touch it from above and do not count."""
        c, rb = self._client, self._robot
        sides = []
        for link in rb.finger_links:
            sides.append({cp[2] for cp in p.getContactPoints(bodyA=rb.body, linkIndexA=link, physicsClientId=c)
                          if abs(cp[7][2]) < SIDE_CONTACT_NZ})
            if not sides[-1]:
                return set()
        return {b for b in sides[0] & sides[1] if b in self._objects}

    def pads_touch(self) -> bool:
        """Whether a finger pad touches any object."""
        c, rb = self._client, self._robot
        return any(cp[2] in self._objects
                   for link in rb.finger_links
                   for cp in p.getContactPoints(bodyA=rb.body, linkIndexA=link, physicsClientId=c))

    def touching(self, carried: set[int]) -> bool:
        """Whether the gripper touches any object it does not carry."""
        for cp in p.getContactPoints(bodyA=self._robot.body, physicsClientId=self._client):
            if cp[3] in self._robot.gripper_links and cp[2] in self._objects and cp[2] not in carried:
                return True
        return False

    def pressing_by_object(self) -> tuple[float, dict[int, float]]:
        """(vertical force on the gripper N, {object the gripper touches: its deepest penetration m})."""
        total = 0.0
        touched: set[int] = set()
        for cp in p.getContactPoints(bodyA=self._robot.body, physicsClientId=self._client):
            if cp[3] in self._robot.gripper_links:
                total += abs(cp[7][2]) * cp[9]
                if cp[2] in self._objects:
                    touched.add(cp[2])
        depths = {}
        for body in touched:
            depths[body] = max([-cp[8] for cp in p.getContactPoints(bodyA=body, physicsClientId=self._client)
                                if cp[2] != self._robot.body] or [0.0])
        return total, depths

    def pressing(self) -> tuple[float, float]:
        """(vertical force on the gripper N, deepest object penetration m while the gripper
        touches an object).  Rigid blocks squeezed between gripper and table would stop a
        real arm at once; pybullet's soft contacts let them sink instead, so depth counts too.
        Only what the gripper presses on counts: a deep contact elsewhere is not its doing."""
        force, depths = self.pressing_by_object()
        return force, max([0.0, *depths.values()])

    def held(self) -> set[int]:
        """What a width measurement finds in the gripper: objects touching both pads, and also objects
        pinched together between them (one per pad, pressed against each other) if none touches the table."""
        c, rb = self._client, self._robot
        pads = [{cp[2] for cp in p.getContactPoints(bodyA=rb.body, linkIndexA=link, physicsClientId=c)
                 if cp[2] in self._objects} for link in rb.finger_links]
        held = pads[0] & pads[1]
        # grow groups of mutually touching objects from the left pad's; a group reaching the right pad is held
        group, frontier = set(pads[0]), list(pads[0])
        while frontier:
            b = frontier.pop()
            for cp in p.getContactPoints(bodyA=b, physicsClientId=c):
                if cp[2] in self._objects and cp[2] not in group:
                    group.add(cp[2])
                    frontier.append(cp[2])
        if group & pads[1] and not any(p.getContactPoints(bodyA=b, bodyB=self._table, physicsClientId=c)
                                       for b in group):
            held |= group
        return held
