"""The one method vocabulary of both evaluation suites (``eval/robot.py --method``, ``eval/imagenet.py
--method``), parsed here and nowhere else.

==============================  ================================================================
spec                            method
==============================  ================================================================
``dense``                       the model as is (an all-compute plan: bit-identical outputs)
``ddim:K[:SPACING]``            fewer sampling steps: DDIM with K steps, dense; SPACING of the
                                timesteps: leading (Diffusion Policy's, the default) | trailing |
                                linspace
``dpm:K``                       fewer sampling steps: DPM-Solver++ (2nd order) with K steps, dense
``ddpm:K``                      fewer sampling steps: the policy's own stochastic DDPM sampler on K
                                leading timesteps (fresh noise at every step), dense; robot suite
``uniform:RHO:DIRECTION``       ``tts.plans.uniform``: RHO of the (step, branch) decisions reuse
``every_n:N:DIRECTION``         ``tts.plans.every_n``: full compute every N steps (FORA: timestep)
``rotating:RHO:DIRECTION``      ``tts.plans.rotating``: as uniform, the compute steps moved by one
                                step per call (refreshes the rollout cache)
``file:SCHEDULE.json``          a searched static schedule (``eval/search_static.py``)
``pruner:PATH``                 a trained pruner, argmax decisions (the paper)
``pruner:PATH@RHO``             a trained pruner, exactly RHO of the decisions reused per sample
``taylorseer:N:O``              every N-th step computed, an order-O Taylor forecast in between
``toca:N[:RATIO]``, ``@RHO``    ToCa-style token refresh (image); RATIO of the tokens, or the ratio
                                that reuses RHO of the branch MACs
``duca:N[:RATIO]``, ``@RHO``    DuCa-style token refresh (image)
``diffusers:fbc[:THRESHOLD]``   diffusers' First Block Cache (image); ``@RHO``: the threshold
                                calibrated to sparsity RHO on calibration noise
``diffusers:taylorseer:N:O``    diffusers' TaylorSeer cache (image)
==============================  ================================================================

``+taylorO`` after a ``file:``, ``pruner:``, ``uniform:`` or ``every_n:`` spec (or ``--forecast O``, a
separate option) adds a Taylor forecast of order O to timestep reuse; it is part of the row label.

``+ddim:K[:SPACING]`` or ``+dpm:K`` after an engine method runs it on that base sampler instead of
the suite's own (the policy's DDPM-100; the image suite's ``--steps`` / ``--scheduler``): e.g.
``uniform:0.65:timestep+ddim:20`` computes 7 of DDIM-20's steps. Schedules and pruners must have
been made for the base's number of steps. The image suite takes no SPACING.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Optional

__all__ = ["Method", "Sampler", "parse_method", "install", "install_policy", "pruner_weights_sha256", "ROBOT_KINDS",
           "IMAGE_KINDS", "VOCABULARY"]

VOCABULARY = ("dense | ddim:K[:SPACING] | dpm:K | ddpm:K | uniform:RHO:DIRECTION | every_n:N:DIRECTION | rotating:RHO:DIRECTION | "
              "file:SCHEDULE.json | "
              "pruner:PATH[@RHO] (+taylorO after any of the four) | taylorseer:N:O | toca:N[:RATIO][@RHO] | duca:N[:RATIO][@RHO] | "
              "diffusers:fbc[:THRESHOLD][@RHO] | diffusers:taylorseer:N:O; engine methods take +ddim:K[:SPACING] | +dpm:K "
              "(the base sampler)")
ROBOT_KINDS = frozenset({"dense", "ddim", "dpm", "ddpm", "uniform", "every_n", "rotating", "file", "pruner", "taylorseer"})
IMAGE_KINDS = frozenset({"dense", "ddim", "dpm", "uniform", "every_n", "rotating", "file", "pruner", "taylorseer", "toca",
                         "duca", "diffusers"})
_DIRS = ("forward", "timestep", "rollout")
SAMPLERS = {"ddim": ("leading", "trailing", "linspace"), "dpm": (), "ddpm": ()}


@dataclass(frozen=True)
class Sampler:
    """A sampler of a policy: ``scheduler`` ("ddim" | "dpm" | "ddpm"), ``steps``, ``spacing`` (None: default)."""

    scheduler: str
    steps: int
    spacing: Optional[str] = None

    @property
    def spec(self) -> str:
        return f"{self.scheduler}:{self.steps}" + (f":{self.spacing}" if self.spacing else "")


def _sampler(text: str, spec: str) -> Sampler:
    parts = text.split(":")
    name = parts[0]
    if name not in SAMPLERS or len(parts) not in (2, 3) or (len(parts) == 3 and not SAMPLERS[name]):
        raise ValueError(f"method {spec!r}: a sampler is ddim:K[:SPACING], dpm:K or ddpm:K, got {text!r}")
    k = _number(parts[1], int, "the number of steps", spec)
    if k < 1:
        raise ValueError(f"method {spec!r}: {name.upper()} needs at least 1 step")
    spacing = parts[2] if len(parts) == 3 else None
    if spacing is not None and spacing not in SAMPLERS[name]:
        raise ValueError(f"method {spec!r}: unknown timestep spacing {spacing!r}; choose one of {SAMPLERS[name]}")
    return Sampler(name, k, spacing)


@dataclass(frozen=True)
class Method:
    """A parsed method spec. ``kind``: the word before the first colon; ``path``: the schedule or
    pruner of ``file:`` / ``pruner:``; ``n``, ``order``, ``ratio``, ``threshold``, ``direction``: the
    numbers and names of the spec; ``sparsity``: RHO (``uniform``, or an ``@RHO`` budget);
    ``forecast``: the ``--forecast`` order applied to timestep reuse."""

    spec: str
    kind: str
    path: Optional[Path] = None
    sparsity: Optional[float] = None
    direction: Optional[str] = None
    n: Optional[int] = None
    order: int = 0
    ratio: Optional[float] = None
    threshold: Optional[float] = None
    cache: Optional[str] = None  # diffusers: "fbc" | "taylorseer"
    forecast: int = 0
    sampler: Optional[Sampler] = None  # ddim: / dpm:, or the base sampler of an engine method (+ddim:K)

    @property
    def label(self) -> str:
        """The row name of results: the spec with file paths reduced to their stem."""
        if self.kind in ("file", "pruner"):
            stem = self.path.name[:-5] if self.path.name.endswith(".json") else self.path.name
            text = f"{self.kind}:{stem}" + ("" if self.sparsity is None else f"@{self.sparsity:g}")
        else:
            text = self.spec
        if self.sampler is not None and self.engine:
            text += f"+{self.sampler.spec}"
        return text + (f"+taylor{self.forecast}" if self.forecast else "")

    @property
    def slug(self) -> str:
        """The label as a file-name part: ``pruner:lift_tts_0.93@0.93`` -> ``pruner-lift_tts_0.93-at0.93``."""
        return re.sub(r"[^A-Za-z0-9._+-]+", "-", self.label.replace("@", "-at"))

    @property
    def engine(self) -> bool:
        """True when the method runs in the tts engine (everything but ``ddim``, ``dpm``, ``ddpm``, ``diffusers:``)."""
        return self.kind not in (*SAMPLERS, "diffusers")


def _number(text: str, kind: type, what: str, spec: str):
    try:
        value = kind(text)
    except ValueError:
        raise ValueError(f"method {spec!r}: {what} must be {'an integer' if kind is int else 'a number'}, "
                         f"got {text!r}") from None
    return value


def _direction(text: str, spec: str) -> str:
    if text not in _DIRS:
        raise ValueError(f"method {spec!r}: unknown direction {text!r}; choose one of {_DIRS}")
    return text


def _budget(spec: str) -> tuple[str, Optional[float]]:
    if "@" not in spec:
        return spec, None
    body, rho = spec.rsplit("@", 1)
    value = _number(rho, float, "the budget after '@'", spec)
    if not 0.0 <= value < 1.0:
        raise ValueError(f"method {spec!r}: the sparsity after '@' must be in [0, 1), got {value}")
    return body, value


def parse_method(spec: str, *, kinds: frozenset = IMAGE_KINDS, forecast: int = 0) -> Method:
    """Parse ``spec`` (see the module docstring); ``kinds`` limits what the calling suite runs."""
    spec = spec.strip()
    base = None
    while True:  # suffixes, in any order: +taylorO, +ddim:K[:SPACING], +dpm:K
        suffix = re.fullmatch(r"(.*)\+(taylor\d+|(?:ddim|dpm):[^+]*)", spec)
        if not suffix:
            break
        spec, word = suffix.group(1), suffix.group(2)
        if word.startswith("taylor"):
            order = int(word[len("taylor"):])
            if forecast and forecast != order:
                raise ValueError(f"method {spec!r}+taylor{order} and --forecast {forecast} disagree")
            forecast = order
        else:
            if base is not None:
                raise ValueError(f"method {spec!r}: more than one base sampler")
            base = _sampler(word, spec)
    kind = spec.split(":", 1)[0]
    if kind not in IMAGE_KINDS | ROBOT_KINDS:
        raise ValueError(f"unknown method {spec!r}; the vocabulary is {VOCABULARY}")
    if kind not in kinds:
        raise ValueError(f"method {kind!r} is not available in this suite (available: {', '.join(sorted(kinds))})")
    if base is not None and kind in (*SAMPLERS, "diffusers"):
        raise ValueError(f"method {spec!r}: a base sampler (+ddim:K, +dpm:K) applies to engine methods")
    if base is not None and kinds != ROBOT_KINDS and base.spacing is not None:
        raise ValueError(f"method {spec!r}: the image suite spaces timesteps as DiT does (leading); drop the spacing")
    method = _parse_body(spec, kind, forecast)
    return method if base is None else replace(method, sampler=base)


def _parse_body(spec: str, kind: str, forecast: int) -> Method:
    if forecast and kind not in ("file", "pruner", "uniform", "every_n", "rotating"):
        raise ValueError(f"a Taylor forecast (+taylorO, --forecast) applies to timestep reuse of file:, pruner:, "
                         f"uniform: and every_n: methods (taylorseer:N:O has its own order), not to {spec!r}")
    body, rho = _budget(spec)
    if rho is not None and kind not in ("pruner", "toca", "duca", "diffusers"):
        raise ValueError(f"method {spec!r}: an '@RHO' budget applies to pruner:, toca:, duca: and diffusers:fbc")
    parts = body.split(":")
    bad = ValueError(f"malformed method {spec!r}; the vocabulary is {VOCABULARY}")
    if kind == "dense":
        if len(parts) != 1:
            raise bad
        return Method(spec, kind)
    if kind in SAMPLERS:
        sampler = _sampler(body, spec)
        return Method(spec, kind, n=sampler.steps, sampler=sampler)
    if kind in ("uniform", "every_n", "rotating"):
        if len(parts) != 3:
            raise bad
        direction = _direction(parts[2], spec)
        if forecast and direction != "timestep":
            raise ValueError(f"method {spec!r}: a Taylor forecast applies to timestep reuse only")
        if kind == "rotating" and direction == "forward":
            raise ValueError(f"method {spec!r}: a rotating schedule moves whole steps (timestep or rollout)")
        if kind in ("uniform", "rotating"):
            s = _number(parts[1], float, "the sparsity", spec)
            if not 0.0 <= s < 1.0:
                raise ValueError(f"method {spec!r}: sparsity must be in [0, 1), got {s}")
            return Method(spec, kind, sparsity=s, direction=direction, forecast=forecast)
        n = _number(parts[1], int, "the interval", spec)
        if n < 1:
            raise ValueError(f"method {spec!r}: the interval must be >= 1")
        return Method(spec, kind, n=n, direction=direction, forecast=forecast)
    if kind in ("file", "pruner"):
        path = body.split(":", 1)[1] if ":" in body else ""
        if not path:
            raise bad
        return Method(spec, kind, path=Path(path), sparsity=rho, forecast=forecast)
    if kind == "taylorseer":
        if len(parts) != 3:
            raise bad
        n, o = _number(parts[1], int, "the interval", spec), _number(parts[2], int, "the order", spec)
        if n < 1 or o < 1:
            raise ValueError(f"method {spec!r}: interval and order must be >= 1")
        return Method(spec, kind, n=n, order=o, direction="timestep")
    if kind in ("toca", "duca"):
        if len(parts) not in (2, 3):
            raise bad
        n = _number(parts[1], int, "the interval", spec)
        ratio = _number(parts[2], float, "the fresh-token ratio", spec) if len(parts) == 3 else None
        if (ratio is None) == (rho is None):
            raise ValueError(f"method {spec!r} needs exactly one of a fresh-token ratio (:{kind}:N:RATIO) and a "
                             f"budget ({kind}:N@RHO)")
        return Method(spec, kind, n=n, ratio=ratio, sparsity=rho, direction="timestep")
    # diffusers:fbc[:THRESHOLD][@RHO] | diffusers:taylorseer:N:O
    cache = parts[1] if len(parts) > 1 else ""
    if cache == "fbc" and len(parts) in (2, 3):
        threshold = _number(parts[2], float, "the threshold", spec) if len(parts) == 3 else None
        if (threshold is None) == (rho is None):
            raise ValueError(f"method {spec!r} needs exactly one of a threshold (diffusers:fbc:T) and a budget "
                             "(diffusers:fbc@RHO)")
        return Method(spec, kind, cache="fbc", threshold=threshold, sparsity=rho)
    if cache == "taylorseer" and len(parts) == 4 and rho is None:
        n, o = _number(parts[2], int, "the interval", spec), _number(parts[3], int, "the order", spec)
        return Method(spec, kind, cache="taylorseer", n=n, order=o)
    raise bad


def read_schedule(path: Path) -> tuple[tuple[str, ...], Any]:
    """A searched schedule file -> (its directions, its plan)."""
    import tts

    if not Path(path).is_file():
        raise FileNotFoundError(f"no schedule at {path} (write one with eval/search_static.py)")
    doc = json.loads(Path(path).read_text())
    return tuple(doc["directions"]), tts.plans.from_tensor(doc["grid"])


def install(model: Any, method: Method, *, parallel: Any = "auto", memory_width: Optional[int] = None):
    """``tts.accelerate`` for an engine method (every kind but ``ddim`` and ``diffusers``; ``toca`` /
    ``duca`` with a ratio: a budget needs the backbone's MLP share, see the image suite). ``dense``
    installs an all-compute plan (outputs bit-identical; the summary gives MACs)."""
    import tts

    if not method.engine:
        raise ValueError(f"{method.spec} does not run in the tts engine")
    if method.kind == "dense":
        return tts.accelerate(model, _DIRS if _rollout_ok(model) else _DIRS[:2], plan=tts.plans.dense())
    if method.kind == "uniform":
        return tts.accelerate(model, (method.direction,), plan=tts.plans.uniform(method.sparsity, method.direction),
                              forecast=method.forecast)
    if method.kind == "every_n":
        return tts.accelerate(model, (method.direction,), plan=tts.plans.every_n(method.n, method.direction),
                              forecast=method.forecast)
    if method.kind == "rotating":
        return tts.accelerate(model, (method.direction,), plan=tts.plans.rotating(method.sparsity, method.direction),
                              forecast=method.forecast)
    if method.kind == "taylorseer":
        return tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(method.n, "timestep"),
                              forecast=method.order)
    if method.kind in ("toca", "duca"):
        if method.ratio is None:
            raise ValueError(f"{method.spec}: resolve the budget to a fresh-token ratio first")
        make = tts.tokens.toca if method.kind == "toca" else tts.tokens.duca
        return tts.accelerate(model, ("timestep",), plan=make(method.n, method.ratio))
    if method.kind == "file":
        directions, plan = read_schedule(method.path)
        return tts.accelerate(model, directions, plan=plan,
                              forecast=method.forecast if "timestep" in directions else 0)
    pruner = tts.load_pruner(method.path)
    trained = int(getattr(pruner, "metadata", {}).get("forecast", 0) or 0)
    if trained != method.forecast:
        raise ValueError(f"{method.path} was trained with --forecast {trained}; evaluate it with the same")
    if memory_width is not None and pruner.config.memory_dim != memory_width:
        raise ValueError(f"pruner {method.path} reads condition memory of width {pruner.config.memory_dim}, this "
                         f"model's has width {memory_width}: it belongs to another model")
    return tts.accelerate(model, pruner.config.directions, pruner=pruner, sparsity=method.sparsity,
                          forecast=method.forecast, parallel=parallel)


def pruner_weights_sha256(method: Method) -> Optional[str]:
    """The SHA-256 of a ``pruner:`` method's weights file (None for other methods): which weights a result
    came from, as a training in progress rewrites them under the same name."""
    if method.kind != "pruner":
        return None
    from tts.io import checkpoint_pair

    from . import file_sha256

    return file_sha256(checkpoint_pair(method.path)[0])


def install_policy(policy: Any, method: Method, *, parallel: Any = "auto"):
    """``method`` installed on a Diffusion Policy: its sampler first (``ddim:K``, ``dpm:K``, or the base
    of ``SPEC+ddim:K``), then the plan (a dense one for the fewer-step samplers: MACs are counted)."""
    if method.sampler is not None:
        s = method.sampler
        policy.set_sampler(s.scheduler, s.steps, s.spacing)
    if not method.engine:
        return install(policy, Method("dense", "dense"))
    return install(policy, method, parallel=parallel)


def _rollout_ok(model: Any) -> bool:
    """Whether the rollout direction applies (robot policies), i.e. the model is not an image generator."""
    import tts

    try:
        return tts.resolve_target(model).supports_rollout is not False
    except (TypeError, ValueError):
        return True
