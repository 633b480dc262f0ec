"""DP transformer: official parameter names, batched condition encoder, exact fast DDPM step."""
import pytest
import torch
from diffusers import DDPMScheduler

import tts
from conftest import randomize, tiny_dp
from tts.adapters.diffusion_policy import sample_actions
from tts.adapters.schedulers import FastDDPM

pytestmark = pytest.mark.usefixtures("one_thread")  # small models: threads only add synchronisation


def official_keys(n_layer):
    """State-dict keys of diffusion_policy's TransformerForDiffusion (obs cond, MLP cond encoder, causal)."""
    keys = ["_dummy_variable", "pos_emb", "cond_pos_emb", "mask", "memory_mask",
            "input_emb.weight", "input_emb.bias", "cond_obs_emb.weight", "cond_obs_emb.bias",
            "encoder.0.weight", "encoder.0.bias", "encoder.2.weight", "encoder.2.bias",
            "ln_f.weight", "ln_f.bias", "head.weight", "head.bias"]
    for i in range(n_layer):
        p = f"decoder.layers.{i}."
        for attn in ("self_attn", "multihead_attn"):
            keys += [p + attn + s for s in (".in_proj_weight", ".in_proj_bias", ".out_proj.weight", ".out_proj.bias")]
        for mod in ("linear1", "linear2", "norm1", "norm2", "norm3"):
            keys += [p + mod + ".weight", p + mod + ".bias"]
    return set(keys)


def test_state_dict_names_match_official_module():
    model = tiny_dp(layers=3)
    assert set(model.state_dict()) == official_keys(3)
    # memory mask: action token i sees cond token j iff i >= j - 1
    mm = model.memory_mask
    assert mm.shape == (6, 3)
    assert torch.isinf(mm[0, 2]) and mm[0, 1] == 0 and mm[1, 2] == 0


def test_only_decoder_layers_are_branch_sites():
    model = tiny_dp(n_cond_layers=2, layers=3)
    acc = tts.accelerate(model)
    assert [s.name for s in acc.sites] == [f"decoder.layers.{i}" for i in range(3)]
    assert acc.branch_names[:3] == ["decoder.layers.0.self_attn", "decoder.layers.0.cross_attn", "decoder.layers.0.ff"]
    acc.remove()


@pytest.mark.parametrize("n_cond_layers", [0, 1])
def test_batched_condition_memory_equals_per_step_encoder(n_cond_layers):
    model = randomize(tiny_dp(n_cond_layers=n_cond_layers)).eval()
    cond = torch.randn(3, 2, 7)
    timesteps = torch.tensor([99, 50, 3, 0])
    x = torch.randn(3, 6, 5)
    with torch.no_grad():
        mem = model.condition_memory(timesteps, cond)
        assert mem.shape == (3, 4, 3, 32)
        for i, t in enumerate(timesteps):
            per_step = model(x, t, cond)
            with_mem = model(x, t, cond, memory=mem[:, i])
            torch.testing.assert_close(with_mem, per_step, rtol=0, atol=1e-5)


def _scheduler(k=20):
    s = DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                      prediction_type="epsilon")
    s.set_timesteps(k)
    return s


def test_fast_ddpm_equals_diffusers_step():
    sched = _scheduler()
    fast = FastDDPM(sched)
    x = torch.randn(2, 6, 5)
    for i, t in enumerate(sched.timesteps):
        eps = torch.randn(2, 6, 5)
        ref = sched.step(eps, t, x, generator=torch.Generator().manual_seed(i)).prev_sample
        got = fast.step(i, eps, x, torch.Generator().manual_seed(i))
        assert torch.equal(got, ref)
        x = ref


def test_fast_sampler_matches_stock_loop():
    model = randomize(tiny_dp()).eval()
    cond = torch.randn(2, 2, 7)
    sched = _scheduler()
    a = sample_actions(model, cond, sched, generator=torch.Generator().manual_seed(0), fast=False)
    b = sample_actions(model, cond, sched, generator=torch.Generator().manual_seed(0), fast=True)
    torch.testing.assert_close(a, b, rtol=0, atol=1e-4)


def test_accelerated_sampler_counts_steps_and_skips():
    model = randomize(tiny_dp()).eval()
    sched = _scheduler(20)
    acc = tts.accelerate(model, ("timestep",), sparsity=0.8)
    for _ in range(2):
        sample_actions(model, torch.randn(1, 2, 7), sched)
    s = acc.summary()
    assert [len(c.steps) for c in s.calls] == [20, 20]
    assert s.sparsity_of(s.calls[-1]) == pytest.approx(0.8)
    dense, realised = s.macs(s.calls[-1])
    assert realised < 0.35 * dense
    acc.remove()


def test_fast_ddpm_rejects_unsupported_config():
    s = DDPMScheduler(num_train_timesteps=100, variance_type="fixed_large")
    s.set_timesteps(10)
    with pytest.raises(NotImplementedError, match="fixed_small"):
        FastDDPM(s)
