"""Demonstrations in robomimic's hdf5 layout (read and write with h5py; robomimic itself is not
needed). A user's real robomimic ``low_dim.hdf5`` loads through the same reader.

Layout::

    data/                      attrs: total (int), env_args (JSON: env_name, type, env_kwargs)
      demo_0/                  attrs: num_samples
        obs/<key>              [T, ...] float; camera frames (``agentview_image``, ...) [T, H, W, 3]
                               uint8, gzip-compressed one frame per chunk
        actions                [T, action_dim]
        rewards, dones         [T]
        states                 [T, state_dim] (optional: MuJoCo flattened states)
    mask/                      optional filter keys (e.g. "train", "valid"): arrays of demo names
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

__all__ = ["Demo", "write_demos", "read_demos", "read_env_args", "read_masks", "describe_demonstrators"]


@dataclass
class Demo:
    obs: dict[str, np.ndarray]
    actions: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    states: Optional[np.ndarray] = None
    attrs: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.actions.shape[0])


def write_demos(path: Path, demos: Iterable[Demo], env_args: dict, masks: Optional[dict[str, Sequence[str]]] = None) -> int:
    """Write demos atomically (a temporary file renamed into place). Returns the number written."""
    import h5py

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    n = total = 0
    with h5py.File(tmp, "w") as f:
        data = f.create_group("data")
        for i, demo in enumerate(demos):
            g = data.create_group(f"demo_{i}")
            for k, v in demo.obs.items():
                v = np.asarray(v)
                if v.dtype == np.uint8 and v.ndim == 4:  # camera frames [T, H, W, 3]: one chunk per frame
                    g.create_dataset(f"obs/{k}", data=v, chunks=(1, *v.shape[1:]), compression="gzip",
                                     compression_opts=4)
                else:
                    g.create_dataset(f"obs/{k}", data=v)
            g.create_dataset("actions", data=np.asarray(demo.actions, dtype=np.float64))
            g.create_dataset("rewards", data=np.asarray(demo.rewards, dtype=np.float64))
            g.create_dataset("dones", data=np.asarray(demo.dones, dtype=np.int64))
            if demo.states is not None:
                g.create_dataset("states", data=np.asarray(demo.states))
            g.attrs["num_samples"] = len(demo)
            for k, v in demo.attrs.items():
                g.attrs[k] = v
            n += 1
            total += len(demo)
        data.attrs["total"] = total
        data.attrs["env_args"] = json.dumps(env_args)
        for name, keys in (masks or {}).items():
            f.create_dataset(f"mask/{name}", data=np.array([k.encode() for k in keys]))
    os.replace(tmp, path)
    return n


def _demo_sort_key(name: str) -> int:
    return int(name.split("_")[-1])


def read_env_args(path: Path) -> dict:
    import h5py

    with h5py.File(path, "r") as f:
        return json.loads(f["data"].attrs["env_args"])


def read_masks(path: Path) -> dict[str, list[str]]:
    """The filter keys of a dataset: name -> demo names (empty when it has none)."""
    import h5py

    with h5py.File(path, "r") as f:
        if "mask" not in f:
            return {}
        return {name: [k.decode() for k in f["mask"][name][()]] for name in f["mask"]}


def describe_demonstrators(path: Path) -> str:
    """Who made a dataset's demonstrations, from its filter keys: robomimic's quality masks (``better``,
    ``okay``, ``worse``) mark a mix of operators; without them the data is one demonstrator's."""
    if {"better", "okay", "worse"} <= read_masks(path).keys():
        return "scripted operators of mixed quality in robomimic MH proportions (more regular than human operators)"
    return "a single scripted expert (uniform, not human data)"


def read_demos(path: Path, obs_keys: Optional[Sequence[str]] = None, filter_key: Optional[str] = None,
               limit: Optional[int] = None) -> list[Demo]:
    """Read demos (sorted by index); ``obs_keys`` selects observations (default: all)."""
    import h5py

    out = []
    with h5py.File(path, "r") as f:
        if "data" not in f:
            raise ValueError(f"{path} is not a robomimic dataset: no 'data' group")
        names = sorted(f["data"].keys(), key=_demo_sort_key)
        if filter_key is not None:
            if f"mask/{filter_key}" not in f:
                raise KeyError(f"{path} has no filter key {filter_key!r}")
            keep = {k.decode() for k in f[f"mask/{filter_key}"][()]}
            names = [n for n in names if n in keep]
        for name in names[:limit]:
            g = f["data"][name]
            keys = obs_keys if obs_keys is not None else list(g["obs"].keys())
            missing = [k for k in keys if k not in g["obs"]]
            if missing:
                raise KeyError(f"{path}:{name} lacks observation keys {missing}; has {list(g['obs'].keys())}")
            out.append(Demo(
                obs={k: g["obs"][k][()] for k in keys},
                actions=g["actions"][()],
                rewards=g["rewards"][()] if "rewards" in g else np.zeros(len(g["actions"])),
                dones=g["dones"][()] if "dones" in g else np.zeros(len(g["actions"]), dtype=np.int64),
                states=g["states"][()] if "states" in g else None,
                attrs=dict(g.attrs),
            ))
    return out
