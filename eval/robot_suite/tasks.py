"""The manipulation tasks: robosuite 1.5 with robomimic's low-dim observations, and Push-T.

robosuite tasks (robomimic PH settings): Panda arm, OSC_POSE controller (7-D action: 6 delta pose in
[-1, 1] + gripper), 20 Hz control, horizon 400. Observations use robomimic's keys: ``object``
(robosuite's ``object-state``), ``robot0_eef_pos``, ``robot0_eef_quat``, ``robot0_gripper_qpos``.
Push-T (gym-pusht, ``robot_suite/pusht.py``): 2-D target position, 10 Hz, horizon 300, observations
``agent_pos`` and ``block_keypoints``.
"""
from __future__ import annotations

import gc
import importlib.util
import logging
import os
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from .pusht import PUSHT_OBS_KEYS, PushTScene

__all__ = ["TASKS", "TaskConfig", "OBS_KEYS", "CAMERAS", "make_env", "reset_env", "low_dim_obs", "camera_obs",
           "render_state", "env_args", "task_of_env", "sim_state", "step_unobserved"]

OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
CAMERAS = ("agentview", "robot0_eye_in_hand")  # robomimic's image datasets: obs/<camera>_image


@dataclass(frozen=True)
class TaskConfig:
    """A task: its env's name, episode horizon, the policy's observation keys and the simulator
    family (``suite``: "robosuite" or "pusht") that builds, describes and snapshots its env."""

    env_name: str
    horizon: int = 400
    obs_keys: tuple[str, ...] = OBS_KEYS
    suite: str = "robosuite"


TASKS = {
    "lift": TaskConfig("Lift"),
    "can": TaskConfig("PickPlaceCan"),
    "square": TaskConfig("NutAssemblySquare"),
    "pusht": TaskConfig("PushT", horizon=300, obs_keys=PUSHT_OBS_KEYS, suite="pusht"),
}


def task_of_env(env_name: str) -> str:
    """The task whose env a dataset's ``env_args['env_name']`` names."""
    for task, cfg in TASKS.items():
        if cfg.env_name == env_name:
            return task
    raise ValueError(f"no task for env {env_name!r}; known: {[c.env_name for c in TASKS.values()]}")


def _env_kwargs(task: str, render: bool, cameras: Sequence[str] = (), image_size: int = 84) -> dict:
    from robosuite.controllers import load_composite_controller_config

    cams = dict(camera_names=list(cameras), camera_heights=image_size, camera_widths=image_size) if cameras else {}
    return dict(
        robots="Panda",
        controller_configs=load_composite_controller_config(controller="BASIC", robot="Panda"),
        has_renderer=False,
        has_offscreen_renderer=render or bool(cameras),
        use_camera_obs=bool(cameras),
        **cams,
        use_object_obs=True,
        control_freq=20,
        horizon=TASKS[task].horizon,
        ignore_done=True,
        reward_shaping=False,
    )


def _import_chatter(record: logging.LogRecord) -> bool:
    """False for robosuite's import-time advice (no private macro file, optional robot packages)."""
    return not (record.levelno <= logging.WARNING and record.filename in ("macros.py", "__init__.py"))


def import_robosuite():
    """``import robosuite`` without its import-time warnings and per-reset controller chatter
    (errors still print)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    logger = logging.getLogger("robosuite_logs")
    if _import_chatter not in logger.filters:
        logger.addFilter(_import_chatter)
    import robosuite

    for name in ("robosuite", "robosuite_logs"):
        logging.getLogger(name).setLevel(logging.ERROR)
    return robosuite


def make_env(task: str, seed: Optional[int] = None, render: bool = False, cameras: Sequence[str] = (),
             image_size: int = 84):
    """The env of ``task``: robosuite's (lift / can / square; ``seed`` fixes object placements) or the
    Push-T scene (seeded per episode by :func:`reset_env`). ``cameras`` (e.g. :data:`CAMERAS`): render
    those cameras offscreen at ``image_size`` x ``image_size`` into every observation (robosuite
    only; :func:`camera_obs` reads them)."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose from {sorted(TASKS)}")
    if TASKS[task].suite == "pusht":
        if cameras:
            raise ValueError("camera observations are rendered for the robosuite tasks, not Push-T")
        return PushTScene()
    if (render or cameras) and importlib.util.find_spec("triton") is not None:
        import triton  # noqa: F401  loading triton's library after an EGL context exists crashes the process
    suite = import_robosuite()
    if cameras:
        _render_in_own_context()
    return suite.make(TASKS[task].env_name, seed=seed, **_env_kwargs(task, render, cameras, image_size))


def _render_in_own_context() -> None:
    """Make robosuite's offscreen renderer bind its own GL context before it renders, reads pixels or
    frees its GL objects. It makes its context current only when created, so with several camera
    envs in one process every env rendered in the newest context, and a dropped context (a hard reset
    drops the old sim's) freed its GL objects by id in whichever context was current: the live
    env's textures and buffers. Frames then came out wrong, silently. Patched once per process."""
    from robosuite.utils import binding_utils

    cls = binding_utils.MjRenderContext
    for name in ("render", "read_pixels", "__del__"):
        method = getattr(cls, name)
        if getattr(method, "binds_own_context", False):
            continue

        def bound(self, *args, _method=method, _freeing=name == "__del__", **kwargs):
            ctx = getattr(self, "gl_ctx", None)
            try:
                if ctx is not None:
                    ctx.make_current()
            except Exception:
                if not _freeing:  # a render outside its own context is what this patch prevents
                    raise  # at interpreter exit EGL is gone and there is nothing left to free
            return _method(self, *args, **kwargs)

        bound.binds_own_context = True
        setattr(cls, name, bound)


def camera_obs(raw: dict, cameras: Sequence[str]) -> dict[str, np.ndarray]:
    """The frames of ``cameras`` as uint8 [H, W, 3] under robomimic's keys (``agentview_image``),
    upright: robosuite renders with OpenGL's bottom-up rows, which are flipped here, in the
    demonstrations and at evaluation alike."""
    missing = [c for c in cameras if f"{c}_image" not in raw]
    if missing:
        raise KeyError(f"the env renders no {missing} camera: make it with make_env(..., cameras=...)")
    return {f"{c}_image": np.ascontiguousarray(raw[f"{c}_image"][::-1]) for c in cameras}


def step_unobserved(env, action: np.ndarray) -> tuple:
    """``env.step(action)`` without rendering its cameras: a step whose frames nobody reads.

    Robosuite samples a camera on its own clock, inside the physics substeps. Here each camera
    observable keeps that clock but hands back its previous frame instead of rendering, so the
    physics and every later step's frames are those of a run that rendered every step (tested), and
    the step's own camera frames are stale: read only its low-dim keys. Rendering is about 65 ms per
    84x84 camera frame on a CPU, most of a camera env's step."""
    gates = []
    for name, observable in env._observables.items():
        if name.endswith("_image"):
            render = observable._sensor
            if not hasattr(render, "rendering"):  # wrapped once per observable (a hard reset makes new ones)
                render = observable._sensor = _gated_camera(observable, render)
            gates.append(render)
    for g in gates:
        g.rendering = False
    try:
        return env.step(action)
    finally:
        for g in gates:
            g.rendering = True


def _gated_camera(observable, render):
    def sensor(obs_cache):
        return render(obs_cache) if sensor.rendering else observable._current_observed_value

    sensor.rendering = True
    sensor.__modality__ = render.__modality__
    return sensor


def render_state(env, state: np.ndarray) -> dict:
    """The raw observation of ``env`` (cameras included) at a recorded MuJoCo ``state``
    (:func:`sim_state`): how recorded demonstrations get their camera frames."""
    env.sim.set_state_from_flattened(np.asarray(state))
    env.sim.forward()
    return env._get_observations(force_update=True)


def reset_env(env, seed: int) -> dict:
    """Reset ``env`` to the episode of ``seed``: object placement and robot init noise both come
    from ``env.rng``, and a hard reset rebuilds the placement sampler from it, so one env object
    can replay any seed (make + reset costs seconds, a hard reset about 0.2 s)."""
    if isinstance(env, PushTScene):
        return env.reset_seed(seed)
    rng = np.random.default_rng(seed)
    env.rng = rng
    sampler = getattr(env, "placement_initializer", None)  # built once, keeps its own rng reference
    stack = [sampler] if sampler is not None else []
    while stack:
        s = stack.pop()
        s.rng = rng
        stack.extend(getattr(s, "samplers", {}).values())
    obs = env.reset()
    if getattr(env, "use_camera_obs", False):
        # a hard reset drops the old sim and its offscreen render context in reference cycles: about
        # 0.3 GB per reset with two 84x84 cameras, which ran an evaluation out of memory after 20 episodes
        # (freeing a context unbinds the current one: _render_in_own_context rebinds before each render)
        gc.collect()
    return obs


def env_args(task: str, cameras: Sequence[str] = (), image_size: int = 84) -> dict:
    """robomimic-style env metadata stored in datasets (with ``cameras``: an image dataset's)."""
    if TASKS[task].suite == "pusht":
        return {"env_name": "PushT", "type": 0, "env_kwargs": {"obs_type": "state", "control_hz": 10,
                                                                "horizon": TASKS[task].horizon},
                "env_version": "gym-pusht"}
    kw = _env_kwargs(task, False, cameras, image_size)
    kw["controller_configs"] = "BASIC (OSC_POSE arm), Panda"
    return {"env_name": TASKS[task].env_name, "type": 1, "env_kwargs": kw, "env_version": "robosuite 1.5"}


def sim_state(env, raw: dict) -> np.ndarray:
    """The simulator state a dataset records per step (robomimic's ``states``), from which
    ``reset_to`` restores the scene: Push-T's own state vector, or MuJoCo's flattened state."""
    if isinstance(env, PushTScene):
        return np.asarray(raw["state"])
    return env.sim.get_state().flatten()


def low_dim_obs(raw: dict) -> dict[str, np.ndarray]:
    """The policy's observation keys from an env's raw observation."""
    if "object-state" not in raw:  # Push-T: the scene already gives them
        return {k: np.asarray(raw[k], dtype=np.float32) for k in PUSHT_OBS_KEYS}
    return {
        "object": np.asarray(raw["object-state"], dtype=np.float32),
        "robot0_eef_pos": np.asarray(raw["robot0_eef_pos"], dtype=np.float32),
        "robot0_eef_quat": np.asarray(raw["robot0_eef_quat"], dtype=np.float32),
        "robot0_gripper_qpos": np.asarray(raw["robot0_gripper_qpos"], dtype=np.float32),
    }
