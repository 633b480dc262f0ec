"""Figures of the robot experiments (PNG under docs/), from committed checkpoints and result JSONs.

    python eval/figures.py masks --task lift --checkpoint checkpoints/lift_dpt --pruner checkpoints/pruners/lift_tts_0.93 \
        --trajectories data/trajectories/lift.pt          # pruning masks per rollout iteration (paper Figs 12-16)
    python eval/figures.py similarity --task lift --checkpoint checkpoints/lift_dpt \
        --trajectories data/trajectories/lift.pt          # forward / timestep / rollout feature similarity (Fig 9)
    python eval/figures.py data-efficiency --task lift    # success vs trajectories (Figs 10-11; recipes/data_efficiency.sh,
                                                          # recipes/pruner_data_efficiency.sh)
    python eval/figures.py frontier --task lift [--checkpoint checkpoints/lift_mh_dpt]
                                                          # success vs speed-up per batch size (eval/frontier_latency.py)
    python eval/figures.py image-frontier                 # digits DiT: FID vs speed-up (eval/image_latency.py)
    python eval/figures.py training-curves --task pusht --checkpoint checkpoints/pusht_mh_dpt_17k
                                                          # reference-recipe pruners: validation per epoch

Masks and similarities use held-out recorded episodes (index >= ``--first-episode``, past the
pruner's training and validation sets) with the recorded noise seeds.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, add_all_episodes_option, parse_args, policy_slug  # noqa: E402
from common import frontier as frontier_join  # noqa: E402
from robot_suite.replay import replay  # noqa: E402

import tts  # noqa: E402
from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.static_search import record_branch_outputs  # noqa: E402
from tts.trajectories import REPLAY_KEYS, load_trajectories  # noqa: E402

DOCS = REPO / "docs"
COLORS = ["#1b1b1b", "#e6550d", "#3182bd", "#31a354"]  # compute, forward, timestep, rollout


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def masks(args) -> Path:
    from matplotlib.colors import ListedColormap

    plt = _plt()
    episodes, _ = load_trajectories(args.trajectories, successful_only=not args.all_episodes)
    ep = episodes[args.first_episode]
    policy = load_policy(args.checkpoint)
    pruner = tts.load_pruner(args.pruner)
    with tts.accelerate(policy, pruner.config.directions, pruner=pruner, sparsity=args.sparsity) as acc:
        replay(policy, [ep])
        calls = acc.summary().calls
    n = min(args.calls, len(calls))
    fig, axes = plt.subplots(1, n, figsize=(1.6 * n + 1, 5), sharey=True)
    axes = np.atleast_1d(axes)
    for r, ax in enumerate(axes):
        d = calls[r].decisions()[:, 0].numpy()  # [K, nb]
        ax.imshow(d, aspect="auto", cmap=ListedColormap(COLORS), vmin=0, vmax=3, interpolation="nearest")
        sp = float((d != 0).mean())
        ax.set_title(f"call {r}" + (" (dense)" if calls[r].dense else f"\n{sp:.0%} reused"), fontsize=8)
        ax.set_xlabel("branch (SA, CA, FF per layer)", fontsize=7)
        ax.tick_params(labelsize=6)
    axes[0].set_ylabel("denoising step k")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in COLORS]
    fig.legend(handles, ["compute", "forward", "timestep", "rollout"], loc="lower center", ncol=4, fontsize=8)
    mode = "argmax" if args.sparsity is None else f"budget {args.sparsity:g}"
    fig.suptitle(f"{args.task}: pruner decisions per rollout iteration ({Path(args.pruner).name}, {mode}; "
                 f"held-out episode seed {ep['seed']})", fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    out = DOCS / f"{policy_slug(args.task, args.checkpoint)}_pruning_masks.png"
    fig.savefig(out, dpi=110)
    return out


def _cos(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.reshape(a.shape[0], -1), b.reshape(b.shape[0], -1)
    return float(torch.nn.functional.cosine_similarity(a, b, dim=1).mean())


def similarity(args) -> Path:
    plt = _plt()
    episodes, _ = load_trajectories(args.trajectories, successful_only=not args.all_episodes)
    eps = episodes[args.first_episode:args.first_episode + args.episodes]
    policy = load_policy(args.checkpoint)
    n_frames = min(len(e["obs"]) for e in eps)
    eps = [{k: v[:n_frames] if k in REPLAY_KEYS else v for k, v in e.items()} for e in eps]
    outs = record_branch_outputs(policy, lambda: replay(policy, eps))  # [call][k][b] -> [E, H, D]
    K, nb = len(outs[0]), len(outs[0][0])
    sims = {name: np.full((K, nb), np.nan) for name in ("forward", "timestep", "rollout")}
    for k in range(K):
        for b in range(nb):
            vals = {"forward": [], "timestep": [], "rollout": []}
            for r, call in enumerate(outs):
                if b >= 3:
                    vals["forward"].append(_cos(call[k][b], call[k][b - 3]))  # same kind, previous layer
                if k > 0:
                    vals["timestep"].append(_cos(call[k][b], call[k - 1][b]))
                if r > 0:
                    vals["rollout"].append(_cos(call[k][b], outs[r - 1][k][b]))
            for name, v in vals.items():
                if v:
                    sims[name][k, b] = np.mean(v)
    fig, axes = plt.subplots(1, 4, figsize=(14, 4.2), gridspec_kw={"width_ratios": [1, 1, 1, 1.3]})
    for ax, (name, m) in zip(axes, sims.items()):
        im = ax.imshow(m, aspect="auto", vmin=0, vmax=1, cmap="viridis", interpolation="nearest")
        ax.set_title(f"{name} direction", fontsize=9)
        ax.set_xlabel("branch (SA, CA, FF per layer)", fontsize=8)
    axes[0].set_ylabel("denoising step k")
    fig.colorbar(im, ax=axes[2], fraction=0.05)
    ks = np.arange(K)
    for name, m in sims.items():
        rows = ~np.isnan(m).all(axis=1)  # timestep: step 0 has no earlier step
        axes[3].plot(ks[rows], np.nanmean(m[rows], axis=1), label=name)
    axes[3].set_xlabel("denoising step k")
    axes[3].set_ylabel("mean cosine similarity over branches")
    axes[3].legend(fontsize=8)
    axes[3].grid(alpha=0.3)
    fig.suptitle(f"{args.task}: cosine similarity of branch outputs with what each direction would reuse "
                 f"({len(eps)} held-out episodes x {n_frames} calls, dense policy)", fontsize=9)
    fig.tight_layout()
    out = DOCS / f"{policy_slug(args.task, args.checkpoint)}_feature_similarity.png"
    fig.savefig(out, dpi=110)
    return out


def _prior_calibration(prior: Optional[str]) -> Optional[int]:
    """Calibration trajectories of the schedule a pruner was started from (its ``--prior``), if any."""
    path = REPO / prior if prior else None
    return json.loads(path.read_text()).get("calibration_episodes") if path and path.exists() else None


def _schedule_label(sched: dict) -> str:
    """Series of a searched whole-step schedule: one per sparsity and calibration-call budget (the
    ``--calls`` asked for; a search on few trajectories uses the windows it has, see
    ``calibration_calls_used``)."""
    return (f"searched steps, rho={sched['sparsity']:g}, <= {sched.get('calibration_calls', '?')} calls "
            "(calibration trajectories)")


def _efficiency_rows(task: str) -> dict[str, list[tuple[int, float]]]:
    """(training or calibration trajectories, success) per series, from finished result JSONs:
    TTS pruners by their ``n_train_episodes``; searched whole-step schedules (``file:`` rows) by
    their ``calibration_episodes``."""
    series: dict[str, list[tuple[int, float]]] = {}
    for path in sorted((REPO / "results" / "robot").glob(f"{task}_*.json")):
        r = json.loads(path.read_text())
        if "success_rate" not in r or r.get("episodes_done") != r.get("episodes_requested"):
            continue
        meta = r.get("pruner_metadata") or {}
        if "n_train_episodes" in meta:
            if abs(r["tts"]["sparsity_non_dense_calls"] - 0.93) < 0.01:  # the pruners run at 93%
                pipeline = meta["n_train_episodes"] == _prior_calibration(meta.get("prior"))
                label = ("TTS: search + step-query pruner on the same trajectories" if pipeline  # pruner_data_efficiency.sh
                         else "TTS pruners near rho=0.93, recipes differ (training trajectories)")
                series.setdefault(label, []).append((meta["n_train_episodes"], r["success_rate"]))
            continue
        if not r["method"].startswith("file:") or "+" in r["method"]:
            continue
        plan = REPO / "results" / "schedules" / f"{r['method'][len('file:'):]}.json"
        if not plan.exists():
            continue
        sched = json.loads(plan.read_text())
        if sched.get("method", "").startswith("compute steps shared"):
            series.setdefault(_schedule_label(sched), []).append((sched["calibration_episodes"], r["success_rate"]))
    return series


def data_efficiency(args) -> Path:
    plt = _plt()
    series = _efficiency_rows(args.task)
    if not series:
        raise SystemExit(f"no {args.task} results with training / calibration trajectory counts in results/robot/")
    fig, ax = plt.subplots(figsize=(6.0, 4.6))
    for i, ((label, rows), color) in enumerate(zip(sorted(series.items()), COLORS[1:])):
        shift = 1.1 ** (i - 1)  # series that coincide stay visible side by side
        rows = [(n * shift, s) for n, s in rows]
        ns = sorted({n for n, _ in rows})
        if len(ns) > 1:
            means = [np.mean([s for n2, s in rows if n2 == n]) for n in ns]
            ax.plot(ns, means, "o-", color=color, label=f"{label}, mean over runs")
        ax.scatter([n for n, _ in rows], [s for _, s in rows], color=color, s=12, alpha=0.6,
                   label=None if len(ns) > 1 else f"{label}, one dot per run")
    dense = [json.loads(p.read_text())["success_rate"]
             for p in sorted((REPO / "results" / "robot").glob(f"{args.task}_dense_*.json"))]
    if dense:
        ax.axhline(float(np.mean(dense)), color="k", ls="--", label=f"dense (mean of {len(dense)} seeds)")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("trajectories")
    ax.set_ylabel("success rate (50 test episodes per seed)")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=1, frameon=False)
    ax.grid(alpha=0.3)
    ax.set_title(f"{args.task}: success vs number of trajectories", fontsize=9)
    fig.tight_layout()
    out = DOCS / f"{args.task}_data_efficiency.png"
    fig.savefig(out, dpi=110)
    return out


FAMILY_STYLE = {"ddim": ("#3182bd", "DDIM-k (leading, Diffusion Policy's)"),
                "ddim-trailing": ("#9ecae1", "DDIM-k (trailing)"), "dpm": ("#31a354", "DPM-Solver++-k"),
                "ddpm": ("#756bb1", "DDPM-k (stochastic)")}


def _point_label(method: str, prefix: str) -> str:
    """A sparse method's label without what every point of the figure shares (``file:`` and the
    policy's schedule-name prefix), cut to 34 characters."""
    text = method.replace("file:", "").replace("pruner:", "pruner ").replace(f"{prefix}_", "")
    return text if len(text) < 34 else text[:32] + ".."


def _frontier_panels(plt, batches: list[int], points_of, name: str):
    """One panel per batch size; yields (axis, batch, points) for the measured ones and titles the
    others "not measured"."""
    fig, axes = plt.subplots(1, len(batches), figsize=(6.5 * len(batches), 4.6), squeeze=False)

    def measured():
        for ax, batch in zip(axes[0], batches):
            points = points_of(batch)
            if points:
                yield ax, batch, points
            else:
                ax.set_title(f"{name}, batch {batch}: not measured")
    return fig, measured()


def frontier(args) -> Path:
    """One panel per batch size: the score (success with its Wilson 95% interval, or Push-T's mean
    best coverage with a normal one) against speed-up over dense, the fewer-step samplers as lines
    through their k, dense and every sparse method as points."""
    plt = _plt()
    folder = REPO / "results" / "robot"
    name = args.task if args.checkpoint is None or args.checkpoint.name == f"{args.task}_dpt" else \
        f"{args.task} ({args.checkpoint.name})"
    fig, panels = _frontier_panels(plt, [1, 28], lambda b: frontier_join.frontier_points(folder, name, b), name)
    for ax, batch, points in panels:
        for fam, (color, label) in FAMILY_STYLE.items():
            line = sorted((p for p in points if p.family == fam), key=lambda p: p.speedup)
            if line:
                ax.plot([p.speedup for p in line], [p.score for p in line], "-o", color=color, label=label, ms=4)
                for p in line:
                    ax.annotate(p.method.split(":")[1], (p.speedup, p.score), fontsize=7, color=color,
                                xytext=(3, 3), textcoords="offset points")
        for p in points:
            if p.family in FAMILY_STYLE:
                continue
            marker, color = ("s", "black") if p.family == "dense" else ("D", "#e6550d")
            ax.errorbar([p.speedup], [p.score], yerr=[[p.score - p.interval[0]], [p.interval[1] - p.score]],
                        fmt=marker, color=color, ms=5, capsize=2)
            ax.annotate(_point_label(p.method, policy_slug(args.task, args.checkpoint)), (p.speedup, p.score),
                        fontsize=6, xytext=(4, -9), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("policy-call speed-up over dense DDPM-100 (same process)")
        ax.set_ylabel("success rate (test episodes)" if points[0].metric == "success"
                      else "mean best goal coverage (test episodes)")
        if points[0].metric == "success":
            ax.set_ylim(-0.02, 1.05)
        ax.set_title(f"{name}, batch {batch}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    out = DOCS / f"frontier_{policy_slug(args.task, args.checkpoint)}.png"
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def image_frontier(args) -> Path:
    """The digits DiT: FID (bootstrap 95% interval) against speed-up over dense DDIM-50, one panel per
    batch size of results/image/frontier_latency.json; DDIM-k and DPM-Solver++-k as lines, every other
    method a point (filled: the 50-step base; open: a shorter base, ``+ddim:K``)."""
    plt = _plt()
    folder = REPO / "results" / "image"
    latency = folder / "frontier_latency.json"
    batches = sorted({r["batch"] for r in json.loads(latency.read_text())["rows"]}) if latency.exists() else [1]
    fig, panels = _frontier_panels(plt, batches, lambda b: frontier_join.image_frontier_points(folder, latency, b),
                                   "digits DiT")
    for ax, batch, points in panels:
        for families, (color, label) in ((("ddim", "dense"), (FAMILY_STYLE["ddim"][0], "DDIM-k (dense: k = 50)")),
                                         (("dpm",), FAMILY_STYLE["dpm"])):
            line = sorted((p for p in points if p.family in families), key=lambda p: p.speedup)
            if line:
                ax.plot([p.speedup for p in line], [p.score for p in line], "-o", color=color, ms=4, label=label)
            for p in line:
                ax.annotate(str(p.computed_steps), (p.speedup, p.score), fontsize=7, color=color,
                            xytext=(3, 3), textcoords="offset points")
        for p in points:
            if p.family in ("ddim", "dpm", "dense"):
                continue
            shorter = "+ddim:" in p.method or "+dpm:" in p.method
            # the basic-bootstrap interval may lie wholly below the 2000-sample FID: a bar, not error bars
            ax.vlines(p.speedup, *p.interval, color="#e6550d", lw=1)
            ax.plot([p.speedup], [p.score], "D", color="#e6550d", mfc="white" if shorter else "#e6550d", ms=5)
            ax.annotate(_point_label(p.method, "digits"), (p.speedup, p.score), fontsize=6,
                        xytext=(4, -9), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("sampling speed-up over dense DDIM-50 (same process)")
        ax.set_ylabel("FID, 2000 samples (lower is better)")
        ax.set_title(f"digits DiT, batch {batch}")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    out = DOCS / "frontier_digits.png"
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


PAIRED_LABEL = "omni, from scratch, paired noise"  # its L1 is to the dense action on the same noise
CURVE_LABELS = {"forward-timestep-rollout": "omni, from scratch", "prior": "omni, from the searched prior",
                "paired_forward-timestep-rollout": PAIRED_LABEL}
# how the direction panel draws each omni curve (marker and line, so runs stay apart where the lines overlap)
DIRECTION_STYLES = {"omni, from scratch": "o-", "omni, from the searched prior": "^--", PAIRED_LABEL: "s:"}


def training_curves_of(folder: Path, policy: str) -> tuple[dict[str, list[dict]], Optional[float], dict]:
    """The per-epoch history of each reference-recipe pruner of ``policy`` in ``folder``
    (``<policy>_reference_<what>_<rho>.json``; single directions are labelled by their name), the
    validation L1 of the searched steps (epoch 0 of the pruner started from them, ``prior``, whose
    argmax is their schedule; None without it) and the metadata of one of the trainings (an unpaired one
    that records the dense policy's validation L1, ``val_l1_dense``, where one does: a paired run's
    is 0, its target being the dense action on the same noise)."""
    curves, searched, meta = {}, None, {}
    for path in sorted(folder.glob(f"{policy}_reference_*.json")):
        what = path.stem[len(f"{policy}_reference_"):].rsplit("_", 1)[0]
        this = json.loads(path.read_text())["metadata"]
        if ("val_l1_dense" in this and not this.get("paired")) or not meta:
            meta = this
        hist = this["history"]
        if what == "prior" and hist and hist[0]["epoch"] == 0:
            searched = hist[0]["val_l1"]
        curves[CURVE_LABELS.get(what, f"{what} only, from scratch")] = [h for h in hist if h["epoch"] > 0]
    return curves, searched, meta


def training_curves(args) -> Path:
    """Validation action L1 and reuse fraction per epoch of the reference-recipe pruners of one
    policy (test-time argmax decisions on the held-out validation episodes), the searched steps' L1 as
    a dashed line."""
    plt = _plt()
    slug = policy_slug(args.task, args.checkpoint)
    curves, searched, meta = training_curves_of(REPO / "checkpoints" / "pruners", slug)
    if not curves:
        raise SystemExit(f"no reference-recipe pruner of {slug} in checkpoints/pruners/ (recipes/table7.sh)")
    fig, (ax_l1, ax_sp, ax_dir) = plt.subplots(1, 3, figsize=(15.5, 4.0))
    for label, hist in sorted(curves.items()):
        epochs = [h["epoch"] for h in hist]
        paired = label == PAIRED_LABEL
        ax_l1.plot(epochs, [h["val_l1"] for h in hist], "s--" if paired else "o-", ms=3,
                   label=label + (" (L1 on the same noise)" if paired else ""))
        ax_sp.plot(epochs, [h["val_sparsity"] for h in hist], "o-", ms=3, label=label)
        if label.startswith("omni"):  # which direction the reuse decisions take, where a row records it
            for d, color in zip(("forward", "timestep", "rollout"), COLORS[1:]):
                rows = [h for h in hist if f"val_reuse_{d}" in h]
                if not rows:
                    continue
                ax_dir.plot([h["epoch"] for h in rows], [h[f"val_reuse_{d}"] for h in rows],
                            DIRECTION_STYLES.get(label, "d-."), ms=3, color=color,
                            label=f"{d} ({label})")
    if searched is not None:
        ax_l1.axhline(searched, color="k", ls="--", lw=1, label="searched steps (the prior)")
    if "val_l1_dense" in meta:
        ax_l1.axhline(meta["val_l1_dense"], color="grey", ls=":", lw=1, label="dense, another noise draw")
    ax_sp.axhline(meta["sparsity"], color="k", ls=":", lw=1, label=f"target {meta['sparsity']:g}")
    ax_l1.set_yscale("log")
    ax_l1.set_ylabel(f"validation L1 to the dense action ({meta.get('loss_space', 'raw')} actions)")
    ax_sp.set_ylabel("validation reuse fraction (argmax)")
    ax_dir.set_ylabel("share of the validation decisions")
    ax_dir.set_title("omni pruners: reuse by direction", fontsize=9)
    for ax in (ax_l1, ax_sp, ax_dir):
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"{slug}: reference-recipe pruners on {meta.get('n_val_episodes', '?')} held-out episodes",
                 fontsize=9)
    fig.tight_layout()
    out = DOCS / f"{slug}_pruner_training.png"
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figure", choices=["masks", "similarity", "data-efficiency", "frontier", "image-frontier",
                                           "training-curves"])
    ap.add_argument("--task", help="the robot task (every figure but image-frontier)")
    ap.add_argument("--checkpoint", type=Path)
    ap.add_argument("--pruner", type=Path)
    ap.add_argument("--sparsity", type=float, default=None, help="masks: exact-budget mode")
    ap.add_argument("--trajectories", type=Path)
    ap.add_argument("--first-episode", type=int, default=-8, help="first held-out episode (negative: from the end)")
    ap.add_argument("--episodes", type=int, default=4, help="similarity: episodes")
    ap.add_argument("--calls", type=int, default=6, help="masks: rollout iterations shown")
    add_all_episodes_option(ap)
    args = parse_args(ap, argv)
    if args.task is None and args.figure != "image-frontier":
        ap.error(f"{args.figure} needs --task")
    DOCS.mkdir(exist_ok=True)
    fn = {"masks": masks, "similarity": similarity, "data-efficiency": data_efficiency, "frontier": frontier,
          "image-frontier": image_frontier, "training-curves": training_curves}[args.figure]
    print(f"wrote {fn(args)}")


if __name__ == "__main__":
    main()
