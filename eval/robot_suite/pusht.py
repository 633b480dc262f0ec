"""Push-T (gym-pusht): the environment wrapper and a scripted pusher with several strategies.

Push-T is Diffusion Policy's canonical multimodal task: a circular agent (position-controlled,
action = target position in [0, 512]^2, 10 Hz) pushes a T-shaped block into a fixed goal pose;
success is 95% of the goal area covered. To reach the far side of the block the agent must go
around it, clockwise or counter-clockwise: averaging the two routes runs into the block.

The scripted pusher plans one push at a time by simulation: candidate contacts on the T's
outline (three points per edge, pushing along the inward normal, straight or tilted), each pushed
a short distance in a scratch copy of the scene, scored by the block's keypoint error to the goal
plus the travel to reach the contact. It then walks around the block to the chosen contact along a
circle (in the operator's preferred direction, or the shorter way) and executes the push. Operators
(:class:`PushOperator`) differ in route preference, push length, speed, pauses and recorded noise.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

__all__ = ["PushTScene", "PushOperator", "PUSH_EXPERT", "PUSH_OPERATORS", "PushTExpert", "PUSHT_OBS_KEYS",
           "T_OUTLINE", "keypoints", "keypoint_error", "make_pusht"]

PUSHT_OBS_KEYS = ("agent_pos", "block_keypoints")

# The T's outline in the block's frame (gym-pusht's add_tee with scale 30): bar on top, stem below.
T_OUTLINE = np.array([(-60, 0), (60, 0), (60, 30), (15, 30), (15, 120), (-15, 120), (-15, 30), (-60, 30)], float)
GOAL = np.array([256.0, 256.0, np.pi / 4])
AGENT_RADIUS = 15.0
LO, HI = 20.0, 492.0  # agent targets stay inside the walls


def _rot(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def keypoints(pose: np.ndarray) -> np.ndarray:
    """The T outline's 8 corners in the world for a block pose (x, y, angle)."""
    return T_OUTLINE @ _rot(pose[2]).T + pose[:2]


def keypoint_error(pose: np.ndarray) -> float:
    """Mean corner distance (px) between the block at ``pose`` and the goal pose."""
    return float(np.linalg.norm(keypoints(pose) - keypoints(GOAL), axis=1).mean())


def make_pusht():
    """A gym-pusht environment with state observations (agent x, y, block x, y, angle)."""
    try:
        from gym_pusht.envs.pusht import PushTEnv
    except ImportError as e:  # pragma: no cover - depends on the optional extra
        raise ImportError("Push-T needs gym-pusht: pip install 'test-time-sparsity[pusht]'") from e
    return PushTEnv(obs_type="state")


class PushTScene:
    """One Push-T episode with robosuite's env interface as the pipeline uses it: ``reset_seed``,
    ``step`` returning ``(obs, reward, done, info)``, ``_check_success``. Observations (a dict):
    ``agent_pos`` (2), ``block_keypoints`` (the T's 8 corners, 16) and the raw ``state``."""

    def __init__(self):
        self.env = make_pusht()
        self.coverage = 0.0

    def _obs(self, state: np.ndarray) -> dict:
        state = np.asarray(state, float)
        return {"state": state, "agent_pos": state[:2].astype(np.float32),
                "block_keypoints": keypoints(state[2:]).reshape(-1).astype(np.float32)}

    def reset_seed(self, seed: int) -> dict:
        state, _ = self.env.reset(seed=int(seed))
        self.coverage = 0.0
        return self._obs(state)

    def reset_to(self, state: np.ndarray) -> dict:
        """The scene at ``state`` exactly. (gym-pusht's own ``reset_to_state`` sets the block's
        angle after its position, which turns it about its centre of mass and moves it.)"""
        state = np.asarray(state, float)
        self.env.reset(options={"reset_to_state": state})
        self.env.block.angle = float(state[4])
        self.env.block.position = (float(state[2]), float(state[3]))
        self.env.agent.position = (float(state[0]), float(state[1]))
        self.env.agent.velocity = (0.0, 0.0)
        self.coverage = 0.0
        return self._obs(self.env.get_obs())

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, dict]:
        state, reward, _, _, info = self.env.step(np.clip(np.asarray(action, float), 0, 512))
        self.coverage = float(info["coverage"])
        return self._obs(state), float(reward), False, info

    def _check_success(self) -> bool:
        return self.coverage > self.env.success_threshold


@dataclass(frozen=True)
class PushOperator:
    """One demonstrator's style. Defaults: the plain expert (shorter route, medium pushes)."""

    name: str = "expert"
    quality: str = "expert"
    route: Optional[int] = None  # +1 counter-clockwise, -1 clockwise around the block, None: the shorter way
    route_bias: float = 1.0  # probability of following ``route`` on a given detour (else the shorter way)
    push: float = 1.0  # factor on push lengths
    speed: float = 1.0  # factor on the walking speed
    hesitate: float = 0.0  # probability per step of starting a pause while walking
    pause: tuple[int, int] = (3, 8)
    noise: float = 0.0  # recorded target noise (px), temporally correlated
    noise_corr: float = 0.7

    def params(self) -> dict:
        return asdict(self)


PUSH_EXPERT = PushOperator()
PUSH_OPERATORS = [
    PushOperator("better_operator_1", "better", route=+1, route_bias=0.9, push=1.0, speed=1.0, noise=1.0),
    PushOperator("better_operator_2", "better", route=-1, route_bias=0.9, push=1.0, speed=1.0, noise=1.0),
    PushOperator("okay_operator_1", "okay", route=+1, route_bias=0.8, push=0.8, speed=0.8, hesitate=0.02, noise=2.0),
    PushOperator("okay_operator_2", "okay", route=-1, route_bias=0.8, push=1.2, speed=0.8, hesitate=0.02, noise=2.0),
    PushOperator("worse_operator_1", "worse", route=None, push=0.7, speed=0.65, hesitate=0.05, noise=3.5),
    PushOperator("worse_operator_2", "worse", route=-1, route_bias=0.7, push=1.4, speed=0.65, hesitate=0.05, noise=3.5),
]


class PushTExpert:
    """Scripted pusher for one episode: ``act(state)`` returns the next target position."""

    WALK = 50.0  # px per step at speed 1
    GAP = 4.0  # clearance between the agent and the block before a push

    noisy_phases = ()  # no executed-but-unrecorded (DART) noise: the operators' noise is recorded
    failed_grasps = 0
    gave_up = False

    def __init__(self, env=None, operator: Optional[PushOperator] = None, rng: Optional[np.random.Generator] = None):
        self.op = operator if isinstance(operator, PushOperator) else PUSH_EXPERT
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.phase = "push"
        self.pauses = 0
        self.scratch = PushTScene()
        self.queue: list[tuple[str, np.ndarray]] = []  # (walk / contact / push, target)
        self.last_dir = None  # direction of the last push
        self.last_err, self.stalled = None, 0  # keypoint error at the last plan, plans without progress
        self.held = 0  # steps the current walk or contact target has been held
        self.pausing = 0
        self.noise = np.zeros(2)
        self.last = None

    # planning -------------------------------------------------------------------------------
    def _candidates(self, pose: np.ndarray, err: float):
        """Contacts on the outline: (contact point, outward normal, push direction, length)."""
        corners = keypoints(pose)
        base = float(np.clip(0.9 * err, 4.0, 120.0)) * self.op.push
        lengths = (base,) if err > 30 else (self.GAP + 0.3 * base, self.GAP + base)  # the first GAP px only reach the block
        out = []
        for i in range(len(corners)):
            a, b = corners[i], corners[(i + 1) % len(corners)]
            edge = b - a
            normal = np.array([edge[1], -edge[0]]) / np.linalg.norm(edge)  # outward for a CCW outline
            if np.dot(normal, (a + b) / 2 - corners.mean(0)) < 0:
                normal = -normal
            for f in (0.15, 0.5, 0.85):
                p = a + f * edge
                for tilt in (-0.5, 0.0, 0.5):
                    d = _rot(tilt) @ -normal
                    out += [(p, normal, d, length) for length in lengths]
        return out

    def _simulate(self, state: np.ndarray, p, normal, d, length) -> np.ndarray:
        start = p + normal * (AGENT_RADIUS + self.GAP)
        self.scratch.reset_to(np.concatenate([start, state[2:]]))
        for target in self._push_targets(start, d, length):
            obs = self.scratch.step(target)[0]
        return obs["state"][2:]

    @staticmethod
    def _push_targets(start, d, length) -> list[np.ndarray]:
        n = max(2, int(np.ceil(length / 12.0)))
        end = start + d * length
        return [start + d * length * (i / n) for i in range(1, n + 1)] + [end, end]  # the agent catches up

    def _route(self, agent: np.ndarray, goal: np.ndarray, center: np.ndarray, radius: float) -> list[np.ndarray]:
        """Waypoints from ``agent`` to ``goal`` around a circle about the block when the straight
        line would pass through it; the direction follows the operator's preference."""
        from shapely.geometry import LineString, Polygon

        body = Polygon(keypoints(self._pose)).buffer(AGENT_RADIUS + 3.0)
        if not LineString([agent, goal]).intersects(body):
            return [goal]
        a0 = np.arctan2(*(agent - center)[::-1])
        a1 = np.arctan2(*(goal - center)[::-1])
        ccw = (a1 - a0) % (2 * np.pi)  # counter-clockwise sweep
        shorter = 1 if ccw <= np.pi else -1
        side = self.op.route if (self.op.route is not None and self.rng.random() < self.op.route_bias) else shorter
        sweep = ccw if side == 1 else ccw - 2 * np.pi
        n = max(2, int(np.ceil(abs(sweep) / 0.45)))
        pts = [center + radius * np.array([np.cos(a0 + sweep * k / n), np.sin(a0 + sweep * k / n)]) for k in range(n + 1)]
        return [np.clip(q, LO, HI) for q in pts] + [goal]

    def _plan(self, state: np.ndarray) -> None:
        agent, pose = state[:2], state[2:]
        self._pose = pose
        from shapely.geometry import LineString, Polygon

        err = keypoint_error(pose)
        self.stalled = self.stalled + 1 if (self.last_err is not None and err > self.last_err - 0.3) else 0
        self.last_err = err
        block = Polygon(keypoints(pose))
        scored = []
        for p, normal, d, length in self._candidates(pose, err):
            start = p + normal * (AGENT_RADIUS + self.GAP)
            if np.any(start < LO) or np.any(start > HI):
                continue
            if LineString([start - d * 25.0, start]).distance(block) < AGENT_RADIUS + self.GAP - 0.5:
                continue  # the contact cannot be reached straight (a notch of the T, another arm in the way)
            after = keypoint_error(self._simulate(state, p, normal, d, length))
            if after < err - 0.5:
                scored.append((after + 0.03 * np.linalg.norm(start - agent), start, d, length))
        scored.sort(key=lambda c: c[0])
        best = None
        if scored:  # the best push; after a push that did not help, one of the next best
            best = scored[int(self.rng.integers(min(len(scored), 1 + 2 * self.stalled)))][1:]
        if best is None:  # no single push helps: nudge from a random contact
            cands = self._candidates(pose, err)
            p, normal, d, length = cands[self.rng.integers(len(cands))]
            best = (p + normal * (AGENT_RADIUS + self.GAP), d, length)
        start, d, length = best
        corners = keypoints(pose)
        center = corners.mean(0)
        radius = float(np.linalg.norm(corners - center, axis=1).max()) + AGENT_RADIUS + 12.0
        if np.linalg.norm(agent - start) < 12.0 and not self.stalled:  # already there (e.g. continuing the last push)
            walk = [start]
        else:  # back off the block along the last push, then walk around it if it is in the way
            back = [np.clip(agent - self.last_dir * 20.0, LO, HI)] if self.last_dir is not None else []
            walk = back + self._route(back[-1] if back else agent, start - d * 25.0, center, radius) + [start]
        self.last_dir = d
        self.queue = ([("walk", q) for q in self._walk(agent, walk[:-1])] + [("contact", start)]
                      + [("push", q) for q in self._push_targets(start, d, length)])
        self.held = 0

    def _walk(self, agent: np.ndarray, waypoints: list[np.ndarray]) -> list[np.ndarray]:
        out, cur = [], np.asarray(agent, float)
        step = self.WALK * self.op.speed
        for w in waypoints:
            dist = np.linalg.norm(w - cur)
            n = max(1, int(np.ceil(dist / step)))
            out += [cur + (w - cur) * (k / n) for k in range(1, n + 1)]
            cur = np.asarray(w, float)
        return out

    # acting ---------------------------------------------------------------------------------
    def act(self, obs: dict) -> np.ndarray:
        """The next action (target position) for ``state``; pauses repeat the last target.

        Walking targets are held until the agent is near them (the agent lags its target), the
        contact point until the agent rests on it; push targets are played one per step, as in the
        planning simulation."""
        if self.pausing > 0 and self.last is not None:
            self.pausing -= 1
            return self.last
        state = obs["state"]
        agent = state[:2]
        while self.queue:
            kind, target = self.queue[0]
            tol = {"walk": 25.0, "contact": 3.0}.get(kind)
            if tol is not None and (np.linalg.norm(agent - target) < tol or self.held > 12):
                self.queue.pop(0)
                self.held = 0
                continue
            break
        if not self.queue:
            self._plan(state)
        kind, target = self.queue[0]
        if kind == "push":
            self.queue.pop(0)
        else:
            self.held += 1
        if self.op.hesitate and kind == "walk" and self.rng.random() < self.op.hesitate:
            self.pausing = int(self.rng.integers(*self.op.pause))
            self.pauses += 1
        if self.op.noise:
            self.noise = self.op.noise_corr * self.noise + np.sqrt(1 - self.op.noise_corr ** 2) * self.rng.normal(
                0, self.op.noise, 2)
        self.last = np.clip(target + (self.noise if kind == "walk" else 0.0), 0, 512)
        return self.last
