"""tts on Diffusion Policy's own, unmodified classes: the transformer and a policy around it.

``OfficialDPT`` has the attribute layout and forward of diffusion_policy's
``model/diffusion/transformer_for_diffusion.py`` (written here from that layout) and none of our
helpers (no ``condition_memory``, no ``memory=`` argument): its forward embeds the timestep and the
observation tokens, runs the condition encoder and the decoder at every step. ``OfficialStylePolicy``
has what an official low-dim policy offers tts: ``model``, ``noise_scheduler``,
``predict_action(obs_dict)`` and ``reset()``.
"""
import math
from types import SimpleNamespace

import pytest
import torch
import torch.nn as nn

import tts
from conftest import randomize, tiny_dp
from tts.plans import ROLLOUT, TIMESTEP

pytestmark = pytest.mark.usefixtures("one_thread")  # many tiny ops: threads only add synchronisation

HORIZON, N_OBS, OBS_DIM, ACT_DIM, WIDTH, LAYERS = 6, 2, 7, 5, 32, 3
NB = 3 * LAYERS


class TimeEmbedding(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.dim = dim

    def forward(self, t):
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half, device=t.device) * -(math.log(10000) / (half - 1)))
        angles = t[:, None] * freqs[None, :]
        return torch.cat((angles.sin(), angles.cos()), dim=-1)


def additive(allowed):
    return torch.zeros(allowed.shape).masked_fill(~allowed, float("-inf"))


class OfficialDPT(nn.Module):
    """Observations as condition tokens, time as a condition token, causal attention."""

    def __init__(self, n_cond_layers=0):
        super().__init__()
        T, T_cond = HORIZON, 1 + N_OBS
        self._dummy_variable = nn.Parameter()
        self.input_emb = nn.Linear(ACT_DIM, WIDTH)
        self.pos_emb = nn.Parameter(torch.zeros(1, T, WIDTH))
        self.drop = nn.Dropout(0.0)
        self.time_emb = TimeEmbedding(WIDTH)
        self.cond_obs_emb = nn.Linear(OBS_DIM, WIDTH)
        self.cond_pos_emb = nn.Parameter(torch.zeros(1, T_cond, WIDTH))
        if n_cond_layers:
            layer = nn.TransformerEncoderLayer(WIDTH, 2, 4 * WIDTH, 0.3, activation="gelu", batch_first=True,
                                               norm_first=True)
            self.encoder = nn.TransformerEncoder(layer, n_cond_layers, enable_nested_tensor=False)
        else:
            self.encoder = nn.Sequential(nn.Linear(WIDTH, 4 * WIDTH), nn.Mish(), nn.Linear(4 * WIDTH, WIDTH))
        layer = nn.TransformerDecoderLayer(WIDTH, 2, 4 * WIDTH, 0.3, activation="gelu", batch_first=True,
                                           norm_first=True)
        self.decoder = nn.TransformerDecoder(layer, LAYERS)
        rows, cols = torch.meshgrid(torch.arange(T), torch.arange(T_cond), indexing="ij")
        self.register_buffer("mask", additive(torch.ones(T, T, dtype=torch.bool).tril()))
        self.register_buffer("memory_mask", additive(rows >= cols - 1))
        self.ln_f = nn.LayerNorm(WIDTH)
        self.head = nn.Linear(WIDTH, ACT_DIM)
        self.T, self.T_cond, self.horizon = T, T_cond, HORIZON
        self.time_as_cond, self.obs_as_cond, self.encoder_only = True, True, False

    def forward(self, sample, timestep, cond=None, **kwargs):
        t = timestep
        if not torch.is_tensor(t):
            t = torch.tensor([t], dtype=torch.long, device=sample.device)
        elif t.dim() == 0:
            t = t[None].to(sample.device)
        time = self.time_emb(t.expand(sample.shape[0])).unsqueeze(1)
        tokens = torch.cat([time, self.cond_obs_emb(cond)], dim=1)
        memory = self.encoder(self.drop(tokens + self.cond_pos_emb[:, : tokens.shape[1]]))
        x = self.input_emb(sample)
        x = self.drop(x + self.pos_emb[:, : x.shape[1]])
        x = self.decoder(tgt=x, memory=memory, tgt_mask=self.mask, memory_mask=self.memory_mask)
        return self.head(self.ln_f(x))


class TinyScheduler:
    """What the policy's loop needs of a diffusers scheduler."""

    def __init__(self):
        self.set_timesteps(100)

    def set_timesteps(self, n):
        self.timesteps = torch.linspace(99, 0, n).round().long()

    def step(self, out, t, x, generator=None):
        return SimpleNamespace(prev_sample=0.9 * x - 0.1 * out)


class OfficialStylePolicy(nn.Module):
    def __init__(self, model, steps=30):
        super().__init__()
        self.model = model
        self.noise_scheduler = TinyScheduler()
        self.num_inference_steps = steps

    def reset(self):
        pass

    def predict_action(self, obs_dict):
        cond = obs_dict["obs"][:, :N_OBS]
        g = torch.Generator().manual_seed(0)
        x = torch.randn(cond.shape[0], HORIZON, ACT_DIM, generator=g)
        self.noise_scheduler.set_timesteps(self.num_inference_steps)
        with torch.no_grad():
            for t in self.noise_scheduler.timesteps:
                x = self.noise_scheduler.step(self.model(x, t, cond), t, x).prev_sample
        return {"action": x[:, N_OBS - 1:], "action_pred": x}


def official(n_cond_layers=0):
    return randomize(OfficialDPT(n_cond_layers)).eval()


def observations(batch, seed):
    return {"obs": torch.randn(batch, N_OBS, OBS_DIM, generator=torch.Generator().manual_seed(seed))}


def count_branch_calls(model):
    """Branch executions per kind, counted at the modules only that branch uses."""
    counts = {"self_attn": 0, "cross_attn": 0, "ff": 0}
    handles = []
    for layer in model.decoder.layers:
        for name, module in (("self_attn", layer.self_attn), ("cross_attn", layer.multihead_attn),
                             ("ff", layer.linear1)):
            handles.append(module.register_forward_hook(lambda *_, n=name: counts.__setitem__(n, counts[n] + 1)))
    return counts, handles


def test_official_layout_is_ours_and_has_none_of_our_helpers():
    model = official()
    assert not hasattr(model, "condition_memory")
    ours = tiny_dp(layers=LAYERS).eval()
    assert set(model.state_dict()) == set(ours.state_dict())
    ours.load_state_dict(model.state_dict())
    x, t, cond = torch.randn(2, HORIZON, ACT_DIM), torch.tensor(17), torch.randn(2, N_OBS, OBS_DIM)
    with torch.no_grad():
        assert torch.equal(ours(x, t, cond), model(x, t, cond))


@pytest.mark.parametrize("n_cond_layers", [0, 1])
def test_dense_is_bit_exact_on_the_untouched_module_and_policy(n_cond_layers):
    model = official(n_cond_layers)
    policy = OfficialStylePolicy(model, steps=10)
    refs = [policy.predict_action(observations(2, s))["action_pred"] for s in range(2)]
    with tts.accelerate(model) as acc:  # the module itself, calls found from the timesteps
        outs = [policy.predict_action(observations(2, s))["action_pred"] for s in range(2)]
        assert len(acc.summary().calls) == 2
    assert all(torch.equal(a, b) for a, b in zip(outs, refs))
    with tts.accelerate(policy) as acc:  # the policy: predict_action starts a call, reset() an episode
        policy.reset()
        outs = [policy.predict_action(observations(2, s))["action_pred"] for s in range(2)]
        assert acc.summary().sparsity() == 0.0 and len(acc.summary().calls) == 2
    assert all(torch.equal(a, b) for a, b in zip(outs, refs))
    assert all("forward" not in m.__dict__ for m in model.modules()) and "predict_action" not in policy.__dict__


@pytest.mark.parametrize("on", ["module", "policy"])
def test_sparse_plan_really_skips_branches(on):
    model = official()
    policy = OfficialStylePolicy(model, steps=30)
    ref = policy.predict_action(observations(1, 0))["action_pred"]
    with tts.accelerate(policy if on == "policy" else model, ("timestep",),
                        plan=tts.plans.uniform(0.93, "timestep")) as acc:
        policy.predict_action(observations(1, 1))  # the first call also profiles MACs (one dense step)
        counts, handles = count_branch_calls(model)
        out = policy.predict_action(observations(1, 0))["action_pred"]
        for h in handles:
            h.remove()
        last = acc.summary().calls[-1]
    computed_steps = 3  # of 30 at 7% density: steps 0, 15 and 29
    assert counts == {kind: computed_steps * LAYERS for kind in counts}
    assert int((last.decisions() == TIMESTEP).sum()) == (30 - computed_steps) * NB
    assert acc.summary().sparsity_of(last) == pytest.approx(0.9)
    assert (out - ref).abs().max() > 1e-4


def test_rollout_direction_through_reset():
    model = official()
    policy = OfficialStylePolicy(model, steps=10)
    plan = tts.plans.from_tensor(["C" * NB if k % 5 == 0 else "R" * NB for k in range(10)])
    ref = policy.predict_action(observations(2, 0))["action_pred"]
    with tts.accelerate(policy, ("timestep", "rollout"), plan=plan) as acc:
        policy.reset()
        first = policy.predict_action(observations(2, 0))["action_pred"]
        assert len(acc.cache.rollout) == 10  # the dense first call filled the rollout cache
        counts, handles = count_branch_calls(model)
        second = policy.predict_action(observations(2, 1))["action_pred"]
        for h in handles:
            h.remove()
        policy.reset()
        assert acc.cache.rollout == []  # reset() ends the episode
        after_reset = policy.predict_action(observations(2, 0))["action_pred"]
        calls = acc.summary().calls
    assert [c.dense for c in calls] == [True, False, True]
    assert counts == {kind: 2 * LAYERS for kind in counts}  # steps 0 and 5 computed, the rest reused
    assert int((calls[1].decisions() == ROLLOUT).sum()) == 8 * 2 * NB
    assert torch.equal(first, ref) and torch.equal(after_reset, ref)  # first calls of an episode: dense
    dense_second = OfficialStylePolicy(official(), steps=10).predict_action(observations(2, 1))["action_pred"]
    assert (second - dense_second).abs().max() > 1e-4


def test_learned_pruner_reads_the_condition_built_from_the_official_attributes():
    model = official()
    policy = OfficialStylePolicy(model, steps=10)
    ours = tiny_dp(layers=LAYERS).eval()
    ours.load_state_dict(model.state_dict())
    # head bias: reuse the timestep cache everywhere after step 0 (an untrained pruner computes everything)
    pruner = tts.Pruner(tts.PrunerConfig(memory_dim=WIDTH, num_branches=NB, directions=("timestep",),
                                         head_bias=[0.0, 5.0]))
    seen = []
    with tts.accelerate(policy, ("timestep",), pruner=pruner, parallel=False) as acc:
        observe = acc.plan.observe
        acc.plan.observe = lambda memory, dense: seen.append(memory) or observe(memory, dense)
        obs = observations(3, 0)
        out = policy.predict_action(obs)["action_pred"]
        last = acc.summary().calls[-1]
    assert len(seen) == 1 and seen[0].shape == (3, 10, 1 + N_OBS, WIDTH)
    with torch.no_grad():
        expected = ours.condition_memory(policy.noise_scheduler.timesteps, obs["obs"][:, :N_OBS])
    torch.testing.assert_close(seen[0], expected, rtol=0, atol=1e-6)
    assert int((last.decisions() == TIMESTEP).sum()) == 9 * 3 * NB and last.pruner_macs > 0
    assert "encoder" in last.timing
    ref = OfficialStylePolicy(model, steps=10).predict_action(obs)["action_pred"]
    assert (out - ref).abs().max() > 1e-4


def test_learned_pruner_on_the_bare_module_names_what_is_missing():
    pruner = tts.Pruner(tts.PrunerConfig(memory_dim=WIDTH, num_branches=NB, directions=("timestep",)))
    with pytest.raises(ValueError, match="condition_memory.*policy"):
        tts.accelerate(official(), ("timestep",), pruner=pruner)
