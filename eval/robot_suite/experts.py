"""Scripted experts for the robosuite tasks: waypoint controllers on the true object pose.

robomimic's human datasets cannot be downloaded here, so demonstrations come from these experts. They
are far more uniform than human data: say so next to every success rate obtained from them.

Mixed-quality operators (a stand-in for robomimic's multi-human "MH" data)
--------------------------------------------------------------------------
robomimic's MH datasets come from 6 operators, 50 successful demos each: 2 "better", 2 "okay" and
2 "worse" (slower, shakier, more failed attempts; failed demos are not kept). :data:`OPERATORS`
gives each task six scripted operators in the same proportions. Each is the task's expert run
with an :class:`Operator` style:

* strategy, which makes the data multimodal: the approach path (a via point to the left, right or
  far side of the object before going above it, or straight above), the hand's yaw at the grasp
  (which of the object's symmetric grasps, or turning clockwise vs counter-clockwise, or not turning
  at all), the grasp point (along the cube's face, up the can, along the nut's handle) and, for the
  nut, which way its handle points when it goes on the peg;
* skill, which makes it mixed-quality: speed (a factor on every position gain), hesitations
  (pauses of several steps, holding still, that start with some probability per step while
  approaching or carrying), deliberate misses (a grasp 3.5-5 cm off the object, noticed when the
  object does not come up, then a corrective re-grasp), giving up after a number of failed grasps,
  and action noise (temporally correlated and signal-dependent, larger on fast moves than near the
  object, as in human reaching; *recorded* in the demo, unlike the DART noise of
  ``collect_demos.py --noise``, which is executed but not recorded).

Strategies per task: Lift, the hand yaw picks the cube face alignment (every 90 degrees) nearest
0 or +-45 degrees (i.e. turns whichever way is shorter, always counter-clockwise, always clockwise),
or the hand does not turn; Can, the hand holds 0, +-45 or 90 degrees (turning about the vertical
only: held vertical, the hand cannot reach the goal bin's far corner) or does not turn; Square,
of the handle's two grasps 180 degrees apart, the one nearest +0.8 or -0.8 rad or the current
yaw, and the handle goes on the peg pointing toward the robot, left or right.

Recipe (one simulation process, 6 x 100 episodes each, about 8 / 13 / 13 minutes on one core;
an interrupted run resumes per operator)::

    python eval/collect_demos.py --task lift --mix mh --episodes 100 --seed 0 --out data/lift_mh.hdf5
    python eval/collect_demos.py --task can --mix mh --episodes 100 --seed 0 --out data/can_mh.hdf5
    python eval/collect_demos.py --task square --mix mh --episodes 100 --seed 0 --out data/square_mh.hdf5
    python eval/demo_modes.py --task lift --data data/lift_mh.hdf5 --ph data/lift_expert.hdf5

Each records all six operators (operator k on env seeds seed + 100 k + 0..99; its success rate
over them in ``results/experts/<task>_mh.json``; its first 50 successes kept) and writes
robomimic's MH filter keys (``mask/better``, ``mask/okay``, ``mask/worse``, their pairwise unions
and one key per operator) and each demo's ``operator`` and ``quality`` attributes;
``eval/demo_modes.py`` plots how the operators differ (``docs/<task>_mh_modes.png``).
The default operator, :data:`EXPERT`, is the plain expert; experts built without an operator act
exactly as before operators existed.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

from .pusht import PUSH_OPERATORS, PushTExpert

__all__ = ["Operator", "EXPERT", "OPERATORS", "LiftExpert", "CanExpert", "SquareExpert", "EXPERTS", "make_expert"]

_DOWN = np.diag([1.0, -1.0, -1.0])  # the hand pointing down at yaw 0: fingers close along world y
_GAVE_UP = 99  # phase of an operator that stopped trying


@dataclass(frozen=True)
class Operator:
    """One demonstrator's style (see the module docstring). Defaults: the plain expert."""

    name: str = "expert"
    quality: str = "expert"  # better / okay / worse for the MH operators
    speed: float = 1.0  # factor on every position (and rotation) gain
    yaw: Optional[float] = None  # preferred hand yaw at the grasp (rad); None: the task's default
    approach: tuple[float, float] = (0.0, 0.0)  # (x, y) offset (m) of a via point before going above the object
    grasp_shift: float = 0.0  # grasp point shift (m): along the cube face / up the can / out along the handle
    hesitate: float = 0.0  # probability per step (approaching, carrying) of starting a pause
    pause: tuple[int, int] = (5, 15)  # pause length range in steps
    miss: float = 0.0  # probability that a grasp attempt is off the object
    max_grasps: int = 0  # gives up after this many failed grasps (0: never)
    noise: float = 0.0  # recorded, temporally correlated position noise: std per unit of (0.2 + |command|)
    noise_corr: float = 0.8  # its AR(1) coefficient per step
    place: Optional[float] = None  # square: preferred handle direction over the peg (rad); None: least turn

    def params(self) -> dict:
        return asdict(self)


EXPERT = Operator()


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


def _nearest(base: float, period: float, pref: float) -> float:
    """The angle ``base + k * period`` nearest to ``pref``."""
    return base + period * np.round((pref - base) / period)


def _toward(eef: np.ndarray, target: np.ndarray, gain: float = 10.0) -> np.ndarray:
    """Delta-position command in [-1, 1] (OSC_POSE scales 1.0 to 5 cm per step)."""
    return np.clip(gain * (target - eef), -1.0, 1.0)


class _Waypoints:
    """A sequence of phases; each phase returns (position target, gripper, done?).

    ``noisy_phases``: phases in which demonstration collection may perturb the executed action
    (DART-style noise injection: the clean expert action is recorded, so the data shows how to
    recover from the perturbed states a learned policy drifts into). ``hesitant_phases``: phases
    in which an operator may pause. ``miss_distance``: how far off a missed grasp is, along the
    hand's x axis (the fingers come down beside the object). ``free_tilt``: operators with a
    ``yaw`` turn the hand about the vertical only, leaving its tilt as the controller drifts."""

    noisy_phases: tuple[int, ...] = ()
    hesitant_phases: tuple[int, ...] = ()
    miss_distance = 0.035
    free_tilt = False

    def __init__(self, env, operator: Operator = EXPERT, rng: Optional[np.random.Generator] = None):
        self.env = env
        self.op = operator
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.phase = 0
        self.counter = 0
        self.failed_grasps = 0
        self.pauses = 0
        self._paused = 0
        self._jitter = np.zeros(3)
        self._grip = -1.0
        self._via_done = tuple(operator.approach) == (0.0, 0.0)
        self._miss = np.zeros(3)

    @property
    def gave_up(self) -> bool:
        return self.phase == _GAVE_UP

    def act(self, raw: dict) -> np.ndarray:
        """The operator's action: the task's plan, or holding still while paused, plus its noise."""
        op = self.op
        if self._paused > 0 or self.gave_up:
            self._paused = max(self._paused - 1, 0)
            a = np.zeros(7)
            a[6] = self._grip if not self.gave_up else -1.0
            return a
        a = self._plan(raw)
        if op.hesitate > 0 and self.phase in self.hesitant_phases and self.rng.random() < op.hesitate:
            self._paused = int(self.rng.integers(op.pause[0], op.pause[1] + 1))
            self.pauses += 1
        if op.noise > 0:
            c = op.noise_corr
            self._jitter = c * self._jitter + np.sqrt(1 - c * c) * op.noise * self.rng.normal(size=3)
            scale = 0.2 + np.linalg.norm(a[:3])  # signal-dependent: fast moves are the shaky ones
            a[:3] = np.clip(a[:3] + scale * self._jitter, -1.0, 1.0)
        self._grip = a[6]
        return a

    def _plan(self, raw: dict) -> np.ndarray:
        raise NotImplementedError

    def _action(self, eef: np.ndarray, target: np.ndarray, grip: float, gain: float = 10.0) -> np.ndarray:
        a = np.zeros(7)
        a[:3] = _toward(eef, target, gain * self.op.speed)
        a[6] = grip
        return a

    def _approach(self, eef: np.ndarray, obj: np.ndarray, height: float) -> Optional[np.ndarray]:
        """The operator's via point (beside the object, at ``height`` above it) until reached."""
        if self._via_done:
            return None
        via = obj + np.array([self.op.approach[0], self.op.approach[1], height])
        if np.linalg.norm(eef - via) < 0.02:
            self._via_done = True
        return via

    def _aim(self, hand_yaw: float) -> None:
        """Start a grasp attempt: off the object with the operator's miss probability."""
        self._miss = np.zeros(3)
        if self.op.miss > 0 and self.rng.random() < self.op.miss:
            sign = 1.0 if self.rng.random() < 0.5 else -1.0
            self._miss = sign * self.miss_distance * np.array([np.cos(hand_yaw), np.sin(hand_yaw), 0.0])

    def _retry(self) -> None:
        """The object is not in the hand: start over from above it (or give up)."""
        self.phase, self.counter = 0, 0
        if self.op == EXPERT:
            return
        self.failed_grasps += 1
        if self.op.max_grasps and self.failed_grasps >= self.op.max_grasps:
            self.phase = _GAVE_UP

    def _turn_to(self, quat: np.ndarray, yaw: Optional[float]) -> np.ndarray:
        """Rotation command toward ``yaw`` (None: none); ``free_tilt`` turns about the vertical only."""
        if yaw is None:
            return np.zeros(3)
        if self.free_tilt:
            return np.array([0.0, 0.0, np.clip(self.op.speed * _wrap(yaw - _yaw(quat)) / 0.5, -1.0, 1.0)])
        return _turn(quat, yaw, self.op.speed)


class LiftExpert(_Waypoints):
    """Above the cube, down, close, lift.

    Operators with a ``yaw`` turn the hand to the cube face alignment (every 90 degrees) nearest
    to it; if the cube does not come up with the hand, they start over."""

    noisy_phases = (0, 1)
    hesitant_phases = (0, 1, 3)
    miss_distance = 0.035

    def __init__(self, env, operator: Operator = EXPERT, rng=None):
        super().__init__(env, operator, rng)
        self.yaw = None

    def _plan(self, raw: dict) -> np.ndarray:
        eef, cube, quat = raw["robot0_eef_pos"], raw["cube_pos"], raw["robot0_eef_quat"]
        op = self.op
        if op.yaw is not None and self.phase == 0:
            self.yaw = _nearest(_yaw(raw["cube_quat"]), np.pi / 2, op.yaw)
        yaw_ok = self.yaw is None or abs(_wrap(_yaw(quat) - self.yaw)) < 0.1
        face = np.array([np.cos(self.yaw or 0.0), np.sin(self.yaw or 0.0), 0.0])
        grasp = cube + op.grasp_shift * face + [0, 0, -0.005]
        if self.phase == 3 and op != EXPERT and np.linalg.norm(eef - grasp) > 0.04:
            self._retry()  # the cube stayed on the table
        if self.phase == 0:  # above
            target = self._approach(eef, cube, 0.08)
            if target is None:
                target = cube + [0, 0, 0.08]
                if np.linalg.norm(eef - target) < 0.01 and yaw_ok:
                    self.phase, self.counter = 1, 0
                    self._aim(_yaw(quat))
            a = self._action(eef, target, -1)
        elif self.phase == 1:  # descend
            self.counter += 1
            target = grasp + self._miss
            if np.linalg.norm(eef - target) < 0.008 or (op != EXPERT and self.counter > 60):
                self.phase, self.counter = 2, 0
            a = self._action(eef, target, -1)
        elif self.phase == 2:  # grasp
            self.counter += 1
            if self.counter > 8:
                self.phase = 3
            a = self._action(eef, grasp + self._miss, 1)
        elif self.phase == 3:
            a = self._action(eef, cube + [0, 0, 0.25], 1, gain=5.0)  # lift
        else:
            return np.zeros(7)
        a[3:6] = self._turn_to(quat, self.yaw)
        return a


class CanExpert(_Waypoints):
    """Above the can, down, grip, lift, carry over the target bin, lower, release.

    If the can is not in the hand while lifting or carrying (a missed grasp, or a drop), the expert
    starts again from above the can, so perturbed demonstrations also show re-grasping. Operators
    with a ``yaw`` hold the hand at that yaw (the can is round); ``grasp_shift`` grips higher."""

    noisy_phases = (0, 1, 4)
    hesitant_phases = (0, 3, 4)
    miss_distance = 0.05
    free_tilt = True  # with the hand held vertical the far corner of the goal bin is out of reach

    def _plan(self, raw: dict) -> np.ndarray:
        a = self._plan_position(raw)
        a[3:6] = self._turn_to(raw["robot0_eef_quat"], self.op.yaw)
        return a

    def _plan_position(self, raw: dict) -> np.ndarray:
        env, op = self.env, self.op
        eef, can = raw["robot0_eef_pos"], raw["Can_pos"]
        goal = np.array(env.target_bin_placements[env.object_to_id["can"]])
        grasp = can + [0, 0, 0.005 + op.grasp_shift]
        if self.phase in (3, 4, 5) and np.linalg.norm(eef - grasp) > 0.05:
            self._retry()  # the can is not between the fingers: start over
        if self.phase == 0:
            target = self._approach(eef, can, 0.1)
            if target is not None:
                return self._action(eef, target, -1)
            target = can + [0, 0, 0.1]
            yaw_ok = op.yaw is None or abs(_wrap(_yaw(raw["robot0_eef_quat"]) - op.yaw)) < 0.1
            if np.linalg.norm(eef - target) < 0.01 and yaw_ok:
                self.phase = 1
                self._aim(_yaw(raw["robot0_eef_quat"]))
            return self._action(eef, target, -1)
        if self.phase == 1:  # the fingertips stop ~1 cm above the can's centre
            target = grasp + self._miss
            self.counter += 1
            if np.linalg.norm(eef - target) < 0.012 or self.counter > 40:
                self.phase, self.counter = 2, 0
            return self._action(eef, target, -1)
        if self.phase == 2:
            self.counter += 1
            if self.counter > 10:
                self.phase = 3
            return self._action(eef, grasp + self._miss, 1)
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
    current yaw, or an operator's preferred yaw) so the fingers close across the handle, 1.2 cm
    outward of the handle site (the fingers then clear the nut's ring). Over the peg the nut's
    handle is turned to point left, right or toward the robot (never away: the arm cannot reach
    over the peg that far at carrying height), whichever needs the least turn (or is nearest an
    operator's ``place``) within the wrist's range. While carrying and lowering, the hand target
    follows the nut's true position, so slip in the grasp is corrected. If the nut is not in the
    hand while lifting or carrying, the expert starts again from above the handle."""

    noisy_phases = (0, 1, 4)
    hesitant_phases = (0, 3, 4)
    miss_distance = 0.045
    carry_z = 1.01  # nut bottom 1 cm above the peg top (0.95 m) when the hand is at this height
    handle_out = 0.012
    hand_yaw_range = (-1.9, 3.0)  # hand yaws the Panda's last joint reaches from its start (q7 ~ 0.8 - yaw)

    def __init__(self, env, operator: Operator = EXPERT, rng=None):
        super().__init__(env, operator, rng)
        self.yaw = None
        self.handle_dir = None

    def _handle(self, psi: float) -> np.ndarray:
        env = self.env
        site = np.array(env.sim.data.site_xpos[env.object_site_ids[env.nut_id]])
        return site + (self.handle_out + self.op.grasp_shift) * np.array([np.cos(psi), np.sin(psi), 0.0])

    def _grasp_yaw(self, hand: float, psi: float) -> float:
        if self.op.yaw is None:
            return psi + np.pi * np.round((hand - psi) / np.pi)
        lo, hi = self.hand_yaw_range
        options = [psi + k * np.pi for k in range(-3, 4) if lo + 0.2 < psi + k * np.pi < hi - 0.2]
        return min(options, key=lambda y: abs(y - self.op.yaw))

    def _plan(self, raw: dict) -> np.ndarray:
        env = self.env
        eef, quat = raw["robot0_eef_pos"], raw["robot0_eef_quat"]
        nut, psi = raw["SquareNut_pos"], _yaw(raw["SquareNut_quat"])
        peg = np.array(env.sim.data.body_xpos[env.peg1_body_id])
        handle = self._handle(psi)
        hand = _yaw(quat)

        def command(target, grip, yaw, gain=10.0):
            a = self._action(eef, target, grip, gain)
            a[3:6] = _turn(quat, yaw, self.op.speed)
            return a

        if self.phase in (3, 4, 5) and np.linalg.norm(eef - handle) > 0.04:
            self._retry()  # the handle is not between the fingers: start over
            if self.gave_up:
                return np.zeros(7)
        if self.phase == 0:  # above the handle, fingers across it
            self.yaw = self._grasp_yaw(hand, psi)
            target = self._approach(eef, handle, 0.08)
            if target is not None:
                return command(target, -1, self.yaw)
            target = handle + [0, 0, 0.08]
            if np.linalg.norm(eef - target) < 0.01 and abs(_wrap(hand - self.yaw)) < 0.05:
                self.phase, self.counter = 1, 0
                self._aim(hand)
            return command(target, -1, self.yaw)
        if self.phase == 1:  # descend
            self.counter += 1
            if np.linalg.norm(eef - handle - self._miss) < 0.008 or self.counter > 40:
                self.phase, self.counter = 2, 0
            return command(handle + self._miss, -1, self.yaw)
        if self.phase == 2:  # grasp
            self.counter += 1
            if self.counter > 10:
                self.phase = 3
            return command(handle + self._miss, 1, self.yaw)
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
        """Handle direction over the peg: left, toward the robot or right; least turn first, or the
        one nearest the operator's ``place``."""
        lo, hi = self.hand_yaw_range
        options = [(abs(_wrap(d - psi)), d) for d in (np.pi / 2, np.pi, -np.pi / 2)]
        if self.op.place is not None:
            options = [(abs(_wrap(d - self.op.place)), d) for _, d in options]
        return min([o for o in options if lo < hand + _wrap(o[1] - psi) < hi] or options)[1]


EXPERTS = {"lift": LiftExpert, "can": CanExpert, "square": SquareExpert, "pusht": PushTExpert}

_Q = np.pi / 4
OPERATORS: dict[str, list[Operator]] = {
    "lift": [
        Operator("better_operator_1", "better", speed=1.0, yaw=0.0, noise=0.05),
        Operator("better_operator_2", "better", speed=0.9, yaw=_Q, approach=(0.0, 0.08), grasp_shift=0.006,
                 hesitate=0.005, noise=0.08),
        Operator("okay_operator_1", "okay", speed=0.7, approach=(0.0, -0.08), hesitate=0.015, miss=0.2,
                 max_grasps=3, noise=0.15),
        Operator("okay_operator_2", "okay", speed=0.65, yaw=-_Q, approach=(0.08, 0.0), grasp_shift=-0.006,
                 hesitate=0.015, miss=0.25, max_grasps=3, noise=0.15),
        Operator("worse_operator_1", "worse", speed=0.55, yaw=_Q, approach=(0.0, 0.1), hesitate=0.02,
                 pause=(10, 25), miss=0.45, max_grasps=2, noise=0.3),
        Operator("worse_operator_2", "worse", speed=0.5, approach=(0.06, -0.08), grasp_shift=0.008,
                 hesitate=0.02, pause=(10, 25), miss=0.5, max_grasps=2, noise=0.3),
    ],
    "can": [
        Operator("better_operator_1", "better", speed=1.0, noise=0.05),
        Operator("better_operator_2", "better", speed=0.9, yaw=np.pi / 2, approach=(0.0, 0.08), grasp_shift=0.01,
                 hesitate=0.005, noise=0.08),
        Operator("okay_operator_1", "okay", speed=0.85, yaw=-_Q, approach=(-0.08, 0.0), hesitate=0.015, miss=0.2,
                 max_grasps=3, noise=0.15),
        Operator("okay_operator_2", "okay", speed=0.8, yaw=_Q, approach=(0.08, 0.0), grasp_shift=0.012,
                 hesitate=0.015, miss=0.2, max_grasps=3, noise=0.15),
        Operator("worse_operator_1", "worse", speed=0.75, yaw=np.pi / 2, approach=(0.0, -0.1), hesitate=0.015,
                 pause=(10, 25), miss=0.3, max_grasps=3, noise=0.2),
        Operator("worse_operator_2", "worse", speed=0.7, approach=(0.06, 0.08), grasp_shift=0.01, hesitate=0.015,
                 pause=(10, 25), miss=0.35, max_grasps=3, noise=0.2),
    ],
    "square": [
        Operator("better_operator_1", "better", speed=1.0, noise=0.05),
        Operator("better_operator_2", "better", speed=0.9, yaw=0.8, approach=(0.0, -0.08), place=np.pi,
                 hesitate=0.005, noise=0.08),
        Operator("okay_operator_1", "okay", speed=0.85, yaw=-0.8, approach=(0.08, 0.0), place=np.pi / 2,
                 grasp_shift=0.005, hesitate=0.015, miss=0.2, max_grasps=3, noise=0.15),
        Operator("okay_operator_2", "okay", speed=0.8, approach=(-0.08, 0.0), place=-np.pi / 2, grasp_shift=-0.004,
                 hesitate=0.015, miss=0.15, max_grasps=3, noise=0.15),
        Operator("worse_operator_1", "worse", speed=0.75, yaw=0.8, approach=(0.0, 0.1), hesitate=0.015,
                 pause=(10, 25), miss=0.3, max_grasps=3, noise=0.2),
        Operator("worse_operator_2", "worse", speed=0.7, yaw=-0.8, approach=(0.06, -0.08), grasp_shift=0.008,
                 place=np.pi / 2, hesitate=0.015, pause=(10, 25), miss=0.35, max_grasps=3, noise=0.2),
    ],
    "pusht": PUSH_OPERATORS,
}


def make_expert(task: str, env, operator: Operator = EXPERT, rng: Optional[np.random.Generator] = None):
    return EXPERTS[task](env, operator, rng)
