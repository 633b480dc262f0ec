"""Test-time sparsity on any base sampler: DDPM, DDIM (any spacing), DPM-Solver++.

The precomputed steps equal diffusers' ``step`` exactly, an all-compute plan is bit-identical to the
untouched policy on every scheduler, plans work over the base sampler's steps, and calls are found
from non-uniform timesteps without any boundary method.
"""
import pytest
import torch
from diffusers import DDIMScheduler, DDPMScheduler, DPMSolverMultistepScheduler

import tts
from common.methods import ROBOT_KINDS, install_policy, parse_method
from test_robot_pipeline import obs_batch, small_policy
from tts.adapters.schedulers import FastDDIM, FastDDPM
from tts.plans import COMPUTE

SAMPLERS = [("ddpm", 10, None), ("ddim", 4, None), ("ddim", 4, "trailing"), ("ddim", 5, "linspace"), ("dpm", 5, None)]


def _assert_replays_diffusers(s, fast):
    """Every step of ``fast`` equals ``s.step`` exactly on random model outputs (same step noise)."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 10, 7, generator=g)
    for i, t in enumerate(s.timesteps):
        out = torch.randn(3, 10, 7, generator=g)
        want = s.step(out, t, x, generator=torch.Generator().manual_seed(i)).prev_sample
        got = fast.step(i, out, x, generator=torch.Generator().manual_seed(i))
        assert torch.equal(got, want)
        x = got


@pytest.mark.parametrize("spacing", ["leading", "trailing", "linspace"])
@pytest.mark.parametrize("steps", [1, 3, 7])
@pytest.mark.parametrize("prediction", ["epsilon", "sample"])
def test_fast_ddim_equals_diffusers_step(spacing, steps, prediction):
    s = DDIMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                      set_alpha_to_one=True, steps_offset=0, prediction_type=prediction, timestep_spacing=spacing)
    s.set_timesteps(steps)
    _assert_replays_diffusers(s, FastDDIM(s))


@pytest.mark.parametrize("steps", [1, 3, 7, 100])
def test_fast_ddpm_equals_diffusers_step_on_fewer_steps(steps):
    # ddpm:K, the stochastic fewer-step sampler: jumps of 100 // K timesteps, fresh noise at each
    s = DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                      variance_type="fixed_small")
    s.set_timesteps(steps)
    fast = FastDDPM(s)
    _assert_replays_diffusers(s, fast)
    assert len(fast) == steps


@pytest.mark.parametrize("scheduler, steps, spacing", SAMPLERS)
def test_all_compute_plan_is_bit_identical_on_every_sampler(scheduler, steps, spacing):
    pol = small_policy(num_steps=10)
    pol.set_sampler(scheduler, steps, spacing)
    obs = obs_batch(3)
    ref = [pol.predict_action(obs, torch.Generator().manual_seed(c))["action"] for c in range(2)]
    with tts.accelerate(pol, ("timestep",), plan=tts.plans.dense()) as acc:
        got = [pol.predict_action(obs, torch.Generator().manual_seed(c))["action"] for c in range(2)]
        calls = acc.summary().calls
    assert all(torch.equal(a, b) for a, b in zip(ref, got))
    assert [len(c.steps) for c in calls] == [steps, steps]
    # a stateful solver starts fresh each call: the same noise gives the same actions
    again = pol.predict_action(obs, torch.Generator().manual_seed(0))["action"]
    assert torch.equal(again, ref[0])


@pytest.mark.parametrize("scheduler, steps, spacing", [("ddim", 20, None), ("dpm", 10, None)])
def test_plans_run_over_the_base_samplers_steps(scheduler, steps, spacing):
    pol = small_policy(num_steps=10)
    pol.set_sampler(scheduler, steps, spacing)
    calls = []

    def count(module, args, out):
        calls.append(1)

    hook = pol.model.decoder.layers[0].self_attn.register_forward_hook(count)
    with tts.accelerate(pol, ("timestep",), plan=tts.plans.uniform(0.65, "timestep")) as acc:
        pol.predict_action(obs_batch(2), torch.Generator().manual_seed(0))  # + one profiling step
        calls.clear()
        pol.predict_action(obs_batch(2), torch.Generator().manual_seed(1))
        d = acc.summary().calls[-1].decisions()
    hook.remove()
    computed = int((d[:, 0, 0] == COMPUTE).sum())
    assert d.shape[0] == steps and computed == round(steps * 0.35)
    assert len(calls) == computed  # skipped steps never run the branch


@pytest.mark.parametrize("train_steps, steps", [(1000, 10), (100, 6)])
def test_calls_are_found_from_non_uniform_timesteps_without_boundaries(train_steps, steps):
    """A bare transformer in a hand-written DPM-Solver++ loop with Karras sigmas: uneven timesteps.
    (A schedule that repeats a timestep needs boundaries or acc.new_call(): a repeat starts a call.)"""
    pol = small_policy(num_steps=10)
    s = DPMSolverMultistepScheduler(num_train_timesteps=train_steps, algorithm_type="dpmsolver++",
                                    use_karras_sigmas=True)
    s.set_timesteps(steps)
    ts = s.timesteps.tolist()
    assert len({a - b for a, b in zip(ts, ts[1:])}) > 1  # the timesteps really are uneven
    cond = torch.randn(2, 2, 19)
    with tts.accelerate(pol.model, ("timestep",), plan=tts.plans.uniform(0.5, "timestep")) as acc:
        for call in range(3):
            s.set_timesteps(steps)
            x = torch.randn(2, 10, 7, generator=torch.Generator().manual_seed(call))
            for t in s.timesteps:
                with torch.no_grad():
                    x = s.step(pol.model(x, t, cond), t, x).prev_sample
        calls = acc.summary().calls
    assert [len(c.steps) for c in calls] == [steps] * 3
    assert all(int((c.decisions()[:, 0, 0] == COMPUTE).sum()) == steps // 2 for c in calls)


@pytest.mark.parametrize("spec, scheduler, steps, spacing, label, slug", [
    ("ddim:3:trailing", "ddim", 3, "trailing", "ddim:3:trailing", "ddim-3-trailing"),
    ("dpm:5", "dpm", 5, None, "dpm:5", "dpm-5"),
    ("uniform:0.65:timestep+ddim:20", "ddim", 20, None, "uniform:0.65:timestep+ddim:20",
     "uniform-0.65-timestep+ddim-20"),
    ("file:s/lift_steps_0.9.json+dpm:10+taylor1", "dpm", 10, None, "file:lift_steps_0.9+dpm:10+taylor1",
     "file-lift_steps_0.9+dpm-10+taylor1"),
])
def test_sampler_specs(spec, scheduler, steps, spacing, label, slug):
    m = parse_method(spec, kinds=ROBOT_KINDS)
    assert (m.sampler.scheduler, m.sampler.steps, m.sampler.spacing) == (scheduler, steps, spacing)
    assert (m.label, m.slug) == (label, slug)


@pytest.mark.parametrize("spec, message", [
    ("ddim:3:sideways", "unknown timestep spacing 'sideways'"),
    ("dpm:3:trailing", "a sampler is ddim:K"),
    ("dpm:0", "at least 1 step"),
    ("ddim:5+ddim:20", "applies to engine methods"),
    ("uniform:0.5:timestep+ddim:20+dpm:4", "more than one base sampler"),
])
def test_sampler_spec_errors(spec, message):
    with pytest.raises(ValueError, match=message):
        parse_method(spec, kinds=ROBOT_KINDS)


def test_image_engine_methods_take_a_base_sampler_without_spacing():
    m = parse_method("every_n:2:timestep+ddim:20")  # the image suite's vocabulary
    assert (m.sampler.scheduler, m.sampler.steps, m.label) == ("ddim", 20, "every_n:2:timestep+ddim:20")
    with pytest.raises(ValueError, match="drop the spacing"):
        parse_method("uniform:0.5:timestep+ddim:20:trailing")
    with pytest.raises(ValueError, match="applies to engine methods"):
        parse_method("diffusers:taylorseer:2:1+ddim:20")


def test_install_policy_sets_the_base_sampler_first():
    pol = small_policy(num_steps=10)
    with install_policy(pol, parse_method("uniform:0.65:timestep+ddim:20", kinds=ROBOT_KINDS)) as acc:
        pol.predict_action(obs_batch(2), torch.Generator().manual_seed(0))
        d = acc.summary().calls[-1].decisions()
    assert (pol.cfg.scheduler, pol.cfg.num_inference_steps) == ("ddim", 20)
    assert d.shape[0] == 20 and int((d[:, 0, 0] == COMPUTE).sum()) == 7
    with install_policy(pol, parse_method("dpm:3", kinds=ROBOT_KINDS)) as acc:
        pol.predict_action(obs_batch(2), torch.Generator().manual_seed(0))
        assert acc.plan.describe() == "dense" and len(acc.summary().calls[-1].steps) == 3
    with pytest.raises(ValueError, match="scheduler must be one of"):
        pol.set_sampler("euler", 4)


@pytest.mark.parametrize("scheduler", ["ddim", "dpm"])
def test_dit_all_compute_plan_is_bit_identical_on_both_samplers(scheduler):
    from conftest import randomize, tiny_official_dit
    from tts.adapters.dit import sample_dit

    model = randomize(tiny_official_dit(), 0).eval()
    noise = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(0))
    ref = sample_dit(model, [1, 2], steps=6, cfg_scale=1.5, noise=noise, scheduler=scheduler)
    with tts.accelerate(model, ("forward", "timestep"), plan=tts.plans.dense()) as acc:
        got = sample_dit(model, [1, 2], steps=6, cfg_scale=1.5, noise=noise, scheduler=scheduler)
        assert len(acc.summary().calls[-1].steps) == 6
    assert torch.equal(ref, got)
    with tts.accelerate(model, ("timestep",), plan=tts.plans.uniform(0.5, "timestep")) as acc:
        sparse = sample_dit(model, [1, 2], steps=6, cfg_scale=1.5, noise=noise, scheduler=scheduler)
        assert acc.summary().sparsity() == pytest.approx(0.5)
    assert torch.isfinite(sparse).all() and not torch.equal(sparse, ref)
