"""robosuite 1.5 manipulation tasks with robomimic's low-dim observations.

Tasks (robomimic PH settings): Panda arm, OSC_POSE controller (7-D action: 6 delta pose in [-1, 1]
+ gripper), 20 Hz control, horizon 400. Observations use robomimic's keys: ``object`` (robosuite's
``object-state``), ``robot0_eef_pos``, ``robot0_eef_quat``, ``robot0_gripper_qpos``.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ["TASKS", "TaskConfig", "OBS_KEYS", "make_env", "reset_env", "low_dim_obs", "env_args"]

OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


@dataclass(frozen=True)
class TaskConfig:
    env_name: str
    horizon: int = 400


TASKS = {
    "lift": TaskConfig("Lift"),
    "can": TaskConfig("PickPlaceCan"),
    "square": TaskConfig("NutAssemblySquare"),
}


def _env_kwargs(task: str, render: bool) -> dict:
    from robosuite.controllers import load_composite_controller_config

    return dict(
        robots="Panda",
        controller_configs=load_composite_controller_config(controller="BASIC", robot="Panda"),
        has_renderer=False,
        has_offscreen_renderer=render,
        use_camera_obs=False,
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


def make_env(task: str, seed: Optional[int] = None, render: bool = False):
    """A robosuite env for ``task`` (lift / can / square); ``seed`` fixes object placements."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose from {sorted(TASKS)}")
    suite = import_robosuite()
    env = suite.make(TASKS[task].env_name, seed=seed, **_env_kwargs(task, render))
    return env


def reset_env(env, seed: int) -> dict:
    """Reset ``env`` to the episode of ``seed``: object placement and robot init noise both come
    from ``env.rng``, and a hard reset rebuilds the placement sampler from it, so one env object
    can replay any seed (make + reset costs seconds, a hard reset about 0.2 s)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    env.rng = rng
    sampler = getattr(env, "placement_initializer", None)  # built once, keeps its own rng reference
    stack = [sampler] if sampler is not None else []
    while stack:
        s = stack.pop()
        s.rng = rng
        stack.extend(getattr(s, "samplers", {}).values())
    return env.reset()


def env_args(task: str) -> dict:
    """robomimic-style env metadata stored in datasets."""
    kw = _env_kwargs(task, False)
    kw["controller_configs"] = "BASIC (OSC_POSE arm), Panda"
    return {"env_name": TASKS[task].env_name, "type": 1, "env_kwargs": kw, "env_version": "robosuite 1.5"}


def low_dim_obs(raw: dict) -> dict[str, np.ndarray]:
    return {
        "object": np.asarray(raw["object-state"], dtype=np.float32),
        "robot0_eef_pos": np.asarray(raw["robot0_eef_pos"], dtype=np.float32),
        "robot0_eef_quat": np.asarray(raw["robot0_eef_quat"], dtype=np.float32),
        "robot0_gripper_qpos": np.asarray(raw["robot0_gripper_qpos"], dtype=np.float32),
    }
