"""Baselines in the same engine: BAC-style searched schedules, the learned static router, DDIM-N."""
import itertools

import pytest
import torch

import tts
from test_robot_pipeline import obs_batch, small_policy
from tts.plans import COMPUTE, TIMESTEP
from tts.pruner import PrunerConfig, StaticRouter, build_pruner, load_pruner, save_pruner
from tts.static_search import reuse_errors, search_compute_steps, search_schedule, steps_grid


def _brute_force(e: torch.Tensor, m: int) -> float:
    K = e.shape[0]
    best = float("inf")
    for rest in itertools.combinations(range(1, K), m - 1):
        comp = (0,) + rest
        cost, last = 0.0, 0
        for j in range(K):
            if j in comp:
                last = j
            else:
                cost += float(e[j, last])
        best = min(best, cost)
    return best


@pytest.mark.parametrize("sparsity", [0.5, 0.7, 0.9])
def test_search_schedule_is_optimal_and_meets_the_budget(sparsity):
    K, nb = 9, 3
    g = torch.Generator().manual_seed(1)
    errors = torch.tril(torch.rand(nb, K, K, generator=g, dtype=torch.float64), diagonal=-1)
    grid = search_schedule(errors, sparsity)
    m = max(1, round((1 - sparsity) * K))
    assert grid.shape == (K, nb) and set(grid.unique().tolist()) <= {COMPUTE, TIMESTEP}
    assert ((grid == COMPUTE).sum(0) == m).all() and (grid[0] == COMPUTE).all()
    for b in range(nb):
        cost, last = 0.0, 0
        for j in range(K):
            if grid[j, b] == COMPUTE:
                last = j
            else:
                cost += float(errors[b, j, last])
        assert cost == pytest.approx(_brute_force(errors[b], m))


def test_search_compute_steps_descends_to_the_loss_minimum_and_keeps_step_0():
    target = [0, 3, 4, 11, 17]
    calls = []

    def loss(steps):  # separable, so the first-improvement local search reaches the optimum
        calls.append(list(steps))
        assert steps == sorted(steps) and steps[0] == 0 and len(set(steps)) == 5
        return sum(abs(a - b) for a, b in zip(steps, target))

    best, history = search_compute_steps(loss, 20, 5, max_sweeps=20)
    assert best == target and history[0]["steps"] == [0, 4, 8, 12, 16]
    assert [h["loss"] for h in history] == sorted((h["loss"] for h in history), reverse=True)
    assert history[-1]["loss"] == 0
    calls.clear()
    best, history = search_compute_steps(loss, 20, 5, init=target)  # already optimal: nothing moves
    assert best == target and len(history) == 1 and len(calls) > 1
    with pytest.raises(ValueError, match="including 0"):
        search_compute_steps(loss, 20, 3, init=[1, 5, 9])
    with pytest.raises(ValueError, match="computes"):
        search_compute_steps(loss, 20, 0)
    grid = steps_grid(target, 20, 4)
    assert grid.shape == (20, 4) and (grid[target] == COMPUTE).all() and int((grid == COMPUTE).sum()) == 20


def test_reuse_errors_measure_what_timestep_reuse_would_change():
    pol = small_policy(num_steps=5)
    obs = obs_batch(2)
    E = reuse_errors(pol, lambda: pol.predict_action(obs, torch.Generator().manual_seed(0)))
    assert E.shape == (6, 5, 5)
    assert torch.equal(E, torch.tril(E, diagonal=-1)) and (E[:, 1:, 0] > 0).all()
    assert not any(k in pol.__dict__ for k in ("predict_action", "reset"))  # recorder removed
    # a schedule that reuses step 0 for every later step of branch b changes the output exactly by E
    outs = {}

    def grab(m, a, o):
        outs.setdefault("x", []).append(o)

    h = pol.model.decoder.layers[0].self_attn.register_forward_hook(grab)  # the untouched policy
    pol.predict_action(obs, torch.Generator().manual_seed(0))
    h.remove()
    x = torch.stack([o[0] for o in outs["x"]])  # [K, B, H, D] self-attention outputs of layer 0
    rel = (x[3] - x[0]).abs().sum((1, 2)) / x[3].abs().sum((1, 2))
    assert float(E[0, 3, 0]) == pytest.approx(float(rel.mean()), rel=1e-4)
    with pytest.raises(ValueError, match="no sampling call"):
        reuse_errors(pol, lambda: None)


def test_static_router_same_decisions_for_every_observation(tmp_path):
    pol = small_policy(num_steps=6)
    router = build_pruner(PrunerConfig(memory_dim=32, num_branches=6, directions=("timestep",), kind="static", steps=6))
    assert isinstance(router, StaticRouter) and router.macs(6, 3) == 0.0
    with torch.no_grad():
        router.logits[2:, :, 1] = 5.0  # reuse from step 2 on
    save_pruner(router, tmp_path / "r")
    back = load_pruner(tmp_path / "r")
    assert isinstance(back, StaticRouter) and torch.equal(back.logits, router.logits)
    with tts.accelerate(pol, ("timestep",), pruner=back) as acc:
        pol.predict_action(obs_batch(2, 0))
        pol.predict_action(obs_batch(2, 1))
        d = acc.summary().calls[-1].decisions()  # [K, B, nb]
    assert (d[:2] == COMPUTE).all() and (d[2:] == TIMESTEP).all()
    pol.set_sampler(steps=4)
    with tts.accelerate(pol, ("timestep",), pruner=back):
        with pytest.raises(ValueError, match="trained for 6 steps"):
            pol.predict_action(obs_batch(2))
    with pytest.raises(ValueError, match="steps="):
        PrunerConfig(memory_dim=8, num_branches=3, kind="static")


def test_set_sampler_ddim_fewer_steps():
    pol = small_policy(num_steps=10)
    with tts.accelerate(pol) as acc:
        pol.set_sampler("ddim", 4)
        out = pol.predict_action(obs_batch(2), torch.Generator().manual_seed(0))
        assert len(acc.summary().calls[-1].steps) == 4
    assert out["action"].shape == (2, 8, 7) and torch.isfinite(out["action"]).all()
    assert pol.cfg.scheduler == "ddim" and type(pol._fast).__name__ == "FastDDIM"
    with pytest.raises(ValueError, match="steps must be"):
        pol.set_sampler(steps=0)
