"""Robot pipeline pieces: hdf5 layout, normaliser, policy, checkpoints, tts on the policy, envs."""
import numpy as np
import pytest
import torch

import tts
from conftest import randomize
from tts.adapters.dp_policy import DiffusionTransformerLowdimPolicy, Normalizer, PolicyConfig, load_policy, save_policy
from robot_suite.robomimic import Demo, read_demos, read_env_args, write_demos

OBS_DIMS = {"object": 10, "robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2}


def small_policy(num_steps=10, seed=0) -> DiffusionTransformerLowdimPolicy:
    cfg = PolicyConfig(
        model=dict(input_dim=7, output_dim=7, horizon=10, n_obs_steps=2, cond_dim=19, n_layer=2, n_head=2, n_emb=32,
                   p_drop_emb=0.0, p_drop_attn=0.1, causal_attn=True, obs_as_cond=True),
        obs_keys=list(OBS_DIMS), obs_dims=list(OBS_DIMS.values()), action_dim=7, num_inference_steps=num_steps)
    pol = DiffusionTransformerLowdimPolicy(cfg)
    randomize(pol.model, seed)
    pol.obs_normalizer.fit(torch.randn(50, 19) * 3 + 1)
    pol.action_normalizer.fit(torch.rand(50, 7) * 2 - 1)
    return pol.eval()


def obs_batch(b, seed=0):
    g = np.random.default_rng(seed)
    return {k: g.normal(size=(b, 2, d)).astype(np.float32) for k, d in OBS_DIMS.items()}


def test_hdf5_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    demos = [Demo(obs={k: rng.normal(size=(n, d)) for k, d in OBS_DIMS.items()}, actions=rng.normal(size=(n, 7)),
                  rewards=np.arange(n) == n - 1, dones=np.arange(n) == n - 1, states=rng.normal(size=(n, 5)),
                  attrs={"seed": i}) for i, n in enumerate([5, 9, 3])]
    path = tmp_path / "d.hdf5"
    assert write_demos(path, demos, {"env_name": "Lift"}, masks={"train": ["demo_0", "demo_2"]}) == 3
    back = read_demos(path)
    assert [len(d) for d in back] == [5, 9, 3]
    for a, b in zip(demos, back):
        np.testing.assert_array_equal(a.actions, b.actions)
        for k in OBS_DIMS:
            np.testing.assert_array_equal(a.obs[k], b.obs[k])
        np.testing.assert_array_equal(a.states, b.states)
        assert b.attrs["num_samples"] == len(a) and b.attrs["seed"] == a.attrs["seed"]
    assert read_env_args(path) == {"env_name": "Lift"}
    assert [len(d) for d in read_demos(path, filter_key="train")] == [5, 3]
    with pytest.raises(KeyError, match="lacks observation keys"):
        read_demos(path, obs_keys=["agentview_image"])
    import h5py

    with h5py.File(path, "r") as f:  # robomimic's layout
        assert set(f["data/demo_1"].keys()) == {"obs", "actions", "rewards", "dones", "states"}
        assert f["data"].attrs["total"] == 17


def test_normalizer_round_trip_and_range():
    x = torch.randn(100, 6) * torch.tensor([1, 10, 0.1, 5, 1, 0]) + 3  # last dim constant
    n = Normalizer(6).fit(x)
    y = n.normalize(x)
    assert y[:, :5].min() >= -1 - 1e-5 and y[:, :5].max() <= 1 + 1e-5
    assert torch.allclose(y[:, :5].amin(0), torch.full((5,), -1.0), atol=1e-5)
    torch.testing.assert_close(n.unnormalize(y), x, rtol=1e-5, atol=1e-4)
    assert torch.isfinite(y).all()


def test_predict_action_shapes_and_determinism():
    pol = small_policy()
    out = pol.predict_action(obs_batch(3), generator=torch.Generator().manual_seed(0))
    assert out["action"].shape == (3, 8, 7) and out["action_pred"].shape == (3, 10, 7)
    torch.testing.assert_close(out["action"], out["action_pred"][:, 1:9])
    again = pol.predict_action(obs_batch(3), generator=torch.Generator().manual_seed(0))
    assert torch.equal(out["action_pred"], again["action_pred"])
    with pytest.raises(KeyError, match="robot0_eef_pos"):
        pol.predict_action({k: v for k, v in obs_batch(1).items() if k != "robot0_eef_pos"})


@pytest.mark.parametrize("name", ["p", "p_0.93"])  # a dot in the name is not a suffix
def test_save_load_round_trip(tmp_path, name):
    pol = small_policy()
    save_policy(pol, tmp_path / name, metadata={"note": "test"}, dtype=torch.float32)
    assert sorted(f.name for f in tmp_path.iterdir()) == [f"{name}.json", f"{name}.safetensors"]
    back = load_policy(tmp_path / name)
    g = lambda: torch.Generator().manual_seed(1)  # noqa: E731
    assert torch.equal(pol.predict_action(obs_batch(2), g())["action"], back.predict_action(obs_batch(2), g())["action"])
    with pytest.raises(FileNotFoundError):
        load_policy(tmp_path / "missing")


def _official_payload(pol):
    sd = {f"model.{k}": v for k, v in pol.model.state_dict().items()}
    for which, norm in (("obs", pol.obs_normalizer), ("action", pol.action_normalizer)):
        sd[f"normalizer.params_dict.{which}.scale"] = norm.scale.clone()
        sd[f"normalizer.params_dict.{which}.offset"] = norm.offset.clone()
        sd[f"normalizer.params_dict.{which}.input_stats.min"] = torch.zeros(1)
    model = dict(pol.cfg.model, _target_="diffusion_policy.model.diffusion.transformer_for_diffusion.TransformerForDiffusion")
    cfg = {"horizon": 10, "n_obs_steps": 2, "n_action_steps": 8, "obs_dim": 19, "action_dim": 7,
           "policy": {"_target_": "diffusion_policy.policy.diffusion_transformer_lowdim_policy.DiffusionTransformerLowdimPolicy",
                      "model": model, "num_inference_steps": 10,
                      "noise_scheduler": {"num_train_timesteps": 100, "beta_schedule": "squaredcos_cap_v2"}}}
    return {"cfg": cfg, "state_dicts": {"model": sd, "ema_model": sd, "optimizer": {}}, "pickles": {}}


def test_official_checkpoint_layout_loads(tmp_path):
    pol = small_policy()
    path = tmp_path / "latest.ckpt"
    torch.save(_official_payload(pol), path)
    back = load_policy(path)
    assert set(back.model.state_dict()) == set(pol.model.state_dict())
    g = lambda: torch.Generator().manual_seed(1)  # noqa: E731
    obs = {"obs": np.concatenate([obs_batch(2)[k] for k in OBS_DIMS], axis=-1)}
    ref = pol.predict_action(obs_batch(2), g())["action"]
    assert torch.equal(back.predict_action(obs, g())["action"], ref)


class _Cfg(dict):
    """Stands in for OmegaConf's DictConfig: not loadable with weights_only=True."""


def test_official_checkpoint_with_pickled_config_needs_trust(tmp_path):
    payload = _official_payload(small_policy())
    payload["cfg"] = _Cfg(payload["cfg"])
    path = tmp_path / "latest.ckpt"
    torch.save(payload, path)
    with pytest.raises(ValueError, match="trust_pickle=True"):
        load_policy(path)
    assert load_policy(path, trust_pickle=True).cfg.horizon == 10


def test_accelerated_policy_uses_predict_action_and_reset_as_boundaries():
    pol = small_policy(num_steps=10)
    ref = pol.predict_action(obs_batch(2), torch.Generator().manual_seed(3))["action_pred"]
    acc = tts.accelerate(pol, plan=tts.plans.every_n(3, "rollout"))
    assert acc.num_branches == 6 and acc.tracker.explicit
    out = pol.predict_action(obs_batch(2), torch.Generator().manual_seed(3))["action_pred"]
    assert torch.equal(out, ref)  # first call of an episode is dense
    pol.predict_action(obs_batch(2, 1))
    s = acc.summary()
    assert [c.dense for c in s.calls] == [True, False] and [len(c.steps) for c in s.calls] == [10, 10]
    assert s.sparsity_of(s.calls[1]) == pytest.approx(6 / 10)
    pol.reset()
    pol.predict_action(obs_batch(2, 2))
    assert acc.summary().calls[-1].dense
    acc.remove()
    assert "predict_action" not in pol.__dict__ and "reset" not in pol.__dict__


@pytest.mark.parametrize("task", ["lift", "can"])
def test_env_short_rollout(task):
    pytest.importorskip("robosuite")
    from robot_suite.experts import EXPERTS
    from robot_suite.tasks import OBS_KEYS, low_dim_obs, make_env, reset_env

    env = make_env(task)
    raw = reset_env(env, 3)
    obs = low_dim_obs(raw)
    assert set(obs) == set(OBS_KEYS)
    assert obs["object"].shape == ((10,) if task == "lift" else (14,))
    first = obs["robot0_eef_pos"].copy()
    expert = EXPERTS[task](env)
    for _ in range(5):
        raw, _, _, _ = env.step(expert.act(raw))
    assert not np.allclose(low_dim_obs(raw)["robot0_eef_pos"], first)  # the arm moved
    again = low_dim_obs(reset_env(env, 3))  # same seed, same initial state
    np.testing.assert_allclose(again["object"], obs["object"])
    env.close()
