"""TaylorSeer-style forecast for timestep reuse (``tts.accelerate(..., forecast=O)``)."""
import pytest
import torch
import torch.nn as nn

import tts
from tts.cache import TaylorSlot


class PolyBlock(nn.Module):
    """One branch whose output is a polynomial in the input's time coordinate (no residual feedback)."""

    def __init__(self, d=4, quad=0.25):
        super().__init__()
        self.w = nn.Parameter(torch.randn(d))
        self.quad = quad

    def branch(self, h):
        s = h[..., :1]  # the time coordinate
        return self.w * (0.5 + s + self.quad * s * s)

    def forward(self, h):
        return h + self.branch(h)


class PolyModel(nn.Module):
    def __init__(self, quad=0.25):
        super().__init__()
        self.blocks = nn.ModuleList([PolyBlock(quad=quad)])

    def forward(self, x, t):
        h = x + torch.zeros_like(x)
        h[..., :1] = t.float().reshape(-1, 1, 1) / 10
        for b in self.blocks:
            h = b(h)
        return h


def spec():
    def fwd(block, run, h):
        return h + run(0, block.branch, h)

    return tts.BlockSpec("poly", (tts.BranchSpec("f", "mlp", ()),), fwd)


def run_steps(model, plan, forecast, ts, batch=1):
    outs = []
    with torch.no_grad(), tts.accelerate(model, ("timestep",), plan=plan, blocks={"blocks.*": spec()},
                                         forecast=forecast):
        for t in ts:
            outs.append(model(torch.zeros(batch, 3, 4), torch.full((batch,), t)))
    return outs


def test_forecast_is_exact_on_linear_trajectories_and_order0_is_plain_reuse():
    torch.manual_seed(0)
    ts = list(range(20, 8, -1))  # 12 steps, t moves by 1 per step
    grid = [[0] if k % 4 == 0 else [2] for k in range(len(ts))]  # compute at 0, 4, 8
    plan = tts.plans.from_tensor(grid)
    linear = PolyModel(quad=0.0)
    with torch.no_grad():
        dense = [linear(torch.zeros(1, 3, 4), torch.full((1,), t)) for t in ts]
    plain = run_steps(linear, plan, 0, ts)
    assert torch.equal(plain[5][..., 1:], plain[4][..., 1:])  # order 0: the cached delta as is
    o1 = run_steps(linear, plan, 1, ts)
    for k in range(5, 12):  # two computes known: a linear trajectory is forecast exactly
        torch.testing.assert_close(o1[k], dense[k], rtol=1e-5, atol=1e-6)
    curved = PolyModel(quad=0.25)
    curved.load_state_dict(linear.state_dict())
    with torch.no_grad():
        dense = [curved(torch.zeros(1, 3, 4), torch.full((1,), t)) for t in ts]
    errs = [float((run_steps(curved, plan, o, ts)[11] - dense[11]).abs().max()) for o in (0, 1, 2)]
    assert errs[2] < errs[1] < errs[0]  # higher orders track a curved trajectory better
    with pytest.raises(ValueError, match="timestep direction"):
        tts.accelerate(linear, ("forward",), blocks={"blocks.*": spec()}, forecast=1)


def test_forecast_per_sample_history_equals_each_sample_alone():
    torch.manual_seed(1)
    model = PolyModel()
    ts = list(range(30, 18, -1))
    dec = torch.full((2, len(ts), 1), 2, dtype=torch.int8)
    dec[:, 0] = 0
    dec[0, [3, 6, 9], 0] = 0  # sample 0 computes at 3, 6, 9; sample 1 at 2, 7
    dec[1, [2, 7], 0] = 0
    together = run_steps(model, tts.plans.from_tensor(dec), 2, ts, batch=2)
    for s in range(2):
        alone = run_steps(model, tts.plans.from_tensor(dec[s]), 2, ts)
        for k in range(len(ts)):
            torch.testing.assert_close(together[k][s:s + 1], alone[k], rtol=1e-5, atol=1e-6)


def test_taylor_slot_rows_that_did_not_compute_keep_their_history():
    d0 = torch.zeros(2, 3)
    slot = TaylorSlot(d0, 0, dim=0).update(torch.ones(2, 3), 2, order=1)  # slope 0.5 per step
    slot = slot.update_rows(torch.tensor([1]), torch.full((1, 3), 5.0), 4, order=1)  # row 1: slope 2
    f = slot.forecast(6)
    torch.testing.assert_close(f[0], torch.full((3,), 1.0 + 0.5 * 4))
    torch.testing.assert_close(f[1], torch.full((3,), 5.0 + 2.0 * 2))
