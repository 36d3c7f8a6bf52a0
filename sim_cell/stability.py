"""Stability checks and sleeping of the simulated cell's objects (see sim_cell.cell's module docstring).

Every eighth physics step the cell checks each object: a non-finite state, a flight faster than
``MAX_OBJECT_SPEED`` or an object thrown a metre up is unstable physics, and so (every sixth check, the
deep check) is an interpenetration that lasts or is gross.  An object that fell off the table is gone.
The same check counts how long each object has been still and puts still ones to sleep, so that the
solver skips a resting pile; the cell wakes what loses its support when an object is removed or moved
by hand.  The rules live here, apart from the plan execution that steps the world.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pybullet as p

from sim_cell import objects

MAX_OBJECT_SPEED = 4.0      # m/s; faster = unstable
MAX_PENETRATION = 0.015     # m of interpenetration that is unstable when it lasts PENETRATION_CHECKS deep checks
PENETRATION_CHECKS = 3      # deep checks (0.2 s apart): a finger wedging a prism can dip it 15-30 mm for a moment
GROSS_PENETRATION = 0.04    # m: unstable at once
# An object whose centre is this far below the table top has fallen off the table (there is no floor):
# it is out of the cell at once.  Left falling, it passed MAX_OBJECT_SPEED after 0.8 m and the scene was
# reset as "unstable" -- 1 run in 10 of the shipped policy on 20 blocks, a block that slipped out of the
# fingers at the home pose and rolled off the table edge.
FALLEN_DEPTH = 0.05         # m
# Still: slower than these.  A dropped scene is stepped until every object is still (the camera and the
# first grasp must not meet a block still rolling or rocking), and no line is jumped while anything moves.
STILL_SPEED = 0.01          # m/s
STILL_SPIN = 0.2            # rad/s
# Sleeping: an object still for SLEEP_CHECKS stability checks in a row (0.2 s) and touching neither the
# gripper nor anything awake-and-moving is put to sleep (the solver skips it: a resting 20-block pile
# costs 0.08 ms per step asleep against 4.7 ms awake at 150 iterations).  Bullet wakes it when an
# awake body touches it; the cell wakes everything near an object it removes or moves by hand.
# Still enough to sleep: |v|^2 + |w|^2 (m/s, rad/s) below SLEEP_MOTION, i.e. slower than 5 mm/s and
# 0.005 rad/s.  The same number is Bullet's own rule (sleep after 2 s below it, wake above it), so a
# body put to sleep here is not woken again by Bullet at its next step.
SLEEP_MOTION = 0.005 ** 2
SLEEP_CHECKS = 6            # consecutive checks (8 physics steps apart)
WAKE_MARGIN = 0.02          # m around a removed or moved object within which sleepers are woken


class Unstable(Exception):
    """The physics went wrong; the scene must not be learned from."""


class Stability:
    """The stability checks and the sleep bookkeeping of one cell's objects.

    ``objects`` is the cell's own dict of bodies (read, never changed here); an object found fallen off
    the table is handed to the cell's ``remove_fallen`` so that its bookkeeping stays in one place.
    """

    def __init__(self, client: int, objects_by_body: dict, gripper_body: int, table_z: float):
        self._client = client
        self._objects = objects_by_body
        self._gripper_body = gripper_body
        self._table_z = table_z
        self._deep_contacts: dict[tuple[int, int], int] = {}  # body pair -> consecutive deep checks
        self._still_checks: dict[int, int] = {}  # body -> consecutive stability checks it was still
        self._insomniac: set[int] = set()        # bodies woken by hand, may sleep again from the next check

    def reset(self) -> None:
        """Forget every object (the scene was cleared)."""
        self._deep_contacts = {}
        self._still_checks = {}
        self._insomniac = set()

    def forget(self, body: int) -> None:
        """``body`` left the scene."""
        self._still_checks.pop(body, None)

    def check(self, deep: bool, held: set[int], remove_fallen: Callable[[int], None]) -> None:
        """One stability check (raises ``Unstable``); still objects that are not ``held`` go to sleep."""
        c = self._client
        for body in self._insomniac:
            if body in self._objects:
                p.changeDynamics(body, -1, activationState=p.ACTIVATION_STATE_ENABLE_SLEEPING, physicsClientId=c)
        self._insomniac = set()
        drowsy = []
        for body in list(self._objects):
            pos, _ = p.getBasePositionAndOrientation(body, physicsClientId=c)
            lin, ang = p.getBaseVelocity(body, physicsClientId=c)
            if not all(map(math.isfinite, (*pos, *lin))):
                raise Unstable(f"object {body} has a non-finite state")
            if pos[2] < self._table_z - FALLEN_DEPTH:   # fell off the table: gone, as _remove_outside has it
                remove_fallen(body)
                continue
            speed = math.sqrt(sum(v * v for v in lin))
            if speed > MAX_OBJECT_SPEED:
                raise Unstable(f"object {body} flies at {speed:.1f} m/s")
            if pos[2] > self._table_z + 1.0:
                raise Unstable(f"object {body} thrown {pos[2]:.2f} m up")
            if speed * speed + sum(v * v for v in ang) < SLEEP_MOTION:
                n = self._still_checks.get(body, 0) + 1
                self._still_checks[body] = n
                if n % SLEEP_CHECKS == 0:
                    drowsy.append(body)
            else:
                self._still_checks[body] = 0
        if drowsy:
            self._put_to_sleep(drowsy, held)
        if deep:
            self._check_penetration()

    def _check_penetration(self) -> None:
        # A deep contact the solver resolves within a few checks is a transient (a closing finger
        # wedging a sloped block into the table); one that persists, or is gross, is not.
        deep_now: dict[tuple[int, int], float] = {}
        for cp in p.getContactPoints(physicsClientId=self._client):
            if cp[8] < -MAX_PENETRATION and (cp[1] in self._objects or cp[2] in self._objects):
                pair = (min(cp[1], cp[2]), max(cp[1], cp[2]))
                deep_now[pair] = max(deep_now.get(pair, 0.0), -cp[8])
        self._deep_contacts = {pair: self._deep_contacts.get(pair, 0) + 1 for pair in deep_now}
        for pair, depth in deep_now.items():
            if depth > GROSS_PENETRATION or self._deep_contacts[pair] >= PENETRATION_CHECKS:
                lasting = "" if depth > GROSS_PENETRATION else f" for {self._deep_contacts[pair]} checks"
                self._deep_contacts = {}
                raise Unstable(f"bodies {pair[0]} and {pair[1]} interpenetrate by {depth * 1000:.0f} mm"
                               f"{lasting}")

    def _put_to_sleep(self, bodies: list[int], held: set[int]) -> None:
        """Let still objects sleep, except what the gripper touches or holds (it squeezes or carries them)."""
        c = self._client
        touched = {cp[2] for cp in p.getContactPoints(bodyA=self._gripper_body, physicsClientId=c)}
        for body in bodies:
            if body not in touched and body not in held:
                p.changeDynamics(body, -1, activationState=p.ACTIVATION_STATE_SLEEP, physicsClientId=c)

    def wake_near(self, body: int) -> None:
        """Wake every object within WAKE_MARGIN of ``body``'s bounds (it is about to be removed or moved)."""
        c = self._client
        lo, hi = objects.body_aabb(body, c)
        lo, hi = lo - WAKE_MARGIN, hi + WAKE_MARGIN
        for other in self._objects:
            if other == body:
                continue
            a, b = objects.body_aabb(other, c)
            if np.all(a <= hi) and np.all(b >= lo):
                self.wake(other)

    def wake(self, body: int) -> None:
        """Wake ``body`` for sure: a plain wake-up request is undone by its still-sleeping island, so
        sleeping is switched off until the next stability check (at least one step later)."""
        p.changeDynamics(body, -1, activationState=p.ACTIVATION_STATE_WAKE_UP | p.ACTIVATION_STATE_DISABLE_SLEEPING,
                         physicsClientId=self._client)
        self._insomniac.add(body)
        self._still_checks[body] = 0

    def moving(self, exclude: set[int] | frozenset[int] = frozenset()) -> list[int]:
        """Objects (other than ``exclude``) moving faster than STILL_SPEED or turning faster than STILL_SPIN."""
        out = []
        for body in self._objects:
            if body in exclude:
                continue
            lin, ang = p.getBaseVelocity(body, physicsClientId=self._client)
            if np.linalg.norm(lin) > STILL_SPEED or np.linalg.norm(ang) > STILL_SPIN:
                out.append(body)
        return out
