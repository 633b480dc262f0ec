"""The custom-block example in docs/custom_blocks.md works as documented."""
import re
from pathlib import Path

import torch
import torch.nn as nn

import tts

DOC = Path(__file__).resolve().parents[1] / "docs" / "custom_blocks.md"


def _example_namespace():
    code = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)[0]
    code = "\n".join(l for l in code.splitlines() if not l.startswith("acc = "))
    ns: dict = {}
    exec(code, ns)
    return ns


class Net(nn.Module):
    def __init__(self, block_cls, d=16, n=3):
        super().__init__()
        self.blocks = nn.ModuleList(block_cls(d) for _ in range(n))

    def forward(self, x, t, cond):
        for b in self.blocks:
            x = b(x, cond)
        return x


def test_custom_block_example():
    ns = _example_namespace()
    model = Net(ns["MyBlock"]).eval()
    x, cond = torch.randn(2, 5, 16), torch.randn(2, 5, 16)
    with torch.no_grad():
        ref = model(x, torch.tensor(3), cond)
    with tts.accelerate(model, ("forward", "timestep"), blocks={"blocks.*": ns["spec"]}, fast_dense=False) as acc:
        with torch.no_grad():
            assert torch.equal(model(x, torch.tensor(3), cond), ref)
        assert acc.branch_names == [f"blocks.{i}.{n}" for i in range(3) for n in ("attn", "mlp")]
    with tts.accelerate(model, ("forward", "timestep"), blocks={"blocks.*": ns["spec"]}, sparsity=0.8) as acc:
        with torch.no_grad():
            for k in range(10):
                model(x, torch.tensor(10 - k), cond)
        assert acc.summary().sparsity() == 0.8
        dense, realised = acc.summary().macs(acc.summary().calls[-1])
        assert realised < 0.3 * dense
