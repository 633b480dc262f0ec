"""Token-wise partial refresh (ToCa/DuCa-style plans, decision code TOKENS) on a DiT."""
from __future__ import annotations

import math

import pytest
import torch

pytest.importorskip("timm")

import tts  # noqa: E402
from conftest import randomize, tiny_official_dit  # noqa: E402
from tts.adapters.dit import _attention_probe, sample_dit  # noqa: E402
from tts.plans import COMPUTE, TIMESTEP, TOKENS  # noqa: E402
from tts.tokens import TokenRefreshPlan, duca, fresh_ratio_for, toca  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

STEPS = 8


def _model():
    return randomize(tiny_official_dit(), seed=0).eval()  # 8x8x4 (16 tokens), hidden 32, depth 3


def _noise(b=2):
    return torch.randn(b, 4, 8, 8, generator=torch.Generator().manual_seed(1))


def _sample(model, b=2):
    return sample_dit(model, list(range(b)), steps=STEPS, cfg_scale=1.5, noise=_noise(b))


def _mlp_token_counts(model):
    """Token counts seen by every MLP call (forward pre-hooks)."""
    seen = []
    hooks = [blk.mlp.register_forward_pre_hook(lambda m, a: seen.append(a[0].shape[1])) for blk in model.blocks]
    return seen, hooks


def test_full_fresh_ratio_equals_recomputing_the_mlp_and_reusing_attention():
    model = _model()
    # ratio 1: every MLP token is recomputed, attention reused -> the same as an explicit C/T plan
    grid = [["C"] * 6] + [["T", "C"] * 3 for _ in range(3)] + [["C"] * 6] + [["T", "C"] * 3 for _ in range(3)]
    with tts.accelerate(model, ("timestep",), plan=tts.plans.from_tensor(["".join(r) for r in grid])):
        want = _sample(model)
    with tts.accelerate(model, ("timestep",), plan=toca(4, 1.0)) as acc:
        got = _sample(model)
    # equal up to float round-off: tokens run in another order, full steps use non-fused attention (probe)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=2e-5)
    d = acc.summary().calls[-1].decisions()
    assert int((d == TOKENS).sum()) == 6 * 3 * d.shape[1]  # 6 refresh steps x 3 MLPs x rows (CFG doubles)


def test_only_the_chosen_tokens_are_computed_and_macs_follow():
    model = _model()
    seen, hooks = _mlp_token_counts(model)
    try:
        with tts.accelerate(model, ("timestep",), plan=toca(4, 0.25)) as acc:
            _sample(model)
    finally:
        for h in hooks:
            h.remove()
    n_tokens = 16
    m = math.ceil(0.25 * n_tokens)
    # the MAC-profiling dry run of step 0 + 2 full steps (16 tokens, 3 MLPs) + 6 refresh steps (m tokens)
    assert sorted(seen) == sorted([n_tokens] * 3 * 3 + [m] * 6 * 3)
    s = acc.summary()
    call = s.calls[-1]
    assert call.token_work == {b: pytest.approx(6 * m / n_tokens) for b in (1, 3, 5)}
    dense, realised = s.macs(call)
    with tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(4)) as acc2:
        _sample(model)
    _, fora = acc2.summary().macs(acc2.summary().calls[-1])
    mlp = [s.macs_per_row[("branch", b)] for b in (1, 3, 5)]
    shared = sum(s.macs_per_row[("shared", i)] for i in range(3))
    rows = call.batch
    assert realised == pytest.approx(fora + rows * (sum(mlp) * 6 * m / n_tokens + shared * 6))
    assert realised < dense


def test_duplicate_score_refreshes_the_most_distinct_tokens_and_staleness_rotates():
    plan = TokenRefreshPlan(4, 0.25, score="duplicate", staleness_weight=0.0)
    plan.bind(2, ["self_attn", "mlp"])
    plan.begin_call(0, 1)
    plan.step(0, 1)
    cached = torch.ones(1, 8, 3)
    cached[0, 5] = torch.tensor([-1.0, 2.0, 0.0])  # the two odd ones out
    cached[0, 2] = torch.tensor([1.0, -1.0, 1.0])
    idx = plan.select_tokens(1, 0, 1, cached)
    assert sorted(idx[0].tolist()) == [2, 5]
    # with a dominant staleness term, refreshed tokens wait: 4 steps cover all 8 tokens
    plan = TokenRefreshPlan(5, 0.25, score="duplicate", staleness_weight=100.0)
    plan.bind(2, ["self_attn", "mlp"])
    plan.begin_call(0, 1)
    plan.step(0, 1)
    chosen = [plan.select_tokens(1, 0, k, cached)[0].tolist() for k in range(1, 5)]
    assert sorted(sum(chosen, [])) == list(range(8))


def test_attention_probe_matches_the_branch_and_scores_received_attention():
    model = _model()
    blk = model.blocks[0]
    x = torch.randn(2, 16, 32)
    m = blk.adaLN_modulation(torch.randn(2, 32)).chunk(6, dim=1)

    def fn(h, mod):
        from tts.adapters.dit import modulate
        return mod[2].unsqueeze(1) * blk.attn(modulate(blk.norm1(h), mod[0], mod[1]))

    delta, received = _attention_probe(fn, blk, x, m)
    torch.testing.assert_close(delta, fn(x, m), rtol=1e-5, atol=1e-6)
    assert received.shape == (2, 16)
    torch.testing.assert_close(received.sum(1), torch.ones(2))
    assert blk.attn.fused_attn == tts.adapters.dit.DiTBlock(32, 2).attn.fused_attn  # restored


def test_duca_alternates_aggressive_and_conservative_steps():
    model = _model()
    with tts.accelerate(model, ("timestep",), plan=duca(4, 0.5)) as acc:
        _sample(model)
    rows = acc.summary().calls[-1].decisions()[:, 0]
    kinds = [set(r.tolist()) for r in rows]
    assert kinds[0] == {COMPUTE} and kinds[4] == {COMPUTE}
    assert kinds[1] == {TIMESTEP, TOKENS} and kinds[3] == {TIMESTEP, TOKENS}
    assert kinds[2] == {TIMESTEP}


def test_fresh_ratio_for_matches_the_budget():
    r = fresh_ratio_for(0.8, 6, token_share=0.6)
    assert (1 / 6 + 5 / 6 * r * 0.6) == pytest.approx(0.2)
    r = fresh_ratio_for(0.8, 6, token_share=0.6, alternate=True)
    assert (1 / 6 + 3 / 6 * r * 0.6) == pytest.approx(0.2)
    with pytest.raises(ValueError, match="already computes"):
        fresh_ratio_for(0.8, 5, token_share=0.6)


def test_token_plan_errors():
    model = _model()
    with pytest.raises(ValueError, match="timestep"):
        tts.accelerate(model, ("forward",), plan=toca(4, 0.2))
    with pytest.raises(ValueError, match="forecast"):
        tts.accelerate(model, ("timestep",), plan=toca(4, 0.2), forecast=1)
    with pytest.raises(ValueError, match="n must be >= 2"):
        toca(1, 0.2)
    with pytest.raises(ValueError, match="fresh_ratio"):
        duca(4, 0.0)
    with pytest.raises(ValueError, match="unknown token score"):
        TokenRefreshPlan(4, 0.2, score="random")
    with pytest.raises(ValueError, match="no branch of kind"):
        tts.accelerate(model, ("timestep",), plan=toca(4, 0.2, token_kinds=("ffn",)))


def test_imagenet_cli_token_methods(tmp_path):
    from common.methods import parse_method
    from image_suite.sampling import build_accelerator, mlp_share

    with pytest.raises(ValueError, match="exactly one of a fresh-token ratio"):
        parse_method("toca:6")
    with pytest.raises(ValueError, match="exactly one of a fresh-token ratio"):
        parse_method("toca:6:0.1@0.8")
    with pytest.raises(ValueError, match="not available in this suite"):
        parse_method("toca:6:0.1", kinds=frozenset({"dense", "ddim"}))
    model = _model()
    acc = build_accelerator(model, parse_method("duca:6@0.8"), steps=10, cfg=1.5, calib_seed=1)
    try:
        plan = acc.plan
        assert plan.alternate and plan.n == 6
        r = fresh_ratio_for(0.8, 6, mlp_share(model), alternate=True)
        assert plan.fresh_ratio == pytest.approx(r)
        # the MLP share of the tiny DiT (hidden 32, 16 tokens, mlp ratio 4): 256 / (256 + 128 + 32)
        assert mlp_share(model) == pytest.approx(2 * 32 * 128 / (2 * 32 * 128 + 4 * 32 * 32 + 2 * 16 * 32))
    finally:
        acc.remove()
