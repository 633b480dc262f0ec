"""Scripted experts for the robosuite tasks: waypoint controllers on the true object pose.

robomimic's human datasets cannot be downloaded here, so demonstrations come from these experts. They
are far more uniform than human data: say so next to every success rate obtained from them.
"""
from __future__ import annotations

import numpy as np

__all__ = ["LiftExpert", "CanExpert", "SquareExpert", "EXPERTS"]


_DOWN = np.diag([1.0, -1.0, -1.0])  # the hand pointing down at yaw 0: fingers close along world y


def _wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def _yaw(quat_xyzw: np.ndarray) -> float:
    """Heading of a body's x axis in the world xy plane (the hand's yaw, or an object's)."""
    from scipy.spatial.transform import Rotation

    m = Rotation.from_quat(quat_xyzw).as_matrix()
    return float(np.arctan2(m[1, 0], m[0, 0]))


def _turn(quat_xyzw: np.ndarray, yaw: float, gain: float = 1.0) -> np.ndarray:
    """Rotation command in [-1, 1] toward the hand pointing down at ``yaw`` (OSC_POSE scales 1.0 to
    0.5 rad per step, as an axis-angle in the base frame applied to the current orientation)."""
    from scipy.spatial.transform import Rotation

    current = Rotation.from_quat(quat_xyzw).as_matrix()
    want = Rotation.from_euler("z", yaw).as_matrix() @ _DOWN
    return np.clip(gain * Rotation.from_matrix(want @ current.T).as_rotvec() / 0.5, -1.0, 1.0)


def _toward(eef: np.ndarray, target: np.ndarray, gain: float = 10.0) -> np.ndarray:
    """Delta-position command in [-1, 1] (OSC_POSE scales 1.0 to 5 cm per step)."""
    return np.clip(gain * (target - eef), -1.0, 1.0)


class _Waypoints:
    """A sequence of phases; each phase returns (position target, gripper, done?).

    ``noisy_phases``: phases in which demonstration collection may perturb the executed action
    (DART-style noise injection: the clean expert action is recorded, so the data shows how to
    recover from the perturbed states a learned policy drifts into)."""

    noisy_phases: tuple[int, ...] = ()

    def __init__(self, env):
        self.env = env
        self.phase = 0
        self.counter = 0

    def _action(self, eef: np.ndarray, target: np.ndarray, grip: float, gain: float = 10.0) -> np.ndarray:
        a = np.zeros(7)
        a[:3] = _toward(eef, target, gain)
        a[6] = grip
        return a


class LiftExpert(_Waypoints):
    """Above the cube, down, close, lift."""

    noisy_phases = (0, 1)

    def act(self, raw: dict) -> np.ndarray:
        eef, cube = raw["robot0_eef_pos"], raw["cube_pos"]
        if self.phase == 0:  # above
            target = cube + [0, 0, 0.08]
            if np.linalg.norm(eef - target) < 0.01:
                self.phase = 1
            return self._action(eef, target, -1)
        if self.phase == 1:  # descend
            target = cube + [0, 0, -0.005]
            if np.linalg.norm(eef - target) < 0.008:
                self.phase, self.counter = 2, 0
            return self._action(eef, target, -1)
        if self.phase == 2:  # grasp
            self.counter += 1
            if self.counter > 8:
                self.phase = 3
            return self._action(eef, cube + [0, 0, -0.005], 1)
        return self._action(eef, cube + [0, 0, 0.25], 1, gain=5.0)  # lift


class CanExpert(_Waypoints):
    """Above the can, down, grip, lift, carry over the target bin, lower, release.

    If the can is not in the hand while lifting or carrying (a missed grasp, or a drop), the expert
    starts again from above the can, so perturbed demonstrations also show re-grasping."""

    noisy_phases = (0, 1, 4)

    def act(self, raw: dict) -> np.ndarray:
        env = self.env
        eef, can = raw["robot0_eef_pos"], raw["Can_pos"]
        goal = np.array(env.target_bin_placements[env.object_to_id["can"]])
        if self.phase in (3, 4, 5) and np.linalg.norm(eef - (can + [0, 0, 0.005])) > 0.05:
            self.phase, self.counter = 0, 0  # the can is not between the fingers: start over
        if self.phase == 0:
            target = can + [0, 0, 0.1]
            if np.linalg.norm(eef - target) < 0.01:
                self.phase = 1
            return self._action(eef, target, -1)
        if self.phase == 1:  # the fingertips stop ~1 cm above the can's centre
            target = can + [0, 0, 0.005]
            self.counter += 1
            if np.linalg.norm(eef - target) < 0.012 or self.counter > 40:
                self.phase, self.counter = 2, 0
            return self._action(eef, target, -1)
        if self.phase == 2:
            self.counter += 1
            if self.counter > 10:
                self.phase = 3
            return self._action(eef, can + [0, 0, 0.005], 1)
        if self.phase == 3:  # lift
            target = np.array([eef[0], eef[1], goal[2] + 0.2])
            if eef[2] > goal[2] + 0.17:
                self.phase = 4
            return self._action(eef, target, 1)
        if self.phase == 4:  # carry
            target = np.array([goal[0], goal[1], goal[2] + 0.2])
            if np.linalg.norm(eef[:2] - target[:2]) < 0.015:
                self.phase = 5
            return self._action(eef, target, 1, gain=6.0)
        if self.phase == 5:  # lower
            target = np.array([goal[0], goal[1], goal[2] + 0.1])
            if eef[2] < goal[2] + 0.12:
                self.phase, self.counter = 6, 0
            return self._action(eef, target, 1)
        self.counter += 1  # release, then move away (success needs the gripper > 4 cm from the can)
        z = goal[2] + (0.1 if self.counter < 8 else 0.25)
        return self._action(eef, np.array([goal[0], goal[1], z]), -1)


class SquareExpert(_Waypoints):
    """Grasp the square nut by its handle, lift it above the peg top, carry it over the square peg
    while turning it to a multiple of 90 degrees, lower it around the peg, release.

    The hand turns to the handle's axis (of the two grasps 180 degrees apart, the one nearer its
    current yaw) so the fingers close across the handle, 1.2 cm outward of the handle site (the
    fingers then clear the nut's ring). Over the peg the nut's handle is turned to point left,
    right or toward the robot (never away: the arm cannot reach over the peg that far at carrying
    height), whichever needs the least turn within the wrist's range. While carrying and lowering,
    the hand target follows the nut's true position, so slip in the grasp is corrected. If the nut
    is not in the hand while lifting or carrying, the expert starts again from above the handle."""

    noisy_phases = (0, 1, 4)
    carry_z = 1.01  # nut bottom 1 cm above the peg top (0.95 m) when the hand is at this height
    handle_out = 0.012
    hand_yaw_range = (-1.9, 3.0)  # hand yaws the Panda's last joint reaches from its start (q7 ~ 0.8 - yaw)

    def __init__(self, env):
        super().__init__(env)
        self.yaw = None
        self.handle_dir = None

    def _handle(self, psi: float) -> np.ndarray:
        env = self.env
        site = np.array(env.sim.data.site_xpos[env.object_site_ids[env.nut_id]])
        return site + self.handle_out * np.array([np.cos(psi), np.sin(psi), 0.0])

    def act(self, raw: dict) -> np.ndarray:
        env = self.env
        eef, quat = raw["robot0_eef_pos"], raw["robot0_eef_quat"]
        nut, psi = raw["SquareNut_pos"], _yaw(raw["SquareNut_quat"])
        peg = np.array(env.sim.data.body_xpos[env.peg1_body_id])
        handle = self._handle(psi)
        hand = _yaw(quat)

        def command(target, grip, yaw, gain=10.0):
            a = self._action(eef, target, grip, gain)
            a[3:6] = _turn(quat, yaw)
            return a

        if self.phase in (3, 4, 5) and np.linalg.norm(eef - handle) > 0.04:
            self.phase, self.counter = 0, 0  # the handle is not between the fingers: start over
        if self.phase == 0:  # above the handle, fingers across it
            self.yaw = psi + np.pi * np.round((hand - psi) / np.pi)
            target = handle + [0, 0, 0.08]
            if np.linalg.norm(eef - target) < 0.01 and abs(_wrap(hand - self.yaw)) < 0.05:
                self.phase, self.counter = 1, 0
            return command(target, -1, self.yaw)
        if self.phase == 1:  # descend
            self.counter += 1
            if np.linalg.norm(eef - handle) < 0.008 or self.counter > 40:
                self.phase, self.counter = 2, 0
            return command(handle, -1, self.yaw)
        if self.phase == 2:  # grasp
            self.counter += 1
            if self.counter > 10:
                self.phase = 3
            return command(handle, 1, self.yaw)
        if self.phase == 3:  # lift
            if eef[2] > self.carry_z - 0.02:
                self.phase = 4
                self.handle_dir = self._placement_yaw(hand, psi)
            return command(np.array([eef[0], eef[1], self.carry_z]), 1, hand)
        # carry / lower / release: the hand turns by the nut's remaining yaw error
        yaw = hand + _wrap(self.handle_dir - psi)
        grip_offset = eef - nut
        if self.phase == 4:  # carry over the peg
            target = np.array([peg[0] + grip_offset[0], peg[1] + grip_offset[1], self.carry_z])
            if np.linalg.norm(nut[:2] - peg[:2]) < 0.004 and abs(_wrap(self.handle_dir - psi)) < 0.05:
                self.phase = 5
            return command(target, 1, yaw, gain=8.0)
        if self.phase == 5:  # lower around the peg
            target = np.array([peg[0] + grip_offset[0], peg[1] + grip_offset[1], 0.80 + grip_offset[2]])
            if nut[2] < env.table_offset[2] + 0.04:
                self.phase, self.counter = 6, 0
            return command(target, 1, yaw, gain=6.0)
        self.counter += 1  # release, then lift the hand away
        return command(np.array([eef[0], eef[1], eef[2] + (0.0 if self.counter < 6 else 0.1)]), -1, hand)

    def _placement_yaw(self, hand: float, psi: float) -> float:
        """Handle direction over the peg: left, toward the robot or right, least turn first."""
        lo, hi = self.hand_yaw_range
        options = [(abs(_wrap(d - psi)), d) for d in (np.pi / 2, np.pi, -np.pi / 2)]
        return min([o for o in options if lo < hand + _wrap(o[1] - psi) < hi] or options)[1]


EXPERTS = {"lift": LiftExpert, "can": CanExpert, "square": SquareExpert}
