"""How multimodal and mixed-quality are the MH-style demonstrations? A figure and its numbers.

    python eval/demo_modes.py --task lift --data data/lift_mh.hdf5 --ph data/lift_expert.hdf5

Reads a dataset written by ``collect_demos.py --mix mh`` (and optionally the single expert's
"PH" dataset for comparison) and writes ``docs/<task>_mh_modes.png`` and
``results/experts/<task>_mh_modes.json``:

(a) the hand's yaw at the first grasp against the object's yaw, per operator: operators take
    different ones of the object's symmetric grasps (or turn the other way, or not at all);
(b) the approach direction: the azimuth, seen from the grasp point, from which the hand came
    within 5 cm of it (the hand's xy position, first grasp);
(c) the spread of the demonstrators' actions from similar states: for sampled states, the k
    nearest states of *other* demos (z-scored low-dim observations) and the spread of their
    position commands: mean per-axis std, and the fraction of neighbour pairs (both moving)
    whose commands point more than 90 degrees apart; one pure expert is close to unimodal;
(d) demo length per operator (only successful demos are kept), with each operator's success rate;
(e) hesitations (steps commanding no motion) and failed grasps per kept demo, per operator;
(f) square only: where the nut's handle points once the nut is on the peg, per operator.

Push-T (``--task pusht``, ``docs/pusht_mh_modes.png``, ``results/experts/pusht_mh_modes.json``):
(a) detours round the block per operator: stretches where the block stays still and the agent
    walks at least 90 degrees around its centre, counted clockwise or counter-clockwise;
(b) the agent's paths in the block's frame for the two better operators;
(c) the spread of commanded moves (target minus agent position, px) from similar states, as (c) above.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Optional

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, provenance, write_json  # noqa: E402

from robot_suite.robomimic import Demo, read_demos  # noqa: E402
from robot_suite.tasks import OBS_KEYS, TASKS  # noqa: E402

SYMMETRY = {"lift": np.pi / 2, "can": None, "square": np.pi, "pusht": None}  # object yaw period that leaves a grasp the same
QUAT = {"lift": slice(3, 7), "can": slice(10, 14), "square": slice(10, 14)}  # the object's xyzw quaternion in obs "object"


def _yaw(quat_xyzw: np.ndarray) -> np.ndarray:
    """Heading of the body's x axis in the xy plane, for [..., 4] xyzw quaternions."""
    x, y, z, w = np.moveaxis(np.asarray(quat_xyzw, dtype=np.float64), -1, 0)
    return np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def first_grasp(demo: Demo) -> Optional[int]:
    """Step of the first close command (gripper action from open to closed)."""
    g = demo.actions[:, 6]
    onsets = np.flatnonzero((g[1:] > 0) & (g[:-1] <= 0)) + 1
    return int(onsets[0]) if len(onsets) else None


def still_fraction(demo: Demo) -> float:
    """Fraction of steps that command no motion at all (an operator's pauses)."""
    return float(np.mean(np.all(demo.actions[:, :6] == 0, axis=1)))


def grasp_features(demo: Demo, task: str) -> Optional[dict]:
    t = first_grasp(demo)
    if t is None:
        return None
    eef = demo.obs["robot0_eef_pos"]
    hand_yaw = float(_yaw(demo.obs["robot0_eef_quat"][t]))
    obj_yaw = float(_yaw(demo.obs["object"][t, QUAT[task]]))
    turn = float(_wrap(hand_yaw - _yaw(demo.obs["robot0_eef_quat"][0])))
    far = np.flatnonzero(np.linalg.norm(eef[:t, :2] - eef[t, :2], axis=1) > 0.05)
    azimuth = None
    if len(far):
        d = eef[far[-1], :2] - eef[t, :2]
        azimuth = float(np.arctan2(d[1], d[0]))
    return {"t": t, "hand_yaw": hand_yaw, "object_yaw": obj_yaw, "turn": turn, "azimuth": azimuth}


def _position_commands(demo: Demo) -> np.ndarray:
    return demo.actions[:, :3]


def neighbour_spread(demos: list[Demo], queries: int = 1500, k: int = 10, seed: int = 0,
                     scale: Optional[tuple[np.ndarray, np.ndarray]] = None, keys=OBS_KEYS,
                     commands=_position_commands, moving: float = 0.1) -> dict:
    """Action spread among the k nearest states of other demos (see the module docstring);
    ``commands`` maps a demo to the motion commands compared, ``moving`` is the norm above which a
    command counts as a move."""
    x = np.concatenate([np.concatenate([d.obs[key] for key in keys], axis=1) for d in demos]).astype(np.float32)
    a = np.concatenate([commands(d) for d in demos]).astype(np.float32)
    owner = np.concatenate([np.full(len(d), i) for i, d in enumerate(demos)])
    mu, sd = scale if scale is not None else (x.mean(0), x.std(0) + 1e-6)
    z = (x - mu) / sd
    rng = np.random.default_rng(seed)
    q = rng.choice(len(z), size=min(queries, len(z)), replace=False)
    stds, opposed, pairs, dists = [], 0, 0, []
    for chunk in np.array_split(q, max(1, len(q) // 200)):
        d2 = ((z[chunk, None, :] - z[None, :, :]) ** 2).sum(-1)
        d2[owner[chunk][:, None] == owner[None, :]] = np.inf  # neighbours from other demos only
        nn = np.argpartition(d2, k, axis=1)[:, :k]
        for row, idx in zip(chunk, nn):
            acts = a[idx]
            stds.append(acts.std(0).mean())
            dists.append(float(np.sqrt(np.sort(d2[np.where(chunk == row)[0][0], idx])).mean()))
            moves = acts[np.linalg.norm(acts, axis=1) > moving]
            if len(moves) > 1:
                u = moves / np.linalg.norm(moves, axis=1, keepdims=True)
                cos = u @ u.T
                iu = np.triu_indices(len(u), 1)
                opposed += int((cos[iu] < 0).sum())
                pairs += len(iu[0])
    return {"queries": len(q), "k": k, "mean_action_std": float(np.mean(stds)),
            "opposed_pair_fraction": opposed / max(pairs, 1), "mean_neighbour_distance_z": float(np.mean(dists))}


def push_moves(demo: Demo) -> np.ndarray:
    """Push-T: the commanded move of each step (target minus agent position, px)."""
    return demo.actions - demo.obs["agent_pos"]


def detours(demo: Demo, min_turn: float = np.pi / 2, min_radius: float = 60.0) -> list[float]:
    """Signed angles (rad, + counter-clockwise) of the stretches in which the block stays still and
    the agent, at least ``min_radius`` px from the block's centre, walks at least ``min_turn`` round it."""
    centre = demo.obs["block_keypoints"].reshape(len(demo), 8, 2).mean(1)
    still = np.r_[np.abs(np.diff(centre, axis=0)).max(1) < 0.5, False]
    rel = demo.obs["agent_pos"] - centre
    far = np.linalg.norm(rel, axis=1) > min_radius
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    out, total = [], 0.0
    for t in range(len(demo) - 1):
        if still[t] and far[t] and far[t + 1]:
            total += _wrap(ang[t + 1] - ang[t])
        else:
            if abs(total) >= min_turn:
                out.append(total)
            total = 0.0
    return out


def push_modes(args, demos: list[Demo], by_op: dict[str, list[Demo]], success: dict) -> None:
    """The Push-T figure and numbers (module docstring)."""
    import matplotlib.pyplot as plt

    from robot_suite.pusht import PUSHT_OBS_KEYS, T_OUTLINE

    ops = list(by_op)
    per_op = {}
    for op in ops:
        turns = [a for d in by_op[op] for a in detours(d)]
        lengths = np.array([len(d) for d in by_op[op]])
        per_op[op] = {"quality": str(by_op[op][0].attrs["quality"]), "demos": len(by_op[op]),
                      "success_rate": success.get(op), "mean_length": float(lengths.mean()),
                      "detours": len(turns), "detours_ccw": int(sum(a > 0 for a in turns)),
                      "detours_per_demo": len(turns) / len(by_op[op])}
    x_all = np.concatenate([np.concatenate([d.obs[k] for k in PUSHT_OBS_KEYS], axis=1) for d in demos])
    scale = (x_all.mean(0), x_all.std(0) + 1e-6)
    sets = {"MH all": demos, "MH better": [d for d in demos if d.attrs["quality"] == "better"], **by_op}
    if args.ph is not None and args.ph.exists():
        sets = {"PH expert": read_demos(args.ph, PUSHT_OBS_KEYS)[: len(sets["MH better"])], **sets}
        turns = [a for d in sets["PH expert"] for a in detours(d)]
        per_op["PH expert"] = {"detours": len(turns), "detours_ccw": int(sum(a > 0 for a in turns)),
                               "detours_per_demo": len(turns) / len(sets["PH expert"])}
    spread = {name: neighbour_spread(ds, args.queries, args.k, scale=scale, keys=PUSHT_OBS_KEYS,
                                     commands=push_moves, moving=5.0) for name, ds in sets.items()}
    fig, axes = plt.subplots(1, 3, figsize=(17, 5))
    names = list(per_op)
    xs = np.arange(len(names))
    ccw = [per_op[n]["detours_ccw"] for n in names]
    cw = [per_op[n]["detours"] - per_op[n]["detours_ccw"] for n in names]
    axes[0].bar(xs, ccw, 0.6, label="counter-clockwise")
    axes[0].bar(xs, cw, 0.6, bottom=ccw, label="clockwise")
    axes[0].set_xticks(xs)
    axes[0].set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    axes[0].set_ylabel("detours of >= 90 deg round the still block")
    axes[0].set_title("(a) which way round the block")
    axes[0].legend(fontsize=8)
    ax = axes[1]
    outline = np.vstack([T_OUTLINE, T_OUTLINE[:1]])
    ax.plot(outline[:, 0], outline[:, 1], color="k", lw=2)
    for op, color in zip([o for o in ops if per_op[o]["quality"] == "better"][:2], ("tab:blue", "tab:orange")):
        for d in by_op[op][:12]:
            kp = d.obs["block_keypoints"].reshape(len(d), 8, 2)
            pos = (kp[:, 0] + kp[:, 1]) / 2  # corners 0 and 1 are (-60, 0) and (60, 0) in the block's frame
            u = (kp[:, 1] - kp[:, 0]) / np.linalg.norm(kp[:, 1] - kp[:, 0], axis=1, keepdims=True)
            rel = d.obs["agent_pos"] - pos
            local = np.stack([rel[:, 0] * u[:, 0] + rel[:, 1] * u[:, 1], -rel[:, 0] * u[:, 1] + rel[:, 1] * u[:, 0]], 1)
            ax.plot(local[:, 0], local[:, 1], color=color, lw=0.6, alpha=0.6)
        ax.plot([], [], color=color, label=op)
    ax.set_aspect("equal")
    ax.set_xlim(-250, 250)
    ax.set_ylim(-200, 300)
    ax.set_title("(b) agent paths in the block's frame")
    ax.legend(fontsize=8)
    ax = axes[2]
    names = list(spread)
    xs = np.arange(len(names))
    ax.bar(xs, [spread[n]["opposed_pair_fraction"] for n in names], 0.6)
    ax.set_xticks(xs)
    ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    ax.set_title(f"(c) neighbours' moves > 90 deg apart ({args.k} nearest states, other demos)", fontsize=10)
    fig.suptitle(f"pusht: scripted MH-style operators ({len(demos)} demos)")
    fig.tight_layout()
    fig_path = args.fig or REPO / "docs" / "pusht_mh_modes.png"
    fig.savefig(fig_path, dpi=110)
    out = {"provenance": provenance(), "task": "pusht", "data": str(args.data), "ph": str(args.ph) if args.ph else None,
           "operators": per_op, "neighbour_action_spread": spread,
           "units": "neighbours' action std in px of commanded move (target - agent position)"}
    write_json(args.out or REPO / "results" / "experts" / "pusht_mh_modes.json", out)
    print(f"wrote {fig_path}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True, choices=sorted(SYMMETRY))
    ap.add_argument("--data", type=Path, required=True, help="collect_demos.py --mix mh output")
    ap.add_argument("--ph", type=Path, default=None, help="the single expert's dataset, for comparison")
    ap.add_argument("--report", type=Path, default=None, help="results/experts/<task>_mh.json (success rates)")
    ap.add_argument("--queries", type=int, default=1500)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--fig", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    demos = read_demos(args.data, TASKS[args.task].obs_keys)
    by_op: dict[str, list[Demo]] = defaultdict(list)
    for d in demos:
        by_op[str(d.attrs["operator"])].append(d)
    ops = list(by_op)
    quality = {op: str(by_op[op][0].attrs["quality"]) for op in ops}
    report_path = args.report or REPO / "results" / "experts" / f"{args.task}_mh.json"
    success = {}
    if report_path.exists():
        success = {r["operator"]: r["success_rate"] for r in json.loads(report_path.read_text())["operators"]}
    if args.task == "pusht":
        return push_modes(args, demos, by_op, success)

    per_op, feats = {}, {}
    for op in ops:
        f = [g for g in (grasp_features(d, args.task) for d in by_op[op]) if g is not None]
        feats[op] = f
        turn = np.array([g["turn"] for g in f])
        az = np.array([g["azimuth"] for g in f if g["azimuth"] is not None])
        lengths = np.array([len(d) for d in by_op[op]])
        per_op[op] = {
            "quality": quality[op], "demos": len(by_op[op]), "success_rate": success.get(op),
            "mean_length": float(lengths.mean()), "std_length": float(lengths.std()),
            "still_step_fraction": float(np.mean([still_fraction(d) for d in by_op[op]])),
            "mean_failed_grasps": float(np.mean([int(d.attrs.get("failed_grasps", 0)) for d in by_op[op]])),
            "hand_turn_before_grasp_deg": {"mean": float(np.degrees(turn.mean())), "std": float(np.degrees(turn.std())),
                                           "fraction_ccw_over_10deg": float((turn > np.radians(10)).mean()),
                                           "fraction_cw_over_10deg": float((turn < -np.radians(10)).mean())},
            "approach_azimuth_deg": {"circular_mean": float(np.degrees(np.arctan2(np.sin(az).mean(), np.cos(az).mean()))),
                                     "resultant_length": float(np.hypot(np.sin(az).mean(), np.cos(az).mean()))},
        }

    x_all = np.concatenate([np.concatenate([d.obs[k] for k in OBS_KEYS], axis=1) for d in demos])
    scale = (x_all.mean(0), x_all.std(0) + 1e-6)  # one z-scoring for every dataset compared
    sets = {"MH all": demos,
            "MH better": [d for d in demos if d.attrs["quality"] == "better"]}
    for op in ops:
        sets[op] = by_op[op]
    if args.ph is not None and args.ph.exists():
        sets = {"PH expert": read_demos(args.ph, OBS_KEYS)[: len(sets["MH better"])], **sets}
    spread = {name: neighbour_spread(ds, args.queries, args.k, scale=scale) for name, ds in sets.items()}

    colors = plt.get_cmap("tab10")
    fig, axes = plt.subplots(2, 3, figsize=(17, 9))
    ax = axes[0, 0]
    period = SYMMETRY[args.task]
    for i, op in enumerate(ops):
        obj = np.array([g["object_yaw"] for g in feats[op]])
        if period is not None:
            obj = _wrap(obj * (2 * np.pi / period)) * period / (2 * np.pi)  # object yaw up to its symmetry
        ax.scatter(np.degrees(obj), np.degrees([g["hand_yaw"] for g in feats[op]]), s=12, color=colors(i), label=op)
    ax.set_xlabel("object yaw at grasp, deg" + (f" (mod {np.degrees(period):.0f})" if period else ""))
    ax.set_ylabel("hand yaw at grasp, deg")
    ax.set_title("(a) which grasp: hand yaw vs object yaw")
    ax.legend(fontsize=7)
    ax = axes[0, 1]
    bins = np.linspace(-180, 180, 25)
    for i, op in enumerate(ops):
        az = [np.degrees(g["azimuth"]) for g in feats[op] if g["azimuth"] is not None]
        ax.hist(az, bins=bins, histtype="step", lw=2, color=colors(i), label=op)
    ax.set_xlabel("approach azimuth from the grasp point, deg (\u00b1180: robot side, 90: +y side)")
    ax.set_ylabel("demos")
    ax.set_title("(b) approach direction at the first grasp")
    ax = axes[1, 0]
    names = list(spread)
    xs = np.arange(len(names))
    ax.bar(xs - 0.2, [spread[n]["mean_action_std"] for n in names], 0.4, label="mean per-axis std of neighbours' commands")
    ax.bar(xs + 0.2, [spread[n]["opposed_pair_fraction"] for n in names], 0.4,
           label="fraction of moving neighbour pairs > 90 deg apart")
    ax.set_xticks(xs)
    ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    ax.set_title(f"(c) position commands from similar states ({args.k} nearest states of other demos)")
    ax.legend(fontsize=8)
    ax = axes[1, 1]
    ax.boxplot([[len(d) for d in by_op[op]] for op in ops], tick_labels=[op.replace("_operator_", " ") for op in ops])
    for i, op in enumerate(ops):
        if success.get(op) is not None:
            ax.annotate(f"{100 * success[op]:.0f}%", (i + 1, 0.97), xycoords=("data", "axes fraction"), ha="center",
                        fontsize=9)
    ax.set_ylabel("demo length, steps")
    ax.set_title("(d) successful demo lengths; operator success rate on top")
    ax = axes[0, 2]
    xs = np.arange(len(ops))
    ax.bar(xs - 0.2, [per_op[op]["still_step_fraction"] for op in ops], 0.4, label="fraction of still steps (pauses)")
    ax.bar(xs + 0.2, [per_op[op]["mean_failed_grasps"] for op in ops], 0.4, label="failed grasps per kept demo")
    ax.set_xticks(xs)
    ax.set_xticklabels([op.replace("_operator_", " ") for op in ops])
    ax.set_title("(e) hesitations and re-grasps in the kept demos")
    ax.legend(fontsize=8)
    ax = axes[1, 2]
    if args.task == "square":  # the handle's direction once the nut is on the peg
        placed = {op: np.degrees([_yaw(d.obs["object"][-1, QUAT[args.task]]) for d in by_op[op]]) for op in ops}
        for op in ops:
            per_op[op]["handle_direction_on_peg_deg"] = {
                name: float(np.mean(np.abs(_wrap(np.radians(placed[op] - c))) < np.radians(30)))
                for name, c in (("left_+90", 90), ("robot_180", 180), ("right_-90", -90))}
        ax.hist([placed[op] for op in ops], bins=np.linspace(-180, 180, 13), color=[colors(i) for i in range(len(ops))],
                label=ops)
        ax.set_xlabel("handle direction on the peg, deg (180: toward the robot)")
        ax.set_ylabel("demos")
        ax.set_title("(f) where the handle points when the nut is placed")
        ax.legend(fontsize=7)
    else:
        ax.axis("off")
    fig.suptitle(f"{args.task}: scripted MH-style operators ({len(demos)} demos)")
    fig.tight_layout()
    fig_path = args.fig or REPO / "docs" / f"{args.task}_mh_modes.png"
    fig_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(fig_path, dpi=110)
    out = {"provenance": provenance(), "task": args.task, "data": str(args.data), "ph": str(args.ph) if args.ph else None,
           "operators": per_op, "neighbour_action_spread": spread, "figure": str(fig_path.relative_to(REPO))}
    write_json(args.out or REPO / "results" / "experts" / f"{args.task}_mh_modes.json", out)
    print(json.dumps({n: {k: round(v, 3) for k, v in s.items()} for n, s in spread.items()}, indent=1))
    print(f"wrote {fig_path}")


if __name__ == "__main__":
    main()
