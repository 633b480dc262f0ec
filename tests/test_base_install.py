"""A base install (torch, numpy, tqdm, safetensors; no extras) accelerates a plain PyTorch transformer.

The check runs in a fresh interpreter in which the optional libraries cannot be imported, so an
import of one of them anywhere on the path ``import tts`` -> ``tts.accelerate(nn.TransformerEncoder)``
fails the test.
"""
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# the extras of pyproject.toml (and what they pull in): none of them may be needed for torch-only models
OPTIONAL = ("diffusers", "timm", "robosuite", "mujoco", "h5py", "accelerate", "torchvision", "scipy",
            "sklearn", "matplotlib", "pytorch_fid", "huggingface_hub", "transformers")

SCRIPT = textwrap.dedent(
    """
    import importlib.abc
    import sys

    BLOCKED = set(sys.argv[1].split(","))

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"{name} is not installed (blocked by the base-install test)")
            return None

    sys.meta_path.insert(0, Block())

    import torch
    import torch.nn as nn

    import tts

    torch.set_num_threads(1)
    torch.manual_seed(0)
    layer = nn.TransformerEncoderLayer(16, 2, 32, dropout=0.0, batch_first=True, norm_first=True)
    model = nn.TransformerEncoder(layer, 3, enable_nested_tensor=False).eval()
    xs = [torch.randn(2, 5, 16) for _ in range(4)]

    def sample(acc=None):
        if acc is not None:
            acc.new_call()  # no timestep argument: mark the sampling call explicitly
        with torch.no_grad():
            return [model(x).clone() for x in xs]

    ref = sample()
    with tts.accelerate(model, ("timestep",)) as acc:
        dense = sample(acc)
    assert all(torch.equal(a, b) for a, b in zip(dense, ref)), "dense plan is not bit-exact"

    calls = []
    with tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(2)) as acc:
        sample(acc)  # the first call also profiles MACs with one extra dense step
        hook = model.layers[1].linear1.register_forward_hook(lambda *a: calls.append(1))
        sparse = sample(acc)
        hook.remove()
        last = acc.summary().calls[-1]
    assert len(calls) == 2, f"the MLP of layer 1 ran {len(calls)} times in 4 steps, expected 2"
    assert int((last.decisions() == tts.plans.TIMESTEP).sum()) == 2 * 2 * 6  # 2 steps x 2 samples x 6 branches
    assert (sparse[1] - ref[1]).abs().max() > 1e-4  # step 1 really reused step 0's branch outputs
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
    assert not leaked, leaked
    print("ok")
    """
)


def test_base_install_accelerates_a_torch_transformer_without_extras():
    proc = subprocess.run([sys.executable, "-c", SCRIPT, ",".join(OPTIONAL)], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip().endswith("ok")
