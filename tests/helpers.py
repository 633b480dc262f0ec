"""Test helpers shared by several test files."""
from __future__ import annotations

import torch


def as_tensor(out):
    """Model outputs may be diffusers output objects."""
    return out.sample if hasattr(out, "sample") else out


def run(model, args):
    with torch.no_grad():
        return as_tensor(model(*args)).clone()
