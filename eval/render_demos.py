"""Camera frames for recorded demonstrations: a low-dim robomimic hdf5 in, its image counterpart out.

    MUJOCO_GL=egl python eval/render_demos.py --data data/lift_mh.hdf5 --out data/lift_mh_image.hdf5 \
        [--cameras agentview robot0_eye_in_hand] [--size 84] [--limit N]

Like robomimic's ``dataset_states_to_obs.py``: every recorded MuJoCo state of every demo is restored
in an env that renders the cameras offscreen (:func:`robot_suite.tasks.render_state`), and the frames
are stored upright as ``obs/<camera>_image`` uint8 [T, H, W, 3] next to the low-dim keys, actions,
states, attributes and filter keys of the input. As a check that the restored scene is the recorded
one, the low-dim observation rendered from each state is compared with the recorded one; the largest
difference goes into the report ``<out>.json`` (with the cost per frame and provenance). It is not
zero: ``mj_step`` computes positions before it integrates, so a recorded observation lags its state
by one physics substep (under a millimetre for the scripted experts), while a restored state's
positions are computed from that state itself. It is reported per key because an object's
quaternion (inside ``object``) can come out as ``q`` in one and ``-q`` in the other, the same
rotation: robosuite does not fix the sign, and consecutive recorded frames flip it too.

Rendering is the expensive part (about 0.1 s per frame for two 84x84 cameras on one CPU core with software GL): demos are
rendered in chunks of ``--chunk`` kept under ``<out>.parts/``, so an interrupted run resumes, and the
output is written atomically at the end.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import parse_args, provenance, write_json  # noqa: E402

from robot_suite.robomimic import Demo, read_demos, read_env_args, read_masks, write_demos  # noqa: E402
from robot_suite.tasks import (CAMERAS, TASKS, camera_obs, env_args, low_dim_obs, make_env,  # noqa: E402
                               render_state, reset_env, task_of_env)


def render_demo(env, demo: Demo, cameras: list[str]) -> tuple[Demo, dict[str, float]]:
    """``demo`` with camera frames added, and per low-dim key the largest difference between the
    observation rendered from its states and the recorded one."""
    if demo.states is None:
        raise ValueError("a demo without recorded states cannot be rendered (collect it with eval/collect_demos.py)")
    reset_env(env, int(demo.attrs.get("seed", 0)))  # the scene of the episode (object models, placements)
    frames: dict[str, list[np.ndarray]] = {f"{c}_image": [] for c in cameras}
    worst: dict[str, float] = {}
    for t, state in enumerate(demo.states):
        raw = render_state(env, state)
        for k, img in camera_obs(raw, cameras).items():
            frames[k].append(img)
        for k, v in low_dim_obs(raw).items():
            if k in demo.obs:
                worst[k] = max(worst.get(k, 0.0), float(np.abs(v - demo.obs[k][t]).max()))
    obs = dict(demo.obs, **{k: np.stack(v) for k, v in frames.items()})
    return Demo(obs=obs, actions=demo.actions, rewards=demo.rewards, dones=demo.dones, states=demo.states,
                attrs=demo.attrs), worst


def merge_worst(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    """Per-key maximum of two difference reports."""
    return {k: max(a.get(k, 0.0), b.get(k, 0.0)) for k in sorted(set(a) | set(b))}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="a low-dim robomimic hdf5 with recorded states")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cameras", nargs="+", default=list(CAMERAS))
    ap.add_argument("--size", type=int, default=84, help="frame height and width")
    ap.add_argument("--limit", type=int, default=None, help="render only the first N demos")
    ap.add_argument("--chunk", type=int, default=10, help="demos per resumable part")
    args = parse_args(ap, argv)
    if args.size < 8:
        ap.error(f"--size must be at least 8, got {args.size}")
    task = task_of_env(read_env_args(args.data)["env_name"])
    if TASKS[task].suite != "robosuite":
        ap.error(f"{args.data} is a {task} dataset: camera frames are rendered for the robosuite tasks")
    demos = read_demos(args.data, limit=args.limit)
    kept = {f"demo_{i}" for i in range(len(demos))}  # filter keys keep only the demos rendered (--limit)
    masks = {k: [n for n in v if n in kept] for k, v in read_masks(args.data).items()}
    parts = args.out.with_name(args.out.name + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    # parts rendered under another key render again
    key = {"data": str(args.data), "data_bytes": args.data.stat().st_size, "cameras": args.cameras,
           "size": args.size, "chunk": args.chunk, "difference": "per key"}
    env = make_env(task, cameras=args.cameras, image_size=args.size)
    rendered, worst, frames, seconds = [], {}, 0, 0.0
    for start in tqdm(range(0, len(demos), args.chunk), desc=f"render {task}"):
        part, meta = parts / f"{start:05d}.hdf5", parts / f"{start:05d}.json"
        if part.exists() and meta.exists() and json.loads(meta.read_text()).get("key") == key:
            info = json.loads(meta.read_text())
            rendered.extend(read_demos(part))
        else:
            t0, chunk, info = time.perf_counter(), [], {"key": key, "worst": {}}
            for demo in demos[start:start + args.chunk]:
                out, w = render_demo(env, demo, args.cameras)
                chunk.append(out)
                info["worst"] = merge_worst(info["worst"], w)
            info.update(frames=sum(len(d) for d in chunk), seconds=time.perf_counter() - t0)
            write_demos(part, chunk, env_args(task, args.cameras, args.size))
            write_json(meta, info)
            rendered.extend(chunk)
        worst, frames, seconds = merge_worst(worst, info["worst"]), frames + info["frames"], seconds + info["seconds"]
    write_demos(args.out, rendered, env_args(task, args.cameras, args.size), masks=masks)
    report = {"data": str(args.data), "out": str(args.out), "task": task, "demos": len(rendered), "frames": frames,
              "cameras": args.cameras, "size": args.size, "ms_per_frame": 1e3 * seconds / max(frames, 1),
              "max_low_dim_difference": max(worst.values(), default=0.0), "low_dim_difference_by_key": worst,
              "provenance": provenance()}
    write_json(args.out.with_suffix(".json"), report)
    shutil.rmtree(parts)
    print(f"wrote {args.out}: {len(rendered)} demos, {frames} frames, {report['ms_per_frame']:.0f} ms per frame; "
          "rendered low-dim observations against the recorded ones, largest difference per key: "
          + ", ".join(f"{k} {v:.2e}" for k, v in sorted(worst.items())))
    return report


if __name__ == "__main__":
    main()
