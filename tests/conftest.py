"""Small models of every supported block family, with non-trivial random weights."""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
# the eval/ scripts are importable as modules in every test (import robot, search_static, ...)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "eval"))

import pytest
import torch
import torch.nn as nn

# TTS_TEST_THREADS=1 next to a background job: oversubscribed OpenMP threads spin and crawl
torch.set_num_threads(int(os.environ.get("TTS_TEST_THREADS", "2")))


@pytest.fixture(scope="module")
def one_thread():
    """Torch on one thread for a module (heavy tests on small CI machines); restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def randomize(model: nn.Module, seed: int = 0, std: float = 0.1) -> nn.Module:
    """Replace every floating parameter by N(0, std) (zero-initialised adaLN gates would hide bugs)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            if p.dtype.is_floating_point and p.numel():
                p.copy_(torch.randn(p.shape, generator=g) * std)
    return model


class TorchStack(nn.Module):
    """A denoiser made of nn.Transformer{Encoder,Decoder}Layers: forward(x, t, memory)."""

    def __init__(self, kind: str, norm_first: bool, batch_first: bool = True, layers: int = 3, d: int = 32):
        super().__init__()
        self.kind, self.batch_first = kind, batch_first
        self.inp = nn.Linear(4, d)
        cls = nn.TransformerDecoderLayer if kind == "decoder" else nn.TransformerEncoderLayer
        self.layers = nn.ModuleList(
            cls(d, 4, 2 * d, dropout=0.1, activation="gelu", batch_first=batch_first, norm_first=norm_first)
            for _ in range(layers)
        )
        self.out = nn.Linear(d, 4)
        self.register_buffer("mask", nn.Transformer.generate_square_subsequent_mask(6))

    def forward(self, x, t, memory=None):
        h = self.inp(x) + t.float().reshape(-1, 1, 1) * 0.01
        if not self.batch_first:
            h = h.transpose(0, 1)
            memory = None if memory is None else memory.transpose(0, 1)
        for layer in self.layers:
            if self.kind == "decoder":
                h = layer(h, memory, tgt_mask=self.mask)
            else:
                h = layer(h, src_mask=self.mask)
        if not self.batch_first:
            h = h.transpose(0, 1)
        return self.out(h)


def torch_stack_inputs(batch: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, 6, 4, generator=g), torch.full((batch,), 7), torch.randn(batch, 3, 32, generator=g)


def tiny_dit_diffusers():
    from diffusers import DiTTransformer2DModel

    return DiTTransformer2DModel(
        num_attention_heads=2, attention_head_dim=16, in_channels=4, out_channels=8, num_layers=3,
        sample_size=8, patch_size=2, num_embeds_ada_norm=10, norm_type="ada_norm_zero",
    )


class PixArtStyle(nn.Module):
    """BasicTransformerBlocks with ada_norm_single and cross-attention, timestep given as [B, 6D]."""

    def __init__(self, d: int = 32, layers: int = 2, with_cross: bool = True, norm_type: str = "ada_norm_single"):
        super().__init__()
        from diffusers.models.attention import BasicTransformerBlock

        self.inp = nn.Linear(4, d)
        self.t_proj = nn.Linear(1, 6 * d)
        self.blocks = nn.ModuleList(
            BasicTransformerBlock(d, 2, d // 2, cross_attention_dim=d if with_cross else None,
                                  norm_type=norm_type, norm_elementwise_affine=norm_type != "ada_norm_single")
            for _ in range(layers)
        )
        self.out = nn.Linear(d, 4)

    def forward(self, x, t, context):
        h = self.inp(x)
        temb = self.t_proj(t.float().reshape(-1, 1))
        for b in self.blocks:
            h = b(h, encoder_hidden_states=context, timestep=temb)
        return self.out(h)


def tiny_official_dit():
    from tts.adapters.dit import DiT, DiTConfig

    return DiT(DiTConfig(input_size=8, patch_size=2, in_channels=4, hidden_size=32, depth=3, num_heads=2,
                         num_classes=10, learn_sigma=True))


def tiny_dp(n_cond_layers: int = 0, causal: bool = True, layers: int = 3):
    from tts.adapters.diffusion_policy import DPTransformerConfig, TransformerForDiffusion

    cfg = DPTransformerConfig(input_dim=5, output_dim=5, horizon=6, n_obs_steps=2, cond_dim=7, n_layer=layers,
                              n_head=2, n_emb=32, p_drop_attn=0.3, p_drop_emb=0.0, causal_attn=causal,
                              obs_as_cond=True, n_cond_layers=n_cond_layers)
    return TransformerForDiffusion(cfg)


# (name, builder, inputs(batch) -> args tuple); every model is called as model(*args)
FAMILIES = {
    "decoder_prenorm": (lambda: TorchStack("decoder", True),
                        lambda b: torch_stack_inputs(b)),
    "decoder_postnorm": (lambda: TorchStack("decoder", False),
                         lambda b: torch_stack_inputs(b)),
    "decoder_seqfirst": (lambda: TorchStack("decoder", True, batch_first=False),
                         lambda b: torch_stack_inputs(b)),
    "encoder_prenorm": (lambda: TorchStack("encoder", True), lambda b: torch_stack_inputs(b)[:2]),
    "encoder_postnorm": (lambda: TorchStack("encoder", False), lambda b: torch_stack_inputs(b)[:2]),
    "diffusers_dit": (tiny_dit_diffusers,
                      lambda b: (torch.randn(b, 4, 8, 8, generator=torch.Generator().manual_seed(1)),
                                 torch.full((b,), 5), torch.arange(b) % 10)),
    "diffusers_pixart": (PixArtStyle,
                         lambda b: (torch.randn(b, 6, 4, generator=torch.Generator().manual_seed(2)),
                                    torch.full((b,), 3), torch.randn(b, 5, 32, generator=torch.Generator().manual_seed(3)))),
    "diffusers_layernorm_noattn2": (lambda: PixArtStyle(with_cross=False, norm_type="layer_norm"),
                                    lambda b: (torch.randn(b, 6, 4, generator=torch.Generator().manual_seed(2)),
                                               torch.full((b,), 3), torch.randn(b, 5, 32))),
    "official_dit": (tiny_official_dit,
                     lambda b: (torch.randn(b, 4, 8, 8, generator=torch.Generator().manual_seed(4)),
                                torch.full((b,), 5), torch.arange(b) % 10)),
    "diffusion_policy": (tiny_dp,
                         lambda b: (torch.randn(b, 6, 5, generator=torch.Generator().manual_seed(5)),
                                    torch.tensor(9), torch.randn(b, 2, 7, generator=torch.Generator().manual_seed(6)))),
}


@pytest.fixture(params=sorted(FAMILIES))
def family(request):
    build, inputs = FAMILIES[request.param]
    model = randomize(build()).eval()
    return request.param, model, inputs
