"""Class-conditional DiT sampling with tts: condition memory, sample_dit, checkpoints, eval/imagenet.py."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("timm")
pytest.importorskip("diffusers")

import tts  # noqa: E402
from conftest import randomize, tiny_official_dit  # noqa: E402
from tts.adapters.dit import (DIT_CONFIGS, DiT, DiTConfig, dit_config_from_state_dict, load_dit,  # noqa: E402
                              sample_dit, save_dit)

REPO = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest: 1 torch thread for this module


def _model(seed: int = 0) -> DiT:
    return randomize(tiny_official_dit(), seed=seed).eval()  # 8x8x4, hidden 32, depth 3, 10 classes


def _noise(b: int, c: int = 4, size: int = 8, seed: int = 0) -> torch.Tensor:
    return torch.randn(b, c, size, size, generator=torch.Generator().manual_seed(seed))


# ------------------------------------------------------------------------------ condition memory
def test_condition_memory_equals_per_step_embedders_and_forward_with_c_is_exact():
    model = _model()
    timesteps = torch.tensor([999, 500, 20, 0])
    y = torch.tensor([1, 7, 10])  # 10 = the null class
    x = _noise(3)
    with torch.no_grad():
        memory = model.condition_memory(timesteps, y)
        assert memory.shape == (3, 4, 1, 32)
        for k, t in enumerate(timesteps):
            tb = t.expand(3)
            per_step = model.t_embedder(tb) + model.y_embedder(y, False)
            # one batched matmul over K rows vs B rows: equal up to the last bit of float32 round-off
            torch.testing.assert_close(memory[:, k, 0], per_step, rtol=1e-6, atol=1e-5)
            plain = model(x, tb, y)
            assert torch.equal(model(x, tb, y, c=per_step), plain)  # the embedders are all c= skips
            assert torch.equal(model(x, tb, y, c=per_step[:, None]), plain)  # memory[:, k] layout
            torch.testing.assert_close(model(x, tb, y, c=memory[:, k]), plain, rtol=0, atol=1e-5)
        with pytest.raises(ValueError, match=r"c must be the conditioning vector \[batch=3, hidden=32\]"):
            model(x, timesteps[:3], y, c=memory[:2, 0])


def test_adapter_declares_the_condition_memory():
    model = _model()
    target = tts.resolve_target(model)
    assert target.condition == (model, "condition_memory") and target.supports_rollout is False


# ------------------------------------------------------------------------------------- sampling
def _reference_ddim_cfg(model: DiT, labels: torch.Tensor, noise: torch.Tensor, steps: int, scale: float) -> torch.Tensor:
    """Independent DDIM (eta 0) with DiT's linear betas in float64 and the official forward_with_cfg."""
    betas = torch.linspace(1e-4, 0.02, 1000, dtype=torch.float64)
    abar = torch.cumprod(1 - betas, 0)
    ts = list(range(0, 1000, 1000 // steps))[::-1]
    x = noise.double()
    y = torch.cat([labels, torch.full_like(labels, model.config.num_classes)])
    with torch.no_grad():
        for i, t in enumerate(ts):
            xin = torch.cat([x, x]).float()
            eps = model.forward_with_cfg(xin, torch.full((len(xin),), t), y, scale)[: len(x), : model.in_channels].double()
            a, a_prev = abar[t], (abar[ts[i + 1]] if i + 1 < len(ts) else torch.tensor(1.0, dtype=torch.float64))
            x0 = (x - (1 - a).sqrt() * eps) / a.sqrt()
            x = a_prev.sqrt() * x0 + (1 - a_prev).sqrt() * eps
    return x.float()


def test_sample_dit_is_ddim_with_cfg_and_dense_plan_is_bit_identical():
    model = randomize(tiny_official_dit(), seed=1, std=0.03).eval()
    labels, noise = torch.tensor([0, 3, 9]), _noise(3)
    ref = sample_dit(model, labels, steps=5, cfg_scale=1.5, noise=noise)
    assert ref.shape == (3, 4, 8, 8)
    torch.testing.assert_close(ref, _reference_ddim_cfg(model, labels, noise, 5, 1.5), rtol=1e-4, atol=1e-4)
    with tts.accelerate(model, ("forward", "timestep")) as acc:  # default plan: dense
        out = sample_dit(model, labels, steps=5, cfg_scale=1.5, noise=noise)
        assert acc.summary().sparsity() == 0.0 and len(acc.calls) == 1 and acc.calls[0].batch == 6
    assert torch.equal(out, ref)
    assert torch.equal(sample_dit(model, labels, steps=5, cfg_scale=1.5, noise=noise), ref)  # removed cleanly
    with pytest.raises(ValueError, match=r"labels must lie in \[0, 10\)"):
        sample_dit(model, torch.tensor([10]), steps=2)


def test_learned_pruner_on_sample_dit_decides_per_row():
    model = _model()
    nb = 2 * model.config.depth
    pruner = randomize(tts.Pruner(tts.PrunerConfig(memory_dim=32, num_branches=nb, directions=("forward", "timestep"))),
                       seed=3, std=0.5)
    labels, noise, K = torch.tensor([0, 1, 2, 3]), _noise(4), 6
    dense = sample_dit(model, labels, steps=K, noise=noise)
    with tts.accelerate(model, ("forward", "timestep"), pruner=pruner, sparsity=0.5) as acc:
        out = sample_dit(model, labels, steps=K, noise=noise)
        out2 = sample_dit(model, labels, steps=K, noise=noise)  # a second call is detected from the timesteps
        summary = acc.summary()
    assert len(summary.calls) == 2 and torch.equal(out, out2)
    d = summary.calls[-1].decisions()  # [K, 2B, nb]: cond rows 0..3, uncond rows 4..7
    assert d.shape == (K, 8, nb)
    assert summary.sparsity() == pytest.approx(0.5, abs=0.02)
    assert bool((d[:, :4] != d[:, 4:]).any())  # cond and uncond halves take their own decisions
    dense_macs, realised = summary.macs(summary.calls[-1])
    assert realised < dense_macs
    assert torch.isfinite(out).all() and not torch.equal(out, dense)
    with tts.accelerate(model, ("forward", "timestep"), pruner=pruner, parallel=False) as acc:  # argmax mode
        sample_dit(model, labels, steps=K, noise=noise)
        assert acc.summary().calls[-1].decisions().shape == (K, 8, nb)


# ----------------------------------------------------------------------------------- checkpoints
def _official_keys(depth: int) -> set[str]:
    keys = {"pos_embed", "x_embedder.proj.weight", "x_embedder.proj.bias", "y_embedder.embedding_table.weight"}
    keys |= {f"t_embedder.mlp.{i}.{p}" for i in (0, 2) for p in ("weight", "bias")}
    for layer in ("final_layer.linear", "final_layer.adaLN_modulation.1"):
        keys |= {f"{layer}.weight", f"{layer}.bias"}
    for n in range(depth):
        for layer in ("attn.qkv", "attn.proj", "mlp.fc1", "mlp.fc2", "adaLN_modulation.1"):
            keys |= {f"blocks.{n}.{layer}.weight", f"blocks.{n}.{layer}.bias"}
    return keys


def test_official_state_dict_and_our_format_load(tmp_path):
    model = _model()
    state = model.state_dict()
    assert set(state) == _official_keys(3)
    path = tmp_path / "DiT-tiny.pt"
    torch.save(state, path)
    loaded = load_dit(path, num_heads=2)
    assert loaded.config == model.config and not loaded.training
    assert all(torch.equal(v, state[k]) for k, v in loaded.state_dict().items())
    torch.save({"ema": state, "model": {}}, tmp_path / "train.pt")  # an official training checkpoint's layout
    assert load_dit(tmp_path / "train.pt", num_heads=2).config == model.config
    with pytest.raises(ValueError, match="cannot infer the number of attention heads"):
        load_dit(path)
    save_dit(model, tmp_path / "ours", metadata={"note": "test"})
    ours = load_dit(tmp_path / "ours")
    assert ours.config == model.config and ours.checkpoint_info["metadata"] == {"note": "test"}
    assert all(torch.equal(v, state[k]) for k, v in ours.state_dict().items())
    assert load_dit(tmp_path / "ours.safetensors").config == model.config


def test_config_of_an_official_xl_checkpoint_from_shapes():
    e = lambda *s: torch.empty(s, device="meta")  # noqa: E731
    state = {"x_embedder.proj.weight": e(1152, 4, 2, 2), "pos_embed": e(1, 256, 1152),
             "y_embedder.embedding_table.weight": e(1001, 1152), "final_layer.linear.weight": e(32, 1152),
             "blocks.0.mlp.fc1.weight": e(4608, 1152), "blocks.27.attn.qkv.weight": e(3456, 1152)}
    assert dit_config_from_state_dict(state) == DIT_CONFIGS["DiT-XL/2"]  # 256x256: 32x32 latents, 1000 classes
    assert dit_config_from_state_dict(state, "DiT-XL/2").num_heads == 16
    with pytest.raises(ValueError, match="DiT-B/2 has hidden 768"):
        dit_config_from_state_dict(state, "DiT-B/2")


def test_missing_model_names_what_to_download(tmp_path):
    for missing in (tmp_path / "nothing", tmp_path / "DiT-XL-2-256x256.pt"):
        with pytest.raises(FileNotFoundError, match="no DiT checkpoint at") as err:
            load_dit(missing)
        assert "https://dl.fbaipublicfiles.com/DiT/models/DiT-XL-2-256x256.pt" in str(err.value)
        assert "eval/train_dit.py" in str(err.value)
    import imagenet

    with pytest.raises(FileNotFoundError, match="no DiT checkpoint"):
        imagenet.main(["--model", str(tmp_path / "nothing"), "--num-samples", "2", "--out", str(tmp_path / "s.npz")])
    with pytest.raises(ValueError, match="malformed method 'pruner'"):
        imagenet.main(["--model", str(tmp_path / "nothing"), "--method", "pruner", "--out", str(tmp_path / "s.npz")])


# ------------------------------------------------------------------------------ eval/imagenet.py
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_imagenet_script_two_processes_equal_one_process(tmp_path):
    pytest.importorskip("accelerate")
    cfg = DiTConfig(input_size=8, patch_size=2, in_channels=3, hidden_size=32, depth=2, num_heads=2, num_classes=5)
    save_dit(randomize(DiT(cfg), std=0.03), tmp_path / "tiny")
    pruner = randomize(tts.Pruner(tts.PrunerConfig(memory_dim=32, num_branches=4, directions=("forward", "timestep"))),
                       seed=2, std=0.5)
    tts.save_pruner(pruner, tmp_path / "pruner")
    common = ["eval/imagenet.py", "--model", str(tmp_path / "tiny"), "--method",
              f"pruner:{tmp_path / 'pruner'}@0.5", "--steps", "4", "--num-samples", "8", "--batch", "4",
              "--threads", "1", "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1")
    launch = [sys.executable, "-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes", "2",
              "--num_machines", "1", "--mixed_precision", "no", "--dynamo_backend", "no",
              "--main_process_port", str(_free_port())]
    two = subprocess.run(launch + common + ["--out", str(tmp_path / "two.npz")], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=300)
    assert two.returncode == 0, two.stderr[-3000:]
    one = subprocess.run([sys.executable] + common + ["--out", str(tmp_path / "one.npz")], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=300)
    assert one.returncode == 0, one.stderr[-3000:]
    with np.load(tmp_path / "two.npz") as z2, np.load(tmp_path / "one.npz") as z1:
        assert z2["arr_0"].shape == (8, 8, 8, 3) and z2["arr_0"].dtype == np.uint8
        assert z2["arr_1"].tolist() == [0, 1, 2, 3, 4, 0, 1, 2]
        assert len(np.unique(z2["arr_0"])) > 20  # not a saturated image
        assert np.array_equal(z2["arr_0"], z1["arr_0"]) and np.array_equal(z2["arr_1"], z1["arr_1"])
    res = json.loads((tmp_path / "two.json").read_text())
    assert res["num_processes"] == 2 and res["distributed_type"].endswith("MULTI_CPU")
    assert res["sparsity"] == pytest.approx(0.5, abs=0.02) and res["macs_ratio"] > 1.5
    assert res["macs_ratio_with_pruner"] < res["macs_ratio"] and res["s_per_image"] > 0
    assert res["provenance"]["git_sha"] and res["image_shape"] == [8, 8, 3]
    assert json.loads((tmp_path / "one.json").read_text())["num_processes"] == 1


def test_image_pruner_trains_end_to_end_and_static_schedule_search(tmp_path):
    """eval/search_static.py --dit finds a schedule; eval/train_image_pruner.py starts from it
    (--prior: epoch 0 is exactly that schedule) and writes a pruner that eval/imagenet.py can run."""
    import search_static
    import train_image_pruner

    cfg = DiTConfig(input_size=8, patch_size=2, in_channels=4, hidden_size=32, depth=2, num_heads=2,
                    num_classes=10, learn_sigma=True)
    save_dit(randomize(DiT(cfg), std=0.03), tmp_path / "tiny")
    sched = tmp_path / "bac.json"
    search_static.main(["--dit", str(tmp_path / "tiny"), "--sparsity", "0.5", "--steps", "6", "--calls", "4",
                        "--batch", "4", "--out", str(sched)])
    doc = json.loads(sched.read_text())
    assert len(doc["grid"]) == 6 and all(len(r) == 4 for r in doc["grid"]) and doc["realised_sparsity"] == 0.5
    out = tmp_path / "pruner"
    best = train_image_pruner.main(["--model", str(tmp_path / "tiny"), "--out", str(out), "--sparsity", "0.5",
                                    "--steps", "6", "--n-train", "4", "--n-val", "4", "--batch", "4",
                                    "--epochs", "1", "--hidden", "16", "--prior", str(sched), "--val-mode", "budget",
                                    "--run-dir", str(tmp_path / "run")])
    pr = tts.load_pruner(out)
    hist = pr.metadata["history"]
    assert [h["epoch"] for h in hist] == [0, 1] and hist[0]["val_sparsity"] == pytest.approx(0.5)
    assert best["val_score"] <= hist[0]["val_score"]
    with tts.accelerate(load_dit(tmp_path / "tiny"), pr.config.directions, pruner=pr, sparsity=0.5) as acc:
        sample_dit(acc.target.denoiser, torch.arange(2), steps=6, cfg_scale=1.5, generator=torch.Generator().manual_seed(0))
        assert acc.summary().sparsity_of(acc.summary().calls[-1]) == pytest.approx(0.5)


def test_every_n_prior_grid():
    from tts.training import read_grid

    g = read_grid(Path("every_n:5"), steps=12, branches=4)
    assert g.shape == (12, 4)
    assert g[0].eq(0).all() and g[5].eq(0).all() and g[10].eq(0).all()
    assert int(g.eq(0).sum()) == 3 * 4 and int(g.eq(2).sum()) == 9 * 4
    with pytest.raises(ValueError, match="number of steps"):
        read_grid(Path("every_n:5"))


def test_prior_reuse_maps_every_reuse_decision_to_one_direction():
    """--prior-reuse rollout: the same compute steps, rollout reuse in between (single-direction variant)."""
    from tts.training import read_grid

    base = read_grid(Path("every_n:4"), steps=8, branches=3)
    g = read_grid(Path("every_n:4"), steps=8, branches=3, reuse="rollout")
    assert g.eq(0).equal(base.eq(0))  # compute steps unchanged
    assert set(g[base != 0].unique().tolist()) == {tts.plans.ROLLOUT}
    with pytest.raises(ValueError, match="unknown direction"):
        read_grid(Path("every_n:4"), steps=8, branches=3, reuse="sideways")


def test_base_sampler_of_an_image_method_and_latency_of_every_sampler_in_one_process(tmp_path):
    """``SPEC+ddim:K`` samples on K DDIM steps (the same images as ``--steps K``); eval/image_latency.py
    times fewer-step samplers and methods on their own base against one dense reference."""
    import image_latency
    import imagenet

    cfg = DiTConfig(input_size=8, patch_size=2, in_channels=3, hidden_size=32, depth=2, num_heads=2, num_classes=5)
    save_dit(randomize(DiT(cfg), std=0.03), tmp_path / "tiny")
    run = ["--model", str(tmp_path / "tiny"), "--num-samples", "2", "--batch", "2", "--no-progress"]
    based = imagenet.main(run + ["--method", "every_n:2:timestep+ddim:3", "--steps", "6",
                                 "--out", str(tmp_path / "based.npz")])
    plain = imagenet.main(run + ["--method", "every_n:2:timestep", "--steps", "3", "--out", str(tmp_path / "plain.npz")])
    assert based["steps"] == plain["steps"] == 3 and based["method"] == "every_n:2:timestep+ddim:3"
    with np.load(tmp_path / "based.npz") as a, np.load(tmp_path / "plain.npz") as b:
        assert np.array_equal(a["arr_0"], b["arr_0"])
    res = image_latency.main(["--model", str(tmp_path / "tiny"), "--steps", "4", "--batch", "1", "--trials", "1",
                              "--methods", "ddim:2", "every_n:2:timestep+ddim:3", "--out", str(tmp_path / "lat.json")])
    rows = res["rows"][0]["methods"]
    assert rows["ddim:2"]["sampler"] == "ddim:2" and rows["ddim:2"]["macs_ratio"] == pytest.approx(2.0)
    based = rows["every_n:2:timestep+ddim:3"]
    assert based["sampler"] == "ddim:3" and based["sparsity_decisions"] == pytest.approx(1 / 3)
    assert based["macs_ratio"] == pytest.approx(4 / 2, rel=0.1)  # 2 of 3 steps computed, against 4 dense steps
