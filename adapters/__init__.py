"""Backbone adapters, shipped as ``tts.adapters``: importing this package registers the built-in
block families and model adapters with the core. Heavy libraries (diffusers, timm) are imported
only when a model that needs them is accelerated."""
from . import torch_layers, diffusion_policy, dp_policy, dit, diffusers_blocks, dit_diffusers  # noqa: F401  (registration)
