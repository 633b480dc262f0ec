"""The image-observation DP-T: encoder shapes, the encoder hoisted out of the denoising loop (once
per policy call, also when accelerated), exactness of an all-compute plan, checkpoints, and the
robomimic image hdf5 layout."""
import numpy as np
import pytest
import torch

import tts
from test_robot_pipeline import OBS_DIMS
from tts.adapters.dp_image_policy import (DiffusionTransformerHybridImagePolicy, ImageEncoderConfig, ObsEncoder,
                                          SpatialSoftmax)
from tts.adapters.dp_policy import PolicyConfig, load_policy, save_policy

from conftest import randomize

CAMS = ("agentview_image", "robot0_eye_in_hand_image")
IMG = ImageEncoderConfig(cameras=CAMS, image_size=32, crop_size=24, num_kp=4, feature_dim=8, width=16)


def image_policy(steps: int = 6) -> DiffusionTransformerHybridImagePolicy:
    cond = IMG.features + sum(OBS_DIMS.values())
    cfg = PolicyConfig(model=dict(input_dim=7, output_dim=7, horizon=10, n_obs_steps=2, cond_dim=cond, n_layer=2,
                                  n_head=2, n_emb=32, p_drop_emb=0.0, p_drop_attn=0.1, causal_attn=True,
                                  obs_as_cond=True),
                       obs_keys=list(OBS_DIMS), obs_dims=list(OBS_DIMS.values()), action_dim=7,
                       num_inference_steps=steps)
    pol = DiffusionTransformerHybridImagePolicy(cfg, IMG)
    randomize(pol.model, 0)
    pol.obs_normalizer.fit(torch.randn(50, sum(OBS_DIMS.values())) * 3 + 1)
    pol.action_normalizer.fit(torch.rand(50, 7) * 2 - 1)
    return pol.eval()


def image_obs(b: int, seed: int = 0, frames: int = 2) -> dict:
    g = np.random.default_rng(seed)
    obs = {k: g.normal(size=(b, frames, d)).astype(np.float32) for k, d in OBS_DIMS.items()}
    for cam in CAMS:
        obs[cam] = g.integers(0, 256, size=(b, frames, 32, 32, 3), dtype=np.uint8)
    return obs


def test_encoder_shapes_keypoints_and_crops():
    enc = ObsEncoder(IMG)
    imgs = {cam: torch.randint(0, 256, (5, 32, 32, 3), dtype=torch.uint8) for cam in CAMS}
    assert enc.eval()(imgs).shape == (5, 2 * 8)
    x = torch.rand(5, 3, 32, 32)
    centre = enc.crop(x)
    assert centre.shape == (5, 3, 24, 24) and torch.equal(centre, x[..., 4:28, 4:28])
    enc.train()
    torch.manual_seed(0)
    crops = enc.crop(x)
    assert crops.shape == (5, 3, 24, 24) and not torch.equal(crops, centre)
    kp = SpatialSoftmax(16, 3, 3, num_kp=4)(torch.randn(2, 16, 3, 3))
    assert kp.shape == (2, 8) and kp.abs().max() <= 1
    with pytest.raises(ValueError, match="expected \\[N, H, W, 3\\]"):
        enc({cam: torch.zeros(2, 3, 32, 32, dtype=torch.uint8) for cam in CAMS})
    with pytest.raises(ValueError, match="multiple of 16"):
        ImageEncoderConfig(width=20)


def test_image_encoder_runs_once_per_call_and_is_timed():
    pol = image_policy()
    calls = []
    pol.obs_encoder.register_forward_hook(lambda m, a, o: calls.append(a[0][CAMS[0]].shape[0]))
    pol.predict_action(image_obs(3), torch.Generator().manual_seed(0))
    assert calls == [3 * 2]  # one forward for all frames of the batch, none inside the 6-step loop
    calls.clear()
    with tts.accelerate(pol, ("timestep",), plan=tts.plans.uniform(0.5, "timestep")) as acc:
        for c in range(2):
            pol.predict_action(image_obs(3, c), torch.Generator().manual_seed(c))
        timing = acc.summary().calls[-1].timing
        phases = acc.summary().timing(acc.summary().calls[-1:])
    assert calls == [6, 6]
    assert timing["image_encoder"] > 0 and timing["total"] >= timing["image_encoder"]
    # the breakdown's phases add up to the call: the encoder is not counted again in the rest
    parts = ("encoder", "wait", "decoder", "engine", "image_encoder", "scheduler_and_rest")
    assert sum(phases.get(k, 0.0) for k in parts) == pytest.approx(phases["total"], rel=1e-5)
    assert phases["scheduler_and_rest"] < phases["total"] - 0.9 * phases["image_encoder"]


def test_encoder_share_timer_times_each_call_and_puts_the_encoder_back():
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "eval"))
    from common.policy_timing import timed_image_encoder

    pol = image_policy()
    with tts.accelerate(pol, ("timestep",), plan=tts.plans.uniform(0.5, "timestep")) as acc:
        engine_forward = pol.obs_encoder.__dict__["forward"]  # the engine's own timer
        with timed_image_encoder(pol) as times:
            for c in range(3):
                pol.predict_action(image_obs(2, c), torch.Generator().manual_seed(c))
        assert len(times) == 3 and min(times) > 0
        assert pol.obs_encoder.__dict__["forward"] is engine_forward
        assert acc.summary().calls[-1].timing["image_encoder"] > 0  # still timed under the wrapper
    assert "forward" not in pol.obs_encoder.__dict__
    with timed_image_encoder(pol) as times:
        pol.predict_action(image_obs(2), torch.Generator().manual_seed(0))
    assert len(times) == 1 and "forward" not in pol.obs_encoder.__dict__
    with timed_image_encoder(object()) as times:  # a policy without an obs_encoder records nothing
        pass
    assert times == []


def test_all_compute_plan_is_bit_identical_and_checkpoints_round_trip(tmp_path):
    pol = image_policy()
    obs = image_obs(2, 3)
    ref = pol.predict_action(obs, torch.Generator().manual_seed(1))["action"]
    with tts.accelerate(pol, ("timestep", "rollout"), plan=tts.plans.dense()):
        assert torch.equal(pol.predict_action(obs, torch.Generator().manual_seed(1))["action"], ref)
    save_policy(pol, tmp_path / "img", dtype=torch.float32)
    back = load_policy(tmp_path / "img")
    assert isinstance(back, DiffusionTransformerHybridImagePolicy) and back.image_cfg == pol.image_cfg
    assert torch.equal(back.predict_action(obs, torch.Generator().manual_seed(1))["action"], ref)


def test_mismatched_condition_width_and_missing_camera_are_clear_errors():
    cfg = image_policy().cfg
    with pytest.raises(ValueError, match="cond_dim"):
        DiffusionTransformerHybridImagePolicy(cfg, ImageEncoderConfig(cameras=CAMS[:1], image_size=32, crop_size=24,
                                                                      num_kp=4, feature_dim=8, width=16))
    obs = image_obs(2)
    del obs[CAMS[1]]
    with pytest.raises(KeyError, match="robot0_eye_in_hand_image"):
        image_policy().predict_action(obs)


def test_image_hdf5_round_trip_keeps_uint8_frames_compressed(tmp_path):
    import h5py

    from robot_suite.robomimic import Demo, read_demos, write_demos

    g = np.random.default_rng(0)
    frames = np.zeros((4, 32, 32, 3), dtype=np.uint8)
    frames[:, 8:16, 8:16] = g.integers(0, 256, size=(4, 8, 8, 3), dtype=np.uint8)
    demo = Demo(obs={"agentview_image": frames, "robot0_eef_pos": g.normal(size=(4, 3))},
                actions=g.normal(size=(4, 7)), rewards=np.zeros(4), dones=np.arange(4) == 3)
    write_demos(tmp_path / "img.hdf5", [demo], {"env_name": "Lift"})
    back = read_demos(tmp_path / "img.hdf5", obs_keys=["agentview_image", "robot0_eef_pos"])[0]
    assert back.obs["agentview_image"].dtype == np.uint8 and np.array_equal(back.obs["agentview_image"], frames)
    with h5py.File(tmp_path / "img.hdf5") as f:
        d = f["data/demo_0/obs/agentview_image"]
        assert d.compression == "gzip" and d.chunks == (1, 32, 32, 3)
        assert f["data/demo_0/obs/robot0_eef_pos"].compression is None


class _RoboSoftmax(torch.nn.Module):
    """robomimic's spatial softmax as its checkpoints store it: ``nets`` (1x1 conv), ``pos_x``/``pos_y``
    over [-1, 1] (x along the width), ``temperature``; keypoints flattened as (x, y) pairs."""

    def __init__(self, c, h, w, k):
        super().__init__()
        self.nets = torch.nn.Conv2d(c, k, 1)
        px, py = np.meshgrid(np.linspace(-1, 1, w), np.linspace(-1, 1, h))
        self.register_buffer("pos_x", torch.tensor(px.reshape(1, -1), dtype=torch.float32))
        self.register_buffer("pos_y", torch.tensor(py.reshape(1, -1), dtype=torch.float32))
        self.register_buffer("temperature", torch.ones(1))
        self.k, self.hw = k, h * w

    def forward(self, x):
        a = torch.softmax(self.nets(x).reshape(-1, self.hw) / self.temperature, dim=-1)
        xy = torch.cat([(self.pos_x * a).sum(1, keepdim=True), (self.pos_y * a).sum(1, keepdim=True)], 1)
        return xy.reshape(-1, self.k * 2)


class _Trunk(torch.nn.Module):
    def __init__(self, nets):
        super().__init__()
        self.nets = nets

    def forward(self, x):
        return self.nets(x)


class _RoboCore(torch.nn.Module):
    """robomimic's VisualCore over torchvision's ResNet-18 with BatchNorm swapped for GroupNorm(C // 16),
    as Diffusion Policy builds it: each submodule by attribute and again in ``nets``."""

    def __init__(self, crop, k, feat):
        super().__init__()
        import torchvision

        net = torchvision.models.resnet18(weights=None)

        def swap(m):
            for name, child in m.named_children():
                if isinstance(child, torch.nn.BatchNorm2d):
                    setattr(m, name, torch.nn.GroupNorm(child.num_features // 16, child.num_features))
                else:
                    swap(child)
        swap(net)
        self.backbone = _Trunk(torch.nn.Sequential(*list(net.children())[:-2]))
        side = -(-crop // 32)
        self.pool = _RoboSoftmax(512, side, side, k)
        self.nets = torch.nn.Sequential(self.backbone, self.pool, torch.nn.Flatten(1), torch.nn.Linear(2 * k, feat))

    def forward(self, x):
        return self.nets(x)


def test_official_hybrid_image_checkpoint_loads_and_computes_the_official_condition(tmp_path):
    """An official-layout hybrid-image checkpoint (keys interleaved in shape_meta, pixels mapped to
    [-1, 1]) loads; the loaded policy's denoiser output equals the official encoder + transformer's."""
    from tts.adapters.diffusion_policy import DPTransformerConfig, TransformerForDiffusion

    size, crop, k, feat = 72, 64, 4, 8
    meta = {"obs": {"agentview_image": {"shape": [3, size, size], "type": "rgb"},
                    "robot0_eef_pos": {"shape": [3]},
                    "robot0_eye_in_hand_image": {"shape": [3, size, size], "type": "rgb"},
                    "robot0_gripper_qpos": {"shape": [2]}},
            "action": {"shape": [7]}}
    cams, low = ["agentview_image", "robot0_eye_in_hand_image"], {"robot0_eef_pos": 3, "robot0_gripper_qpos": 2}
    torch.manual_seed(1)  # torchvision's initialisation keeps the features input-dependent; peaked keypoint maps
    cores = torch.nn.ModuleDict({c: _RoboCore(crop, k, feat) for c in cams})
    for i, c in enumerate(cams):
        randomize(cores[c].pool, seed=i + 1, std=0.5)
    arch = dict(n_layer=2, n_head=2, n_emb=32, p_drop_emb=0.0, p_drop_attn=0.1, causal_attn=True, time_as_cond=True,
                obs_as_cond=True, n_cond_layers=0)
    ref = randomize(TransformerForDiffusion(DPTransformerConfig(input_dim=7, output_dim=7, horizon=10, n_obs_steps=2,
                                                                cond_dim=2 * feat + 5, **arch)), seed=5).eval()
    g = torch.Generator().manual_seed(0)
    norms = {key: (torch.rand(d, generator=g) + 0.5, torch.randn(d, generator=g)) for key, d in {**low, "action": 7}.items()}
    norms.update({c: (torch.tensor([2.0]), torch.tensor([-1.0])) for c in cams})
    sd = {f"model.{n}": v for n, v in ref.state_dict().items()}
    sd.update({f"obs_encoder.obs_nets.{n}": v for n, v in cores.state_dict().items()})
    for key, (scale, offset) in norms.items():
        sd[f"normalizer.params_dict.{key}.scale"], sd[f"normalizer.params_dict.{key}.offset"] = scale, offset
    assert "obs_encoder.obs_nets.agentview_image.backbone.nets.4.0.bn1.weight" in sd  # the stored layout
    cfg = {"horizon": 10, "n_obs_steps": 2, "n_action_steps": 8,
           "policy": {"_target_": "diffusion_policy.policy.diffusion_transformer_hybrid_image_policy."
                                  "DiffusionTransformerHybridImagePolicy", "shape_meta": meta, "crop_shape": [crop, crop],
                      "obs_encoder_group_norm": True, "eval_fixed_crop": True, "num_inference_steps": 10,
                      "noise_scheduler": {"num_train_timesteps": 100}, **arch}}
    path = tmp_path / "epoch=0100.ckpt"
    torch.save({"cfg": cfg, "state_dicts": {"model": sd, "ema_model": sd}}, path)
    pol = load_policy(path)
    assert isinstance(pol, DiffusionTransformerHybridImagePolicy) and pol.image_cfg.width == 64

    obs = {key: np.random.default_rng(1).normal(size=(3, 2, d)).astype(np.float32) for key, d in low.items()}
    for i, c in enumerate(cams):
        obs[c] = np.random.default_rng(2 + i).integers(0, 256, size=(3, 2, size, size, 3), dtype=np.uint8)
    feats = []
    with torch.no_grad():
        for key in meta["obs"]:  # the official encoder: shape_meta order, normalised, centre crop
            x = torch.as_tensor(obs[key]).reshape(6, *obs[key].shape[2:]).float()
            scale, offset = norms[key]
            if key in cams:
                top = (size - crop) // 2
                x = (x.permute(0, 3, 1, 2) / 255.0 * scale + offset)[..., top:top + crop, top:top + crop]
                x = torch.relu(cores[key](x))  # robomimic's ObservationEncoder: ReLU on each camera's features
            else:
                x = x * scale + offset
            feats.append(x)
        cond = torch.cat(feats, -1).reshape(3, 2, -1)
        a, t = torch.randn(3, 10, 7, generator=g), torch.tensor(37)
        torch.testing.assert_close(pol.model(a, t, pol.condition(obs)), ref(a, t, cond), atol=2e-5, rtol=1e-4)
    assert torch.equal(pol.action_normalizer.scale, norms["action"][0])

    bad = dict(sd)
    bad["obs_encoder.obs_nets.agentview_image.nets.1.temperature"] = torch.tensor([2.0])
    torch.save({"cfg": cfg, "state_dicts": {"model": bad}}, path)
    with pytest.raises(ValueError, match="temperature"):
        load_policy(path)
    cfg["policy"]["obs_encoder_group_norm"] = False
    torch.save({"cfg": cfg, "state_dicts": {"model": sd}}, path)
    with pytest.raises(ValueError, match="GroupNorm"):
        load_policy(path)
