"""Learned pruner: gate scheduler, lockstep trajectory batching, pruner network, engine integration."""
import numpy as np
import pytest
import torch

import tts
from test_robot_pipeline import obs_batch, small_policy
from tts.gates import argmax_codes, budget_codes, reuse_fraction, ste_gates
from tts.plans import COMPUTE, FORWARD, ROLLOUT, TIMESTEP
from tts.pruner import Pruner, PrunerConfig, PrunerPlan, dropout_fast, load_pruner, pruner_loss, save_pruner
from tts.trajectories import episode_groups, lockstep_frames, split_episodes


# ---------------------------------------------------------------- gate scheduler
def test_ste_gates_forward_one_hot_step0_forced_and_identity_gradient():
    logits = torch.randn(3, 5, 6, 4, requires_grad=True)
    hard, p = ste_gates(logits)
    assert torch.equal(hard.detach().sum(-1), torch.ones(3, 5, 6))
    assert set(hard.detach().unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(hard.detach()[:, 0, :, 0], torch.ones(3, 6))  # step 0: compute
    torch.testing.assert_close(hard.detach()[:, 1:], torch.nn.functional.one_hot(logits[:, 1:].argmax(-1), 4).float())
    # straight-through: d hard / d p = I, so d(sum w*hard)/d logits = d(sum w*p)/d logits
    w = torch.randn_like(hard)
    (g_hard,) = torch.autograd.grad((w * hard).sum(), logits, retain_graph=True)
    (g_soft,) = torch.autograd.grad((w * p).sum(), logits)
    torch.testing.assert_close(g_hard, g_soft)
    assert torch.equal(g_hard[:, 0], torch.zeros_like(g_hard[:, 0]))  # no gradient into step 0
    assert g_hard[:, 1:].abs().sum() > 0


def test_reuse_fraction_counts_non_compute():
    codes = torch.tensor([[[0, 1], [2, 0]], [[0, 0], [0, 0]]])  # [B=2, K=2, nb=2] option indices
    gates = torch.nn.functional.one_hot(codes, 3).float()
    torch.testing.assert_close(reuse_fraction(gates), torch.tensor([0.5, 0.0]))


def test_argmax_codes_maps_options_to_direction_codes_and_forces_step0():
    logits = torch.zeros(2, 3, 4, 2)
    logits[..., 1] = 1.0  # option 1 (the only direction) wins everywhere
    out = argmax_codes(logits, [COMPUTE, TIMESTEP])
    assert out.dtype == torch.int8
    assert (out[:, 0] == COMPUTE).all() and (out[:, 1:] == TIMESTEP).all()


@pytest.mark.parametrize("sparsity", [0.0, 0.5, 0.9, 0.95])
def test_budget_codes_exact_count_ranked_by_compute_probability(sparsity):
    B, K, nb = 3, 10, 6
    logits = torch.randn(B, K, nb, 4, generator=torch.Generator().manual_seed(0))
    codes = [COMPUTE, FORWARD, TIMESTEP, ROLLOUT]
    out = budget_codes(logits, codes, sparsity)
    keep = max(nb, round((1 - sparsity) * K * nb))
    assert ((out == COMPUTE).sum((1, 2)) == keep).all()
    assert (out[:, 0] == COMPUTE).all()
    p = logits.softmax(-1)[..., 0]
    for s in range(B):  # every computed (k>0) branch is at least as likely to compute as every reused one
        comp = p[s, 1:][out[s, 1:] == COMPUTE]
        reuse = p[s, 1:][out[s, 1:] != COMPUTE]
        if len(comp) and len(reuse):
            assert comp.min() >= reuse.max()
    # reused decisions take their best reuse direction
    best = torch.tensor(codes)[logits[..., 1:].argmax(-1) + 1].to(torch.int8)
    mask = out != COMPUTE
    assert torch.equal(out[mask], best[mask])


def test_budget_codes_rejects_bad_sparsity_and_compute_only_head():
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        budget_codes(torch.randn(1, 4, 3, 2), [0, 2], 1.0)
    with pytest.raises(ValueError, match="reuse direction"):
        budget_codes(torch.randn(1, 4, 3, 1), [0], 0.5)


# ---------------------------------------------------------------- lockstep trajectory batching
def _episode(n, tag):
    return {"obs": np.full((n, 2, 3), tag, np.float32), "action_pred": np.arange(n, dtype=np.float32)[:, None, None]
            * np.ones((n, 4, 2), np.float32), "noise_seed": np.arange(n) + 100 * tag}


def test_lockstep_frames_pad_short_episodes_with_zero_weight():
    group = [_episode(3, 1), _episode(5, 2)]
    frames = list(lockstep_frames(group, ("obs", "action_pred", "noise_seed")))
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [f.first for f in frames] == [True, False, False, False, False]
    assert frames[2].weight.tolist() == [1.0, 1.0] and frames[3].weight.tolist() == [0.0, 1.0]
    assert frames[4].data["obs"].shape == (2, 2, 3)
    # the short episode repeats its last frame; the long one advances
    assert frames[4].data["noise_seed"].tolist() == [102, 204]
    assert frames[4].data["action_pred"][:, 0, 0].tolist() == [2.0, 4.0]


def test_lockstep_frames_rejects_ragged_episode():
    bad = _episode(3, 1)
    bad["noise_seed"] = bad["noise_seed"][:2]
    with pytest.raises(ValueError, match="differ in length"):
        list(lockstep_frames([bad], ("obs", "noise_seed")))


def test_episode_groups_and_split():
    eps = [_episode(2, i) for i in range(7)]
    groups = episode_groups(eps, 3, np.random.default_rng(0))
    assert [len(g) for g in groups] == [3, 3, 1]
    assert sorted(int(e["obs"][0, 0, 0]) for g in groups for e in g) == list(range(7))
    assert episode_groups(eps, 3, None)[0][0] is eps[0]
    train, val = split_episodes(eps, 4, 2)
    assert len(train) == 4 and len(val) == 2 and val[0] is eps[4]
    with pytest.raises(ValueError, match="only 7 usable"):
        split_episodes(eps, 6, 2)
    with pytest.raises(ValueError, match="at least one"):
        split_episodes(eps, 0, 2)


# ---------------------------------------------------------------- pruner network
def _pruner(directions=("forward", "timestep", "rollout"), nb=6, dim=32, dropout=0.0, seed=0):
    torch.manual_seed(seed)
    return Pruner(PrunerConfig(memory_dim=dim, num_branches=nb, directions=directions, hidden=16, heads=2, ffn=32,
                               dropout=dropout))


def test_pruner_shapes_query_cache_and_errors():
    pr = _pruner()
    mem = torch.randn(2, 7, 3, 32)
    train_out = pr.train()(mem)
    assert train_out.shape == (2, 7, 6, 4)
    pr.eval()
    with torch.no_grad():
        first = pr(mem)
        assert pr._query_cache is not None  # input-independent query self-attention cached
        torch.testing.assert_close(pr(mem), first)
    torch.testing.assert_close(first, train_out.detach())  # dropout 0: same function either way
    assert _pruner(("timestep",))(mem).shape == (2, 7, 6, 2)
    with pytest.raises(ValueError, match="memory"):
        pr(torch.randn(2, 7, 3, 16))
    with pytest.raises(ValueError, match="unknown direction"):
        PrunerConfig(memory_dim=8, num_branches=3, directions=("sideways",))
    with pytest.raises(ValueError, match="at least one"):
        PrunerConfig(memory_dim=8, num_branches=3, directions=())
    with pytest.raises(ValueError, match="one value per option"):
        PrunerConfig(memory_dim=8, num_branches=3, head_bias=[2.0, 0.0])
    biased = Pruner(PrunerConfig(memory_dim=32, num_branches=6, hidden=16, heads=2, ffn=32, head_bias=[0, 0, 5, 0]))
    with torch.no_grad():
        assert (argmax_codes(biased.eval()(mem), biased.config.codes)[:, 1:] == TIMESTEP).all()


def test_shared_query_cross_attention_equals_the_module_on_expanded_queries():
    """The decoder layer projects the shared queries once and applies Wo to the memory's values: the
    same output and gradients as nn.MultiheadAttention run on the queries copied per sample."""
    torch.manual_seed(0)
    pr = Pruner(PrunerConfig(memory_dim=12, num_branches=6, hidden=32, heads=4, ffn=64, dropout=0.0))
    layer = pr.layer
    q = torch.randn(6, 32, requires_grad=True)
    mem = torch.randn(5, 3, 32, requires_grad=True)
    fast = layer._cross(q, mem)
    ref = layer.cross_attn(layer.norm2(q).expand(5, -1, -1), mem, mem, need_weights=False)[0]
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)
    w = torch.randn_like(ref)
    grads_fast = torch.autograd.grad((w * fast).sum(), [q, mem, layer.cross_attn.in_proj_weight])
    grads_ref = torch.autograd.grad((w * ref).sum(), [q, mem, layer.cross_attn.in_proj_weight])
    for a, b in zip(grads_fast, grads_ref):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_fast_dropout_drops_p_keeps_the_mean_and_is_identity_in_eval():
    torch.manual_seed(0)
    x = torch.ones(1000, 1001)  # an odd element count: the mask is cut from whole int64 draws
    y = dropout_fast(x, 0.1, True)
    dropped = float((y == 0).float().mean())
    assert dropped == pytest.approx(0.1, abs=0.003)
    assert float(y.mean()) == pytest.approx(1.0, abs=0.01)
    assert y.unique().tolist() == pytest.approx([0.0, 1 / 0.9])
    assert dropout_fast(x, 0.1, False) is x and dropout_fast(x, 0.0, True) is x
    g = torch.ones(3, 5, requires_grad=True)
    out = dropout_fast(g, 0.5, True)
    out.sum().backward()
    torch.testing.assert_close(g.grad, out.detach())  # gradient passes exactly where the value did


def test_bfloat16_autocast_training_gates_match_float32_and_reach_the_pruner():
    """PrunerPlan(autocast=bfloat16): mixed-precision training; the gates stay float32 and, with clear
    margins between the options, take the same decisions as in float32."""
    pol = small_policy(num_steps=6)
    pr = _pruner(nb=6, dim=32).train()  # dropout 0: the two runs see the same network
    with torch.no_grad():
        pr.head.bias.copy_(torch.tensor([0.0, 4.0, 0.0, 0.0]))  # forward reuse wins by a wide margin
    obs = [obs_batch(2, i) for i in range(2)]
    gates = {}
    for name, dtype in (("float32", None), ("bfloat16", torch.bfloat16)):
        plan = PrunerPlan(pr, mode="ste", autocast=dtype)
        with tts.accelerate(pol, plan=plan):
            for o in obs:
                pred = pol.predict_action(o, [torch.Generator().manual_seed(1)] * 2, enable_grad=True)["action_pred"]
        gates[name] = plan.gates
        pr.zero_grad()
        pruner_loss(pred, pred.detach() + 0.1, plan.gates, 0.5)["loss"].backward()
        assert sum(float(p.grad.abs().sum()) for p in pr.parameters() if p.grad is not None) > 0
    assert gates["bfloat16"].dtype == torch.float32
    torch.testing.assert_close(gates["bfloat16"].detach(), gates["float32"].detach())
    with pytest.raises(ValueError, match="autocast applies to training"):
        PrunerPlan(pr, mode="argmax", autocast=torch.bfloat16)
    from tts.training import PrunerTrainingConfig

    with pytest.raises(ValueError, match="precision must be one of"):
        PrunerTrainingConfig(out="x", precision="float16")


def test_pruner_macs_counted_and_small_next_to_the_policy():
    pol = small_policy(num_steps=10)
    pr = _pruner(nb=6, dim=32)
    K = pol.cfg.num_inference_steps
    m = pr.macs(K, 3)
    h, q, tc = 16, 6, 3
    # analytic lower bound per step: memory projection, keys, values and their output projection
    # (the shared queries are projected once per call), FFN, head
    per_step = tc * 32 * h + tc * h * h * 3 + q * h * 32 * 2 + q * h * 4
    assert per_step * K <= m <= 2 * per_step * K
    acc = tts.accelerate(pol, pruner=pr)
    pol.predict_action(obs_batch(1))
    dense_macs, _ = acc.summary().macs(acc.summary().calls[-1])
    acc.remove()
    assert m < 0.2 * dense_macs


def test_pruner_save_load_round_trip_and_mismatch(tmp_path):
    pr = _pruner(("timestep", "rollout"))
    save_pruner(pr, tmp_path / "p", metadata={"note": "x"})
    back = load_pruner(tmp_path / "p")
    assert back.config.directions == ("timestep", "rollout") and back.metadata == {"note": "x"}
    mem = torch.randn(1, 4, 3, 32)
    with torch.no_grad():
        torch.testing.assert_close(back(mem), pr.eval()(mem))
    pol = small_policy()  # 2 layers x 3 branches = 6
    with pytest.raises(ValueError, match="does not belong"):
        tts.accelerate(pol, pruner=_pruner(nb=9))
    with pytest.raises(ValueError, match="not in directions"):
        tts.accelerate(pol, ("timestep",), pruner=pr)
    with pytest.raises(ValueError, match="either plan= or pruner="):
        tts.accelerate(pol, pruner=pr, plan=tts.plans.dense())
    with pytest.raises(FileNotFoundError, match="pruner config"):
        load_pruner(tmp_path / "missing")


def test_accelerate_moves_the_pruner_to_the_models_device(monkeypatch):
    """The pruner reads the model's condition memory, so it must live where the model does (a GPU
    policy with a pruner loaded on the CPU would fail at its first call)."""
    pol, pr = small_policy(), _pruner()
    moved = []
    monkeypatch.setattr(pr, "to", lambda *a, **k: moved.append(a) or pr)
    acc = tts.accelerate(pol, pruner=pr)
    acc.remove()
    assert moved == [(next(pol.parameters()).device,)]


# ---------------------------------------------------------------- engine integration
def test_pruner_decisions_follow_its_argmax_on_the_condition_memory():
    pol = small_policy(num_steps=10)
    pr = _pruner(seed=3)
    with torch.no_grad():
        pr.head.bias.copy_(torch.tensor([0.0, 0.5, 0.5, 0.5]))  # mix of decisions
    acc = tts.accelerate(pol, pruner=pr, parallel=False)
    obs = obs_batch(2)
    pol.predict_action(obs)  # first call of the episode: dense
    pol.predict_action(obs)
    s = acc.summary()
    assert s.calls[0].dense and not s.calls[1].dense
    cond = pol.obs_normalizer.normalize(pol.obs_vector(obs))[:, -2:]
    with torch.no_grad():
        logits = pr(pol.model.condition_memory(pol._fast.timesteps, cond))
    expect = argmax_codes(logits, pr.config.codes)  # [B, K, nb]
    assert torch.equal(s.calls[1].decisions(), expect.transpose(0, 1))
    assert 0 < s.sparsity_of(s.calls[1]) < 1
    t = s.calls[1].timing
    assert {"encoder", "pruner", "wait", "decoder", "total"} <= set(t)
    assert s.calls[1].pruner_macs == pytest.approx(pr.macs(10, 3) * 2)
    assert s.calls[0].pruner_macs == 0  # dense first call: the pruner's decisions are not needed
    acc.remove()


def test_parallel_pruner_gives_the_same_actions_as_sequential():
    pol = small_policy(num_steps=10)
    pr = _pruner(seed=4)
    with torch.no_grad():
        pr.head.bias.copy_(torch.tensor([0.0, 0.5, 0.5, 0.5]))
    outs = []
    for parallel in (False, True):
        with tts.accelerate(pol, pruner=pr, parallel=parallel):
            for i in range(3):
                out = pol.predict_action(obs_batch(3, i), torch.Generator().manual_seed(i))["action_pred"]
        outs.append(out)
    assert torch.equal(outs[0], outs[1])


def test_budget_mode_realises_the_requested_sparsity():
    pol = small_policy(num_steps=10)
    pr = _pruner(seed=5)
    for rho in (0.5, 0.8):
        with tts.accelerate(pol, pruner=pr, sparsity=rho) as acc:
            pol.predict_action(obs_batch(2))
            pol.predict_action(obs_batch(2, 1))
            assert acc.summary().sparsity_of(acc.summary().calls[-1]) == pytest.approx(rho)
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        tts.accelerate(pol, pruner=pr, sparsity=1.2)


def test_ste_training_path_equals_hard_path_and_trains_only_the_pruner():
    """Mixed straight-through path (every branch computed, outputs mixed with one-hot gates) gives
    the same actions as real skipping with the same decisions; gradients reach the pruner only."""
    pol = small_policy(num_steps=10).requires_grad_(False)
    pr = _pruner(seed=6)
    with torch.no_grad():
        pr.head.bias.copy_(torch.tensor([0.0, 0.5, 0.5, 0.5]))
    obs = [obs_batch(3, i) for i in range(3)]
    gen = lambda i: [torch.Generator().manual_seed(10 * i + j) for j in range(3)]  # noqa: E731
    with tts.accelerate(pol, pruner=pr, parallel=False):
        hard = [pol.predict_action(o, gen(i))["action_pred"] for i, o in enumerate(obs)]
    plan = PrunerPlan(pr, mode="ste")
    with tts.accelerate(pol, plan=plan) as acc:
        for i, o in enumerate(obs):
            soft = pol.predict_action(o, gen(i), enable_grad=True)["action_pred"]
            torch.testing.assert_close(soft.detach(), hard[i], rtol=1e-4, atol=1e-5)
        s = acc.summary()
    assert s.sparsity_of(s.calls[-1]) > 0
    loss = pruner_loss(soft, hard[-1] + 0.1, plan.gates, 0.9)
    loss["loss"].backward()
    assert all(p.grad is None for p in pol.parameters())
    grads = [p.grad for p in pr.parameters() if p.grad is not None]
    assert grads and sum(float(g.abs().sum()) for g in grads) > 0


def test_pruner_loss_weights_padded_samples_out():
    pred, target = torch.zeros(2, 4, 3), torch.ones(2, 4, 3)
    target[1] = 5.0
    gates = torch.nn.functional.one_hot(torch.zeros(2, 3, 4, dtype=torch.long), 4).float()
    out = pruner_loss(pred, target, gates, 0.5, lam=2.0, weight=torch.tensor([1.0, 0.0]))
    assert float(out["l1"]) == pytest.approx(1.0)
    assert float(out["sparsity_loss"]) == pytest.approx(0.5)
    assert float(out["loss"]) == pytest.approx(2.0)


# ---------------------------------------------------------------- end to end on a toy policy
def _toy_policy_and_trajectories(tmp_path, lengths: list[int]):
    """A small 6-step policy saved at tmp_path/policy and one recorded successful episode per entry
    of ``lengths`` (that many calls, dense action_pred with noise seed 100 * episode + call) at
    tmp_path/traj.pt, as eval/collect_trajectories.py writes them."""
    from tts.adapters.dp_policy import save_policy
    from tts.trajectories import obs_dict, save_trajectories

    pol = small_policy(num_steps=6)
    save_policy(pol, tmp_path / "policy", dtype=torch.float32)
    episodes = []
    for e, n in enumerate(lengths):
        obs = np.stack([np.concatenate([obs_batch(1, 10 * e + r)[k][0] for k in obs_batch(1)], -1) for r in range(n)])
        preds = np.stack([pol.predict_action(obs_dict(pol, torch.as_tensor(o[None])),
                                             torch.Generator().manual_seed(100 * e + r))["action_pred"][0].numpy()
                          for r, o in enumerate(obs)])
        episodes.append({"seed": e, "success": True, "obs": obs, "action_pred": preds, "action": preds[:, 1:9],
                         "noise_seed": 100 * e + np.arange(n)})
    save_trajectories(tmp_path / "traj.pt", episodes, {"command": "test"})
    return pol


# the metadata of an eval/train_pruner.py checkpoint: provenance, every command-line option, the data
TRAIN_PRUNER_METADATA = {
    "command", "git_sha", "date", "machine", "seeds", "trajectories", "checkpoint", "out", "directions", "sparsity",
    "lam", "epochs", "batch", "lr", "weight_decay", "hidden", "forecast", "prior", "prior_reuse", "train_budget",
    "prior_margin", "tie_branches", "step_query", "val_mode", "seed", "run_dir", "resume", "n_train", "n_val", "paired",
    "loss_space", "static", "head_bias", "init_schedule", "threads", "n_train_episodes", "n_val_episodes", "policy",
    "trajectory_collection", "best_epoch", "history", "train_seconds", "pruner_macs_per_call", "heads", "ffn",
    "lr_schedule", "clip_grad", "recipe", "all_episodes", "precision", "precision_log", "device", "val_l1_dense"}


def test_train_then_eval_end_to_end_on_a_toy_policy(tmp_path):
    """eval/train_pruner.py on trajectories of a tiny policy: the checkpoint is written, the pruner
    learns to reuse (its sparsity moves from ~0 toward the target) and serves test-time decisions."""
    import train_pruner

    pol = _toy_policy_and_trajectories(tmp_path, [3 + e % 2 for e in range(6)])
    out = tmp_path / "pruner_0.6"  # a dot in the name is not a suffix
    args = ["--trajectories", str(tmp_path / "traj.pt"), "--checkpoint", str(tmp_path / "policy"), "--out", str(out),
            "--sparsity", "0.6", "--epochs", "3", "--batch", "2", "--n-train", "4", "--n-val", "2", "--lr", "0.02",
            "--hidden", "16", "--paired", "--run-dir", str(tmp_path / "run")]
    train_pruner.main(args)
    pr = load_pruner(out)
    hist = pr.metadata["history"]
    assert len(hist) == 3 and pr.metadata["n_train_episodes"] == 4
    assert pr.metadata["best_epoch"]["val_sparsity"] > 0.2  # started near 0 (head biased to compute)
    assert pr.metadata["pruner_macs_per_call"] > 0
    # the command line records the metadata fields the committed checkpoints it trained have
    assert set(pr.metadata) == TRAIN_PRUNER_METADATA
    assert pr.metadata["directions"] == "forward,timestep,rollout" and pr.metadata["trajectory_collection"] == "test"
    with tts.accelerate(pol, pruner=pr) as acc:
        pol.predict_action(obs_batch(2))
        pol.predict_action(obs_batch(2, 1))
        assert acc.summary().sparsity_of(acc.summary().calls[-1]) > 0
    # resuming a finished run trains no further epoch and keeps the history
    train_pruner.main(args + ["--resume"])
    assert len(load_pruner(out).metadata["history"]) == 3
    with pytest.raises(ValueError, match="other loss_space"):  # so would the scale of the L1 term
        train_pruner.main(args + ["--resume", "--loss-space", "normalized"])
    assert pr.metadata["device"] == "cpu"
    if not torch.cuda.is_available():  # a GPU that is not there is an error, not a silent CPU run
        with pytest.raises(SystemExit, match="no such CUDA device"):
            train_pruner.main(args + ["--resume", "--device", "cuda"])
    import robot  # the eval report reads the pruner's training metadata from the same pair of files
    from common.methods import parse_method

    meta = robot._pruner_metadata(parse_method(f"pruner:{out}"))
    assert meta["n_train_episodes"] == 4 and meta["epochs_done"] == 3 and len(meta["weights_sha256"]) == 64
    # --resume continues a result only with the weights it was run with: a training that went on since
    # (other weights under the same name) runs again; an older result without the digest compares best epochs
    assert robot._same_pruner(meta, dict(meta)) and robot._same_pruner(None, None)
    assert not robot._same_pruner(meta, dict(meta, weights_sha256="0" * 64))
    assert not robot._same_pruner(None, meta)
    old = {k: v for k, v in meta.items() if k != "weights_sha256"}
    assert robot._same_pruner(old, meta) and not robot._same_pruner(dict(old, best_epoch={"epoch": 9}), meta)
    import pruner_agreement

    with pytest.raises(ValueError, match="without --prior"):
        pruner_agreement.main(["--task", "lift", "--checkpoint", str(tmp_path / "policy"), "--pruner", str(out),
                               "--trajectories", str(tmp_path / "traj.pt")])


def test_train_budget_makes_the_training_forward_take_exactly_the_budget(tmp_path):
    """--train-budget: the straight-through forward is the exact-budget decision, so a static router
    that starts at "compute everything" trains at the target sparsity from its first step (without
    the flag its argmax forward computed everything and the option was silently ignored)."""
    import train_pruner

    _toy_policy_and_trajectories(tmp_path, [3] * 4)
    base = ["--trajectories", str(tmp_path / "traj.pt"), "--checkpoint", str(tmp_path / "policy"), "--sparsity", "0.5",
            "--epochs", "1", "--batch", "2", "--n-train", "2", "--n-val", "2", "--lr", "1e-4", "--paired", "--static",
            "--directions", "timestep", "--val-mode", "budget"]
    train_pruner.main(base + ["--out", str(tmp_path / "plain")])
    train_pruner.main(base + ["--out", str(tmp_path / "budget"), "--train-budget"])
    plain = load_pruner(tmp_path / "plain").metadata["history"][-1]
    budget = load_pruner(tmp_path / "budget").metadata["history"][-1]
    assert plain["train_sparsity"] == pytest.approx(0.0) and plain["train_l1"] == pytest.approx(0.0, abs=1e-6)
    assert budget["train_sparsity"] == pytest.approx(0.5, abs=0.1) and budget["train_l1"] > 0


def test_pruner_agreement_counts_calls_and_decisions_equal_to_the_prior():
    from types import SimpleNamespace

    import pruner_agreement

    prior = torch.tensor([[COMPUTE, COMPUTE], [TIMESTEP, TIMESTEP], [TIMESTEP, COMPUTE]], dtype=torch.int8)
    same = prior[:, None, :].expand(3, 2, 2).clone()  # [K, B, nb], both samples as the prior
    moved = same.clone()
    moved[1, 1, 0] = COMPUTE  # sample 1 computes one more branch at step 1
    calls = [SimpleNamespace(dense=True, decisions=lambda: torch.zeros(3, 2, 2, dtype=torch.int8)),
             SimpleNamespace(dense=False, decisions=lambda: same),
             SimpleNamespace(dense=False, decisions=lambda: moved)]
    res = pruner_agreement.agreement(calls, prior)
    assert (res["calls"], res["calls_identical"]) == (4, 3)  # the dense call is left out
    assert (res["decisions"], res["decisions_identical"]) == (24, 23)
    with pytest.raises(ValueError, match="do not fit"):
        pruner_agreement.agreement(calls[1:], prior[:2])


def test_distill_schedule_warm_start_reproduces_a_static_grid():
    from tts.pruner import distill_schedule

    pr = _pruner(("timestep", "rollout"))
    K, nb = 7, 6
    grid = torch.full((K, nb), TIMESTEP, dtype=torch.int8)
    grid[0] = COMPUTE
    grid[3, ::2] = COMPUTE
    grid[5, 1] = ROLLOUT
    step_code = torch.randn(1, K, 1, 32)  # the memory carries the step identity (DP-T: its time token)
    memory = step_code + 0.1 * torch.randn(20, K, 3, 32)
    agree = distill_schedule(pr, memory, grid, steps=150, lr=1e-2)
    assert agree == 1.0
    with torch.no_grad():
        codes = argmax_codes(pr.eval()(step_code + 0.1 * torch.randn(2, K, 3, 32)), pr.config.codes)
    assert torch.equal(codes[0], grid) and torch.equal(codes[1], grid)
    with pytest.raises(ValueError, match="no option"):
        distill_schedule(_pruner(("timestep",)), memory, grid)


def test_prior_schedule_is_the_starting_decision_and_errors():
    K, nb = 6, 6
    pr = Pruner(PrunerConfig(memory_dim=32, num_branches=nb, hidden=16, heads=2, ffn=32, dropout=0.0,
                             prior=True, steps=K))
    grid = torch.full((K, nb), TIMESTEP, dtype=torch.int8)
    grid[0] = COMPUTE
    grid[4, 2] = COMPUTE
    grid[2, 1] = ROLLOUT
    pr.set_prior(grid)
    with torch.no_grad():
        logits = pr.eval()(torch.randn(3, K, 3, 32))
    assert torch.equal(argmax_codes(logits, pr.config.codes)[1], grid)  # zero-initialised head: the prior decides
    forced = budget_codes(logits, pr.config.codes, 1 - 6 / (K * nb))  # one compute fewer than the grid has (7)
    assert int((forced[0] == COMPUTE).sum()) == 6 and forced[0, 4, 2] == TIMESTEP  # falls back to timestep
    with pytest.raises(ValueError, match="without a prior"):
        _pruner().set_prior(grid)
    with pytest.raises(ValueError, match="shape"):
        pr.set_prior(grid[:3])
    with pytest.raises(ValueError, match="steps="):
        PrunerConfig(memory_dim=8, num_branches=3, prior=True)


def test_a_call_that_skips_the_condition_encoder_gets_no_stale_decisions():
    pol = small_policy(num_steps=4)
    model = pol.model
    pr = _pruner(("forward", "timestep"), seed=7)
    ts = pol._fast.timesteps
    cond = torch.randn(2, 2, 19)
    x = torch.randn(2, 10, 7)
    with tts.accelerate(model, ("forward", "timestep"), pruner=pr), torch.no_grad():
        memory = model.condition_memory(ts, cond)  # observed: decisions for this call
        for k, t in enumerate(ts):
            model(x, t, cond, memory=memory[:, k])
        with pytest.raises(RuntimeError, match="no condition memory"):
            for t in ts:  # DP's stock loop: the encoder runs inside forward, the pruner never sees it
                model(x, t, cond)


def test_checkpoint_names_with_dots_keep_them(tmp_path):
    from tts.pruner import PrunerConfig, build_pruner, load_pruner, save_pruner

    p = build_pruner(PrunerConfig(memory_dim=8, num_branches=4, directions=("timestep",), hidden=8, steps=3))
    save_pruner(p, tmp_path / "tts_0.8")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["tts_0.8.json", "tts_0.8.safetensors"]
    q = load_pruner(tmp_path / "tts_0.8")
    for (k, a), b in zip(p.state_dict().items(), q.state_dict().values()):
        assert torch.equal(a, b), k
    save_pruner(p, tmp_path / "tts_0.9")
    assert load_pruner(tmp_path / "tts_0.9.json").config == p.config


def test_budget_ste_gates_fix_the_sparsity_and_pass_gradients():
    from tts.gates import budget_codes, budget_ste_gates

    torch.manual_seed(0)
    logits = torch.randn(3, 6, 4, 3, requires_grad=True)
    hard, p = budget_ste_gates(logits, 0.75)
    computed = hard.detach()[..., 0]
    assert computed[:, 0].eq(1).all()  # step 0
    assert computed.sum(dim=(1, 2)).eq(round(0.25 * 6 * 4)).all()  # exactly the budget per sample
    # the forward equals the test-time exact-budget decision
    codes = budget_codes(logits.detach(), [0, 1, 2], 0.75)
    assert torch.equal(hard.detach().argmax(-1).to(torch.int8), codes)
    (hard[..., 0] * torch.arange(6.0)[None, :, None]).sum().backward()
    assert logits.grad is not None and logits.grad[:, 1:].abs().sum() > 0


def test_tied_pruner_decides_whole_steps_per_sample():
    from tts.gates import budget_ste_gates

    K, nb = 8, 6
    torch.manual_seed(0)
    pr = Pruner(PrunerConfig(memory_dim=32, num_branches=nb, hidden=16, heads=2, ffn=32, dropout=0.0,
                             tie_branches=True))
    with torch.no_grad():
        pr.head.weight.normal_()  # decisions that depend on the memory
    memory = torch.randn(3, K, 2, 32)
    logits = pr.eval()(memory)
    assert torch.equal(logits, logits[:, :, :1].expand_as(logits))  # one decision per (sample, step)
    codes = budget_codes(logits.detach(), pr.config.codes, 0.75)  # 2 of 8 steps computed
    per_step = (codes == COMPUTE).all(2)
    assert torch.equal(per_step, (codes == COMPUTE).any(2)) and per_step.sum(1).eq(2).all() and per_step[:, 0].all()
    assert not torch.equal(per_step[0], per_step[1]) or not torch.equal(per_step[1], per_step[2])  # per sample
    # a budget that is not a whole number of steps: whole_steps rounds it in steps, never splits one
    split = budget_codes(logits.detach(), pr.config.codes, 0.7)  # 14 of 48 branches: 2 steps + 2
    assert not torch.equal((split == COMPUTE).all(2), (split == COMPUTE).any(2))
    whole = budget_codes(logits.detach(), pr.config.codes, 0.7, whole_steps=True)  # round(0.3 * 8) = 2 steps
    assert torch.equal((whole == COMPUTE).all(2), per_step)
    hard, _ = budget_ste_gates(pr.train()(memory), 0.7, whole_steps=True)
    assert torch.equal(hard[..., 0].amin(2), hard[..., 0].amax(2)) and hard[..., 0].amax(2).sum(1).eq(2).all()
    (hard[..., 0] * torch.arange(float(K))[None, :, None]).sum().backward()
    assert pr.head.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="tie_branches"):
        PrunerConfig(memory_dim=8, num_branches=3, kind="static", steps=4, tie_branches=True)


def test_step_query_pruner_decides_steps_at_a_fraction_of_the_macs(tmp_path):
    K, nb = 8, 24
    cfg = dict(memory_dim=32, num_branches=nb, hidden=16, heads=2, ffn=32, dropout=0.0, tie_branches=True)
    torch.manual_seed(0)
    per_branch, per_step = Pruner(PrunerConfig(**cfg)), Pruner(PrunerConfig(**cfg, step_query=True))
    with torch.no_grad():
        per_step.head.weight.normal_()
    memory = torch.randn(3, K, 2, 32)
    logits = per_step.eval()(memory)
    assert logits.shape == (3, K, nb, 4)  # compute + forward, timestep, rollout
    assert torch.equal(logits, logits[:, :, :1].expand_as(logits))
    assert not torch.equal(logits[0], logits[1])  # still per sample
    assert per_step.macs(K, 2) < per_branch.macs(K, 2) / 4  # the decoder runs 1 query per step, not 24
    save_pruner(per_step, tmp_path / "p")
    assert torch.equal(load_pruner(tmp_path / "p").eval()(memory), logits)
    with pytest.raises(ValueError, match="needs tie_branches"):
        PrunerConfig(memory_dim=8, num_branches=3, step_query=True)


def test_output_search_on_recorded_windows_records_the_calls_it_used(tmp_path):
    """eval/search_static.py --objective output on one toy trajectory: whole compute steps shared by
    all branches at the budget, and the calls asked for (64) vs the windows it had (3) both recorded."""
    import json

    import search_static

    _toy_policy_and_trajectories(tmp_path, [3, 4])
    out = tmp_path / "steps.json"
    search_static.main(["--checkpoint", str(tmp_path / "policy"), "--trajectories", str(tmp_path / "traj.pt"),
                        "--sparsity", "0.5", "--objective", "output", "--calls", "64", "--episodes", "1",
                        "--shifts", "1", "--sweeps", "1", "--out", str(out)])
    doc = json.loads(out.read_text())
    assert (doc["calibration_episodes"], doc["calibration_calls"], doc["calibration_calls_used"]) == (1, 64, 3)
    computes = [row for row in doc["grid"] if set(row) == {"C"}]
    assert doc["grid"][0] == "C" * len(doc["grid"][0]) and len(computes) == 3  # 6 steps at 50%, step 0 included
    assert all(set(row) in ({"C"}, {"T"}) for row in doc["grid"])  # whole steps: every branch alike


def test_output_search_of_a_policy_that_never_succeeds_needs_all_episodes(tmp_path):
    """A weak policy's trajectories hold no success: the search says so, and --all-episodes
    calibrates on every recorded state (recorded in the schedule)."""
    import json

    import search_static
    from tts.trajectories import load_trajectories, save_trajectories

    _toy_policy_and_trajectories(tmp_path, [3])
    episodes, meta = load_trajectories(tmp_path / "traj.pt")
    save_trajectories(tmp_path / "traj.pt", [{**e, "success": False} for e in episodes], meta)
    args = ["--checkpoint", str(tmp_path / "policy"), "--trajectories", str(tmp_path / "traj.pt"), "--sparsity", "0.5",
            "--objective", "output", "--shifts", "1", "--sweeps", "1", "--out", str(tmp_path / "steps.json")]
    with pytest.raises(SystemExit, match="no successful episode"):
        search_static.main(args)
    search_static.main(args + ["--all-episodes"])
    doc = json.loads((tmp_path / "steps.json").read_text())
    assert doc["calibration_on"] == "every recorded episode" and doc["calibration_calls_used"] == 3


def test_pruner_tools_of_a_policy_that_never_succeeds_use_every_episode(tmp_path):
    """Trajectories without a success (Push-T's weak policies): training says how to proceed, trains on
    every episode with --all-episodes, and the agreement check then holds out from the same list (the
    pruner's metadata says which), not from an empty list of successes."""
    import json

    import pruner_agreement
    import search_static
    import train_pruner
    from tts.trajectories import held_out_episodes, load_trajectories, save_trajectories

    _toy_policy_and_trajectories(tmp_path, [3, 4, 3, 4])
    episodes, meta = load_trajectories(tmp_path / "traj.pt")
    save_trajectories(tmp_path / "traj.pt", [{**e, "success": e["seed"] == 3} for e in episodes], meta)
    traj, ckpt = str(tmp_path / "traj.pt"), str(tmp_path / "policy")
    assert [e["seed"] for e in held_out_episodes(tmp_path / "traj.pt", 2, successful_only=False)[0]] == [2, 3]
    with pytest.raises(ValueError, match="no held-out episodes"):
        held_out_episodes(tmp_path / "traj.pt", 2)  # one success in all: index 2 is past it
    steps = tmp_path / "steps.json"
    search_static.main(["--checkpoint", ckpt, "--trajectories", traj, "--sparsity", "0.5", "--objective", "output",
                        "--shifts", "1", "--sweeps", "1", "--out", str(steps), "--all-episodes"])
    out = tmp_path / "pruner"
    args = ["--trajectories", traj, "--checkpoint", ckpt, "--out", str(out), "--sparsity", "0.5", "--epochs", "1",
            "--batch", "2", "--n-train", "2", "--n-val", "1", "--hidden", "16", "--prior", str(steps),
            "--run-dir", str(tmp_path / "run")]
    with pytest.raises(ValueError, match="only 1 usable trajectories"):
        train_pruner.main(args)
    train_pruner.main(args + ["--all-episodes"])
    assert load_pruner(out).metadata["all_episodes"] is True
    res = pruner_agreement.main(["--task", "lift", "--checkpoint", ckpt, "--pruner", str(out), "--trajectories", traj,
                                 "--out", str(tmp_path / "agreement.json")])
    # episodes 2 and 3 (3 + 4 calls, failures included) less their first, dense calls; the third call of
    # the shorter episode, padding in the lockstep replay, is not counted
    assert res["episodes"] == "2..3" and res["calls"] == 5
    assert json.loads((tmp_path / "agreement.json").read_text())["calls"] == 5


def test_a_pruner_checkpoint_of_an_interrupted_training_is_not_finished(tmp_path):
    """fit() writes the best epoch after every epoch: the recipes (recipes/lib.sh `trained`) resume a
    training whose checkpoint's history stops short of its epochs instead of skipping it."""
    import json

    from tts.training import training_finished

    def write(epochs, done):
        meta = {"epochs": epochs, "history": [{"epoch": e} for e in range(done + 1)]}
        (tmp_path / "p.json").write_text(json.dumps({"metadata": meta}))
        return training_finished(tmp_path / "p.json")

    assert not training_finished(tmp_path / "missing.json")
    assert not write(20, 3) and write(20, 20) and write(3, 3)
