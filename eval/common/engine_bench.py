"""Engine benchmarks on random-weight models (speed and MACs only): a DP-sized transformer and DiT-S/2,
tts against dense in one process, interleaved repetitions."""
from __future__ import annotations

import copy
import statistics
import time
from typing import Callable

import torch

import tts
from tts.flops import flop_counter_macs

__all__ = ["bench_dp", "bench_dit", "to_markdown"]


def interleaved(fns: dict[str, Callable[[], torch.Tensor]], reps: int) -> dict[str, list[float]]:
    """Median-friendly timings: every method once per rep, in turn, after one warm-up call each."""
    times = {k: [] for k in fns}
    for fn in fns.values():  # warm-up (and the one-off MAC profiling step of accelerated models)
        fn()
    for _ in range(reps):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return times


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-12))


def per_sample_plan(batch: int, steps: int, nb: int, sparsity: float, seed: int = 0) -> "tts.plans.TensorPlan":
    """Each sample its own random decisions (timestep reuse), exactly ``sparsity`` per sample."""
    g = torch.Generator().manual_seed(seed)
    n_compute = round((1 - sparsity) * steps * nb) - nb  # step 0 is always computed
    dec = torch.full((batch, steps, nb), tts.plans.TIMESTEP, dtype=torch.int8)
    dec[:, 0] = tts.plans.COMPUTE
    for b in range(batch):
        idx = torch.randperm((steps - 1) * nb, generator=g)[:n_compute]
        dec[b, 1:].view(-1)[idx] = tts.plans.COMPUTE
    return tts.plans.from_tensor(dec)


def measure(fns: dict[str, Callable[[], torch.Tensor]], dense: str, acc, reps: int) -> dict:
    """Interleaved timings, FlopCounterMode MACs and output error of ``fns['tts']`` vs ``fns[dense]``;
    removes the accelerator afterwards."""
    times = interleaved(fns, reps)
    err = rel_err(fns["tts"](), fns[dense]())
    macs = {k: flop_counter_macs(fn) for k, fn in fns.items()}
    summary = acc.summary()
    acc.remove()
    return {
        "realised_sparsity": summary.sparsity_of(summary.calls[-1]),
        "latency_s_median": {k: statistics.median(v) for k, v in times.items()},
        "latency_s_all": times,
        "macs": macs,
        "output_rel_error_vs_dense": err,
        "summary": summary,
    }


def bench_dp(batch: int, reps: int, sparsity: float, per_sample: bool = False) -> dict:
    from diffusers import DDPMScheduler

    from tts.adapters.diffusion_policy import DPTransformerConfig, TransformerForDiffusion, sample_actions

    torch.manual_seed(0)
    cfg = DPTransformerConfig(input_dim=7, output_dim=7, horizon=10, n_obs_steps=2, cond_dim=19, n_layer=8,
                              n_head=4, n_emb=256, p_drop_attn=0.3, p_drop_emb=0.0, causal_attn=True, obs_as_cond=True)
    model = TransformerForDiffusion(cfg).eval()
    sched = DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                          prediction_type="epsilon")
    sched.set_timesteps(100)
    cond = torch.randn(batch, 2, 19, generator=torch.Generator().manual_seed(1))
    plan = per_sample_plan(batch, 100, 24, sparsity) if per_sample else tts.plans.uniform(sparsity, "timestep")
    dense_model = copy.deepcopy(model)  # same weights, never accelerated
    acc = tts.accelerate(model, ("timestep",), plan=plan)

    def run(m, fast=True) -> torch.Tensor:
        return sample_actions(m, cond, sched, generator=torch.Generator().manual_seed(2), fast=fast)

    fns = {"dense_stock": lambda: run(dense_model, fast=False), "dense_fast": lambda: run(dense_model),
           "tts": lambda: run(model)}
    m = measure(fns, "dense_fast", acc, reps)
    summary, med = m.pop("summary"), m["latency_s_median"]
    return {
        "model": "DP-T: 8 decoder layers, width 256, 4 heads, horizon 10, obs 2x19, action 7, DDPM-100",
        "batch": batch,
        "plan": ("per-sample random " if per_sample else "") + plan.describe(),
        **m,
        "speedup_vs_dense_fast_loop": med["dense_fast"] / med["tts"],
        "speedup_vs_dense_stock_loop": med["dense_stock"] / med["tts"],
        "macs_ratio_dense_fast_over_tts": m["macs"]["dense_fast"] / m["macs"]["tts"],
        "macs_analytic_decoder_only": dict(zip(("dense", "realised"), summary.macs(summary.calls[-1]))),
    }


def bench_dit(kind: str, reps: int, sparsity: float, steps: int = 50) -> dict:
    from diffusers import DDIMScheduler

    torch.manual_seed(0)
    if kind == "diffusers":
        from diffusers import DiTTransformer2DModel

        model = DiTTransformer2DModel(num_attention_heads=6, attention_head_dim=64, in_channels=4, out_channels=8,
                                      num_layers=12, sample_size=32, patch_size=2, num_embeds_ada_norm=1000)
    else:
        from tts.adapters.dit import DIT_CONFIGS, DiT

        model = DiT(DIT_CONFIGS["DiT-S/2"])
    with torch.no_grad():  # random but non-degenerate weights (DiT zero-inits its adaLN gates)
        for p in model.parameters():
            if p.requires_grad:
                p.normal_(0, 0.02)
    model.eval()
    sched = DDIMScheduler(num_train_timesteps=1000)
    sched.set_timesteps(steps)
    latents0 = torch.randn(1, 4, 32, 32, generator=torch.Generator().manual_seed(1))
    labels = torch.tensor([207, 1000])  # [cond; uncond (null class)]
    plan = tts.plans.uniform(sparsity, "timestep")

    @torch.no_grad()
    def sample(m) -> torch.Tensor:
        x = latents0
        for t in sched.timesteps:
            inp = torch.cat([x, x])
            tt = t.expand(2)
            out = m(inp, tt, labels)
            out = out.sample if hasattr(out, "sample") else out
            eps = out[:, :4]
            cond, uncond = eps.chunk(2)
            x = sched.step(uncond + 1.5 * (cond - uncond), t, x).prev_sample
        return x

    dense_model = copy.deepcopy(model)
    acc = tts.accelerate(model, ("forward", "timestep"), plan=plan)
    fns = {"dense": lambda: sample(dense_model), "tts": lambda: sample(model)}
    m = measure(fns, "dense", acc, reps)
    m.pop("summary")
    med = m["latency_s_median"]
    return {
        "model": f"DiT-S/2 ({kind}): 12 blocks, width 384, 6 heads, 32x32x4 latents, DDIM-{steps}, CFG batch 2",
        "batch": 2,
        "plan": plan.describe(),
        **m,
        "speedup": med["dense"] / med["tts"],
        "macs_ratio": m["macs"]["dense"] / m["macs"]["tts"],
    }


def to_markdown(res: dict) -> str:
    lines = ["# Engine benchmark", "", f"Command: `{res['provenance']['command']}`  ",
             f"Git SHA: `{res['provenance']['git_sha']}`  ", f"Date: {res['provenance']['date']}  ",
             f"Machine: {res['provenance']['machine']['cpu']}, {res['provenance']['machine']['torch_threads']} threads, "
             f"torch {res['provenance']['machine']['torch']}", "",
             "Random weights: speed and MACs only. MACs from FlopCounterMode on one real call.", "",
             "| model | batch | plan | sparsity | dense stock (s) | dense fast (s) | tts (s) | speed-up vs fast | vs stock | MACs ratio |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["diffusion_policy"]:
        m = r["latency_s_median"]
        lines.append(f"| DP-T | {r['batch']} | {r['plan']} | {r['realised_sparsity']:.3f} | {m['dense_stock']:.3f} | "
                     f"{m['dense_fast']:.3f} | {m['tts']:.4f} | **{r['speedup_vs_dense_fast_loop']:.2f}x** | "
                     f"{r['speedup_vs_dense_stock_loop']:.2f}x | {r['macs_ratio_dense_fast_over_tts']:.2f}x |")
    for r in res["dit"]:
        m = r["latency_s_median"]
        lines.append(f"| {r['model'].split(':')[0]} | {r['batch']} | {r['plan']} | {r['realised_sparsity']:.3f} | "
                     f"| {m['dense']:.3f} | {m['tts']:.3f} | **{r['speedup']:.2f}x** | | {r['macs_ratio']:.2f}x |")
    return "\n".join(lines) + "\n"
