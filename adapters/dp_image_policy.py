"""Image-observation Diffusion Policy (DP-T with cameras), in the Diffusion Policy / robomimic style.

Per camera (``agentview_image``, ``robot0_eye_in_hand_image``: 84x84 RGB) a ResNet-18 trunk with
GroupNorm instead of BatchNorm, spatial-softmax keypoints and a linear projection (robomimic's
``VisualCore``); random crops in training, the centre crop at test time; the low-dim proprioception
keys normalised as in the low-dim policy. Per observation frame the camera features and low-dim
keys are concatenated into one condition token, so the transformer, normaliser and schedulers are
the low-dim policy's (:class:`DiffusionTransformerLowdimPolicy`).

The observation encoder runs once per policy call, in :meth:`DiffusionTransformerHybridImagePolicy.condition`,
for all frames of the batch in one forward, never inside the denoising loop; a tts pruner reads the
condition memory built from its output (no second encoding). Weights start from scratch (nothing can
be downloaded here). ``width`` scales the trunk (64 is torchvision's ResNet-18; smaller trains on a
CPU). Parameter names follow robomimic where practical (``obs_encoder.obs_nets.<camera>.backbone``,
``.pool``, ``.linear``); the transformer (``model.*``) is Diffusion Policy's own.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn

from .dp_policy import DiffusionTransformerLowdimPolicy, PolicyConfig

__all__ = ["ImageEncoderConfig", "SpatialSoftmax", "VisualCore", "ObsEncoder", "DiffusionTransformerHybridImagePolicy",
           "CAMERAS"]

CAMERAS = ("agentview_image", "robot0_eye_in_hand_image")


@dataclass
class ImageEncoderConfig:
    """cameras: observation keys of [.., H, W, 3] uint8 images (robomimic's HWC layout); crop_size:
    the random (training) / centre (test) crop; num_kp: spatial-softmax keypoints; feature_dim: per
    camera; width: channels of the trunk's first stage (64 = ResNet-18)."""

    cameras: Sequence[str] = CAMERAS
    image_size: int = 84
    crop_size: int = 76
    num_kp: int = 32
    feature_dim: int = 64
    width: int = 64

    def __post_init__(self) -> None:
        self.cameras = tuple(self.cameras)
        if not self.cameras:
            raise ValueError("an image policy needs at least one camera")
        if not 8 <= self.crop_size <= self.image_size:
            raise ValueError(f"crop_size must be in [8, image_size={self.image_size}], got {self.crop_size}")
        if self.width % 16:
            raise ValueError(f"width must be a multiple of 16 (GroupNorm of 16 channels per group), got {self.width}")

    @property
    def features(self) -> int:
        """Width of the image features: keypoint features of every camera."""
        return len(self.cameras) * self.feature_dim


def _group_norm(channels: int) -> nn.GroupNorm:
    """Diffusion Policy's replacement of BatchNorm: groups of 16 channels."""
    return nn.GroupNorm(channels // 16, channels)


def resnet18_trunk(width: int = 64) -> nn.Sequential:
    """ResNet-18 without its pooling and classifier (stride 32), GroupNorm throughout, from scratch."""
    from torchvision.models.resnet import BasicBlock

    layers: list[nn.Module] = [nn.Conv2d(3, width, 7, 2, 3, bias=False), _group_norm(width), nn.ReLU(inplace=True),
                               nn.MaxPool2d(3, 2, 1)]
    inplanes = width
    for stage, planes in enumerate((width, 2 * width, 4 * width, 8 * width)):
        stride = 1 if stage == 0 else 2
        down = None
        if stride != 1 or inplanes != planes:
            down = nn.Sequential(nn.Conv2d(inplanes, planes, 1, stride, bias=False), _group_norm(planes))
        layers.append(nn.Sequential(BasicBlock(inplanes, planes, stride, down, norm_layer=_group_norm),
                                    BasicBlock(planes, planes, norm_layer=_group_norm)))
        inplanes = planes
    return nn.Sequential(*layers)


class SpatialSoftmax(nn.Module):
    """Keypoints: a 1x1 conv to ``num_kp`` maps, a softmax over each map's pixels, the expected (x, y)
    in [-1, 1]: [N, C, H, W] -> [N, 2 * num_kp]."""

    def __init__(self, channels: int, height: int, width: int, num_kp: int):
        super().__init__()
        self.nets = nn.Conv2d(channels, num_kp, 1)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height), torch.linspace(-1, 1, width), indexing="ij")
        self.register_buffer("pos", torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1), persistent=False)  # [HW, 2]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = self.nets(x)
        attn = torch.softmax(f.flatten(2), dim=-1)  # [N, K, HW]
        return (attn @ self.pos).flatten(1)  # [N, 2K]


class VisualCore(nn.Module):
    """One camera: trunk, spatial softmax, linear projection to ``feature_dim``."""

    def __init__(self, cfg: ImageEncoderConfig):
        super().__init__()
        self.backbone = resnet18_trunk(cfg.width)
        side = -(-cfg.crop_size // 32)  # the trunk's stride-32 output size
        self.pool = SpatialSoftmax(8 * cfg.width, side, side, cfg.num_kp)
        self.linear = nn.Linear(2 * cfg.num_kp, cfg.feature_dim)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.linear(self.pool(self.backbone(images)))


class ObsEncoder(nn.Module):
    """All cameras of a batch of frames: uint8 [N, H, W, 3] per camera -> features [N, cameras * feature_dim]."""

    def __init__(self, cfg: ImageEncoderConfig):
        super().__init__()
        self.cfg = cfg
        self.obs_nets = nn.ModuleDict({cam: VisualCore(cfg) for cam in cfg.cameras})

    def crop(self, x: torch.Tensor) -> torch.Tensor:
        """[N, 3, H, W]: a random crop per image in training mode, the centre crop otherwise."""
        c, (h, w) = self.cfg.crop_size, x.shape[-2:]
        if not self.training:
            top, left = (h - c) // 2, (w - c) // 2
            return x[..., top:top + c, left:left + c]
        n = x.shape[0]
        top = torch.randint(0, h - c + 1, (n,), device=x.device)
        left = torch.randint(0, w - c + 1, (n,), device=x.device)
        rows = (top[:, None] + torch.arange(c, device=x.device))[:, None, :, None]
        cols = (left[:, None] + torch.arange(c, device=x.device))[:, None, None, :]
        return x[torch.arange(n, device=x.device)[:, None, None, None], torch.arange(3, device=x.device)[None, :, None, None],
                 rows, cols]

    def forward(self, images: dict[str, torch.Tensor]) -> torch.Tensor:
        feats = []
        for cam in self.cfg.cameras:
            x = images[cam]
            if x.shape[-1] != 3:
                raise ValueError(f"{cam}: expected [N, H, W, 3] images, got {tuple(x.shape)}")
            x = x.permute(0, 3, 1, 2).float() / 255.0
            feats.append(self.obs_nets[cam](self.crop(x)))
        return torch.cat(feats, dim=-1)


class DiffusionTransformerHybridImagePolicy(DiffusionTransformerLowdimPolicy):
    """DP-T on camera images plus low-dim keys (``cfg.obs_keys`` / ``obs_dims``); the model's
    ``cond_dim`` must equal ``image_cfg.features + sum(obs_dims)``."""

    def __init__(self, cfg: PolicyConfig, image_cfg: ImageEncoderConfig):
        want = image_cfg.features + sum(cfg.obs_dims)
        if cfg.model.get("cond_dim") != want:
            raise ValueError(f"model cond_dim {cfg.model.get('cond_dim')} != camera features {image_cfg.features} + "
                             f"low-dim {sum(cfg.obs_dims)} = {want}")
        super().__init__(cfg)
        self.image_cfg = image_cfg
        self.obs_encoder = ObsEncoder(image_cfg)

    def encode(self, obs: dict[str, Any]) -> torch.Tensor:
        """Features of every frame of ``obs`` in one encoder forward: [B, T, cond_dim] (images of
        [B, T, H, W, 3] uint8; low-dim keys [B, T, dim])."""
        first = obs[self.image_cfg.cameras[0]] if self.image_cfg.cameras[0] in obs else None
        if self.cfg.obs_keys:
            low = self.obs_normalizer.normalize(self.obs_vector(obs))  # [B, T, dl]
        elif first is not None:
            low = torch.zeros(*np.shape(first)[:2], 0, device=self.device)
        else:
            raise KeyError(f"observation key {self.image_cfg.cameras[0]!r} missing")
        B, T = low.shape[:2]
        images = {}
        for cam in self.image_cfg.cameras:
            if cam not in obs:
                raise KeyError(f"observation key {cam!r} missing; the policy's cameras are {list(self.image_cfg.cameras)}")
            x = torch.as_tensor(np.asarray(obs[cam])).to(self.device)
            if x.shape[:2] != (B, T):
                raise ValueError(f"{cam}: {tuple(x.shape[:2])} frames, low-dim keys have {(B, T)}")
            images[cam] = x.reshape(B * T, *x.shape[2:])
        feats = self.obs_encoder(images).reshape(B, T, -1)
        return torch.cat([feats, low], dim=-1)

    def condition(self, obs: dict[str, Any]) -> torch.Tensor:
        """The last ``n_obs_steps`` frames encoded once for the whole call."""
        To = self.cfg.n_obs_steps
        trimmed = {k: (np.asarray(v)[:, -To:] if not torch.is_tensor(v) else v[:, -To:]) for k, v in obs.items()}
        return self.encode(trimmed)

    def compute_loss(self, obs: dict[str, Any], action: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        """DDPM epsilon loss; ``obs`` holds the window's frames (random crops in training mode)."""
        cond = self.condition(obs)
        a = self.action_normalizer.normalize(action)
        noise = torch.randn_like(a)
        t = torch.randint(0, self.cfg.num_train_timesteps, (a.shape[0],), device=a.device)
        noisy = self.scheduler.add_noise(a, noise, t)
        return nn.functional.mse_loss(self.model(noisy, t, cond), noise)

    def config_dict(self) -> dict:
        """The image encoder's options, for the checkpoint."""
        return {"image_encoder": asdict(self.image_cfg)}
