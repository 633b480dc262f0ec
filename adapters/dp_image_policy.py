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

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn

from .dp_policy import DiffusionTransformerLowdimPolicy, PolicyConfig, load_official_normalizer, official_run_fields

__all__ = ["ImageEncoderConfig", "SpatialSoftmax", "VisualCore", "ObsEncoder", "DiffusionTransformerHybridImagePolicy",
           "CAMERAS", "hybrid_policy_from_official"]

CAMERAS = ("agentview_image", "robot0_eye_in_hand_image")


@dataclass
class ImageEncoderConfig:
    """cameras: observation keys of [.., H, W, 3] uint8 images (robomimic's HWC layout); crop_size:
    the random (training) / centre (test) crop; num_kp: spatial-softmax keypoints; feature_dim: per
    camera; width: channels of the trunk's first stage (64 = ResNet-18); pixel_scale, pixel_offset:
    the affine map of pixels in [0, 1] the trunk sees (Diffusion Policy's checkpoints use 2, -1);
    feature_relu: a ReLU on each camera's features (robomimic's ObservationEncoder applies one)."""

    cameras: Sequence[str] = CAMERAS
    image_size: int = 84
    crop_size: int = 76
    num_kp: int = 32
    feature_dim: int = 64
    width: int = 64
    pixel_scale: float = 1.0
    pixel_offset: float = 0.0
    feature_relu: bool = False

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
            top, left = int(round((h - c) / 2.0)), int(round((w - c) / 2.0))  # torchvision's center_crop
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
            if (self.cfg.pixel_scale, self.cfg.pixel_offset) != (1.0, 0.0):
                x = x * self.cfg.pixel_scale + self.cfg.pixel_offset
            f = self.obs_nets[cam](self.crop(x))
            feats.append(torch.relu(f) if self.cfg.feature_relu else f)
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


_TRANSFORMER_DEFAULTS = dict(n_layer=8, n_cond_layers=0, n_head=4, n_emb=256, p_drop_emb=0.0, p_drop_attn=0.3,
                             causal_attn=True, time_as_cond=True, obs_as_cond=True)  # Diffusion Policy's hybrid policy


def _official_camera_key(rest: str) -> str | None:
    """Our name for one robomimic ``VisualCore`` parameter (the part after ``obs_nets.<camera>.``); None
    for the spatial softmax's fixed buffers. robomimic stores each submodule twice: by attribute
    (``backbone.nets.*``, ``pool.*``) and inside its ``nets`` sequence (backbone, pool, flatten, linear)."""
    for prefix, ours in (("nets.0.nets.", "backbone."), ("backbone.nets.", "backbone."), ("nets.1.nets.", "pool.nets."),
                         ("pool.nets.", "pool.nets."), ("nets.3.", "linear.")):
        if rest.startswith(prefix):
            return ours + rest[len(prefix):]
    if rest.split(".")[-1] in ("pos_x", "pos_y", "temperature"):
        return None
    raise ValueError(f"unrecognised image encoder parameter {rest!r} (expected robomimic's VisualCore: "
                     "ResNet18Conv, SpatialSoftmax, Linear)")


def hybrid_policy_from_official(cfg: Any, sd: dict) -> DiffusionTransformerHybridImagePolicy:
    """Diffusion Policy's ``DiffusionTransformerHybridImagePolicy`` checkpoint (run config ``cfg``, state
    dict ``sd``) as our hybrid policy: the transformer and normalisers exactly, the robomimic encoder
    renamed (GroupNorm trunks, ``obs_encoder_group_norm=True``), with robomimic's ReLU on each camera's
    features; test time takes the centre crop (``eval_fixed_crop=True``; without it the official policy
    crops at random at test time too). The official condition lists the
    observation keys' features in ``shape_meta`` order; ours puts the cameras first, so the columns of
    the transformer's condition embedding are permuted to match."""
    pol = cfg["policy"]
    meta = pol["shape_meta"] if "shape_meta" in pol else cfg["shape_meta"]
    obs_meta = {k: dict(v) for k, v in meta["obs"].items()}
    cams = [k for k, v in obs_meta.items() if v.get("type", "low_dim") == "rgb"]
    low = [k for k, v in obs_meta.items() if v.get("type", "low_dim") == "low_dim"]
    if not cams or len(cams) + len(low) != len(obs_meta):
        raise ValueError(f"shape_meta obs types must be rgb or low_dim with at least one camera: {obs_meta}")
    if not pol.get("obs_as_cond", True) or pol.get("pred_action_steps_only", False):
        raise ValueError("only obs_as_cond=True, pred_action_steps_only=False checkpoints are supported")
    if not pol.get("obs_encoder_group_norm", False):
        raise ValueError("the image encoder must use GroupNorm (obs_encoder_group_norm=True); BatchNorm trunks are "
                         "not supported")
    first = f"obs_encoder.obs_nets.{cams[0]}."
    shape = [int(x) for x in obs_meta[cams[0]]["shape"]]
    crop = pol.get("crop_shape") or shape[1:]
    if shape[1] != shape[2] or crop[0] != crop[1]:
        raise ValueError(f"square images and crops only, got {shape} cropped to {list(crop)}")
    pix = [(float(sd[f"normalizer.params_dict.{c}.scale"].reshape(-1)[0]),
            float(sd[f"normalizer.params_dict.{c}.offset"].reshape(-1)[0])) for c in cams]
    if len(set(pix)) != 1:
        raise ValueError(f"cameras with different pixel normalisers: {dict(zip(cams, pix))}")
    image_cfg = ImageEncoderConfig(
        cameras=cams, image_size=shape[1], crop_size=int(crop[0]),
        num_kp=sd[first + "nets.1.nets.weight"].shape[0], feature_dim=sd[first + "nets.3.weight"].shape[0],
        width=sd[first + "nets.0.nets.0.weight"].shape[0], pixel_scale=pix[0][0], pixel_offset=pix[0][1],
        feature_relu=True)
    low_dims = [int(np.prod(obs_meta[k]["shape"])) for k in low]
    action_dim = int(meta["action"]["shape"][0])
    arch = {k: pol.get(k, v) for k, v in _TRANSFORMER_DEFAULTS.items()}
    run = official_run_fields(cfg)
    model = dict(input_dim=action_dim, output_dim=action_dim, horizon=run["horizon"], n_obs_steps=run["n_obs_steps"],
                 cond_dim=image_cfg.features + sum(low_dims), **arch)
    policy = DiffusionTransformerHybridImagePolicy(
        PolicyConfig(model=model, obs_keys=low, obs_dims=low_dims, action_dim=action_dim, **run), image_cfg)

    widths = {k: (image_cfg.feature_dim if k in cams else int(np.prod(v["shape"]))) for k, v in obs_meta.items()}
    starts = dict(zip(widths, np.cumsum([0] + list(widths.values()))[:-1]))
    order = torch.tensor([int(starts[k]) + i for k in cams + low for i in range(widths[k])])
    model_sd = {k[len("model."):]: v for k, v in sd.items() if k.startswith("model.")}
    if model_sd["cond_obs_emb.weight"].shape[1] != len(order):
        raise ValueError(f"condition width {model_sd['cond_obs_emb.weight'].shape[1]} != the shape_meta's {len(order)}")
    model_sd["cond_obs_emb.weight"] = model_sd["cond_obs_emb.weight"][:, order]
    policy.model.load_state_dict(model_sd)

    enc = {}
    for k, v in sd.items():
        if not k.startswith("obs_encoder."):
            continue
        cam, rest = k[len("obs_encoder.obs_nets."):].split(".", 1) if k.startswith("obs_encoder.obs_nets.") else (None, k)
        if cam not in cams:
            raise ValueError(f"unexpected image encoder parameter {k!r}")
        if rest.endswith("temperature") and not torch.allclose(v.float(), torch.ones_like(v.float())):
            raise ValueError(f"{k}: spatial-softmax temperature {v.tolist()} (only 1 is supported)")
        ours = _official_camera_key(rest)
        if ours is not None:
            enc[f"{cam}.{ours}"] = v
    policy.obs_encoder.obs_nets.load_state_dict(enc)
    load_official_normalizer(policy.obs_normalizer, sd, low)
    load_official_normalizer(policy.action_normalizer, sd, ["action"])
    return policy
