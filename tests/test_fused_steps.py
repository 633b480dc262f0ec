"""Whole-step fusion (tts.spec): a step whose every branch reuses T or R runs as one add."""
import pytest
import torch

import tts
from tts.plans import COMPUTE, ROLLOUT, TIMESTEP

from conftest import TorchStack, randomize, tiny_dp, tiny_official_dit, torch_stack_inputs

pytestmark = pytest.mark.usefixtures("one_thread")  # small models: threads only add synchronisation

STEPS = 12


def dit_inputs(batch):
    g = torch.Generator().manual_seed(4)
    return torch.randn(batch, 4, 8, 8, generator=g), torch.arange(batch) % 10


def run_dit(model, plan, *, fuse, forecast=0, batch=2, count_reads=False):
    x, y = dit_inputs(batch)
    outs = []
    with torch.no_grad(), tts.accelerate(model, ("forward", "timestep"), plan=plan, forecast=forecast,
                                         fuse_steps=fuse) as acc:
        reads = []
        if count_reads:
            read = acc.cache.read
            acc.cache.read = lambda *a: reads.append(a) or read(*a)
        for k in range(STEPS):
            outs.append(model(x + 0.01 * k, torch.full((batch,), 900 - 50 * k), y))
        return torch.stack(outs), acc.summary().calls[-1], len(reads)


def whole_steps(compute, nb, reuse=TIMESTEP):
    return tts.plans.from_tensor([[COMPUTE if k in compute else reuse] * nb for k in range(STEPS)])


@pytest.mark.parametrize("forecast", [0, 2])
def test_fused_dit_steps_match_branch_by_branch_and_read_no_branch(forecast):
    model = randomize(tiny_official_dit()).eval()
    plan = whole_steps({0, 3, 5, 9}, nb=6)
    fused, rec, reads = run_dit(model, plan, fuse=True, forecast=forecast, count_reads=True)
    plain, rec_plain, reads_plain = run_dit(model, plan, fuse=False, forecast=forecast, count_reads=True)
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=1e-5)
    assert rec.fused_steps == STEPS - 4 and rec_plain.fused_steps == 0
    assert reads == 0  # per-order sums kept between computes: no per-branch read at all
    assert reads_plain == (STEPS - 4) * 6
    # decisions and sparsity are recorded as before
    assert torch.equal(rec.decisions(), rec_plain.decisions())


def test_fusion_needs_every_branch_and_every_sample_to_reuse():
    model = randomize(tiny_official_dit()).eval()
    grid = [[COMPUTE] * 6 if k in (0, 6) else [TIMESTEP] * 6 for k in range(STEPS)]
    grid[3] = [TIMESTEP] * 5 + [COMPUTE]  # one branch computes: not fused
    per_sample = torch.tensor([grid, grid], dtype=torch.int8)
    per_sample[1, 8] = COMPUTE  # sample 1 computes step 8: samples disagree, not fused
    plan = tts.plans.from_tensor(per_sample)
    fused, rec, _ = run_dit(model, plan, fuse=True)
    plain, _, _ = run_dit(model, plan, fuse=False)
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=1e-5)
    assert rec.fused_steps == STEPS - 2 - 2


def test_fused_rollout_steps_in_a_diffusion_policy_transformer():
    model = randomize(tiny_dp()).eval()  # pre-norm nn.TransformerDecoder: a residual chain
    nb = 3 * 3
    plan = tts.plans.from_tensor([[COMPUTE] * nb] + [[ROLLOUT] * nb, [TIMESTEP] * nb] * 3)
    g = torch.Generator().manual_seed(5)
    xs = [torch.randn(2, 6, 5, generator=g) for _ in range(3)]
    cond = torch.randn(2, 2, 7, generator=g)

    def run(fuse):
        outs = []
        with torch.no_grad(), tts.accelerate(model, ("timestep", "rollout"), plan=plan, fuse_steps=fuse) as acc:
            for x in xs:  # three calls of one episode: the first is dense and fills the rollout cache
                for k in range(7):
                    outs.append(model(x + 0.1 * k, torch.tensor(90 - 10 * k), cond))
            return torch.stack(outs), [c.fused_steps for c in acc.summary().calls]

    fused, counts = run(True)
    plain, counts_plain = run(False)
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=1e-5)
    assert counts == [0, 6, 6] and counts_plain == [0, 0, 0]


@pytest.mark.parametrize("norm_first", [True, False])
def test_no_fusion_without_a_declared_chain_or_for_post_norm_layers(norm_first):
    """Blocks found by discovery (no adapter) make no chain promise; post-norm layers are not sums."""
    model = randomize(TorchStack("decoder", norm_first)).eval()
    x, t, mem = torch_stack_inputs(2)
    plan = whole_steps({0}, nb=9)
    with torch.no_grad(), tts.accelerate(model, ("timestep",), plan=plan) as acc:
        for k in range(3):
            model(x, t - k, mem)
    assert not acc.fuse_steps and acc.summary().calls[-1].fused_steps == 0
    dp = randomize(tiny_dp()).eval()
    for layer in dp.decoder.layers:
        layer.norm_first = norm_first
    with tts.accelerate(dp, ("timestep",), plan=plan) as acc:
        assert acc.fuse_steps == norm_first


@pytest.mark.parametrize("fuse_norm", [False, True])
def test_fused_dp_steps_skip_the_decoder_entirely(fuse_norm):
    """With Target.skip_blocks a fused step runs embedding + sum + head only: no decoder layer is
    entered, and the outputs equal branch-by-branch reuse (up to summation order)."""
    model = randomize(tiny_dp()).eval()
    if fuse_norm:  # an nn.TransformerDecoder(norm=...) applies it after the chain
        model.decoder.norm = torch.nn.LayerNorm(model.pos_emb.shape[-1])
        randomize(model.decoder.norm, 3)
    nb = 3 * 3
    plan = whole_steps({0, 4, 9}, nb=nb)
    g = torch.Generator().manual_seed(6)
    x0, cond = torch.randn(2, 6, 5, generator=g), torch.randn(2, 2, 7, generator=g)
    entered = []
    hook = model.decoder.layers[0].register_forward_pre_hook(lambda m, a: entered.append(1))

    def run(fuse):
        entered.clear()
        outs = []
        with torch.no_grad(), tts.accelerate(model, ("timestep",), plan=plan, fuse_steps=fuse) as acc:
            for k in range(STEPS):
                outs.append(model(x0 + 0.1 * k, torch.tensor(90 - 7 * k), cond))
            return torch.stack(outs), acc.summary().calls[-1].fused_steps, len(entered)

    fused, n_fused, entered_fused = run(True)
    plain, n_plain, entered_plain = run(False)
    hook.remove()
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=1e-5)
    assert n_fused == STEPS - 3 and n_plain == 0
    assert entered_plain == STEPS + 1 and entered_fused == 3 + 1  # steps that run the blocks + one MAC profile
