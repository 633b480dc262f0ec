"""Analytic MACs agree with torch.utils.flop_counter on the dense model and on sparse runs."""
import random

import pytest
import torch

import tts
from tts.flops import flop_counter_macs
from helpers import as_tensor


def _directions(name):
    return ("forward", "timestep") if "dit" in name else ("forward", "timestep", "rollout")


def test_dense_macs_match_flop_counter(family):
    name, model, inputs = family
    args = inputs(3)
    # autograd on: FlopCounterMode sees nothing inside PyTorch's fused encoder-layer kernel
    # (eval + no_grad), which would make it report ~0 for that family
    with torch.enable_grad():
        counted = flop_counter_macs(lambda: model(*args))
    with tts.accelerate(model, _directions(name)) as acc, torch.no_grad():
        model(*args)
        per_row = acc.macs_per_row
    analytic = sum(per_row.values()) * 3
    assert analytic == counted, f"{name}: analytic {analytic} vs FlopCounterMode {counted}"
    branch = sum(v for k, v in per_row.items() if k[0] == "branch")
    assert branch > 0.5 * sum(per_row.values())  # the branches are where the work is


def _sample(model, args, steps):
    x = args[0]
    for k in range(steps):
        x = as_tensor(model(x, torch.full_like(torch.as_tensor(args[1]), 20 - k), *args[2:])) [:, : x.shape[1]]
    return x


@pytest.mark.parametrize("batch", [1, 3])
def test_realised_macs_match_flop_counter(family, batch):
    name, model, inputs = family
    args = inputs(batch)
    steps = 4
    acc = tts.accelerate(model, ("forward", "timestep"), plan=None)
    acc.remove()
    nb = acc.num_branches
    rng = random.Random(batch)
    dec = torch.tensor([[[rng.choice([0, 1, 2]) for _ in range(nb)] for _ in range(steps)] for _ in range(batch)])
    with tts.accelerate(model, ("forward", "timestep"), plan=tts.plans.from_tensor(dec)) as acc, torch.no_grad():
        _sample(model, args, steps)  # first call: profiles MACs (one extra dense dry-run step)
        counted = flop_counter_macs(lambda: _sample(model, args, steps))
        dense, realised = acc.summary().macs(acc.summary().calls[-1])
    assert realised == counted, f"{name}: summary {realised} vs FlopCounterMode {counted}"
    assert realised < dense
