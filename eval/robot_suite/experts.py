"""Scripted experts for the robosuite tasks: waypoint controllers on the true object pose.

robomimic's human datasets cannot be downloaded here, so demonstrations come from these experts. They
are far more uniform than human data: say so next to every success rate obtained from them.
"""
from __future__ import annotations

import numpy as np

__all__ = ["LiftExpert", "CanExpert", "EXPERTS"]


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


EXPERTS = {"lift": LiftExpert, "can": CanExpert}
