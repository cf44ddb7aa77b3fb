"""The method registry (docs/architecture.md "Methods").

Every method lives in ``jaxdenoise/methods/<module>.py`` and exposes the surface stated once in
`jaxdenoise.methods.protocol` (required: ``Config``, ``needs``, ``init``, ``apply``; optional hook
groups: causal ``init_state``/``step``, windowed ``window``/``prepare_frame``/``apply_window``,
trainable ``loss``/``make_dataset``/``batch``; optional attributes ``required``, ``JITTABLE``,
``requirements``, ``WEIGHTS``, ``TRAIN``, ``FROZEN``, ``frame_stats``). `Method` answers "is it trainable /
temporal?" from those protocols, and a test checks every registered module against them.

A registered name maps to a module plus config overrides, so one module serves variants
(``lbf`` / ``lbf-nlm``, ``poisson-l2`` / ``poisson-l1``).
"""
from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

from .protocol import Causal, Trainable, Windowed
from ..errors import JaxdenoiseError

# name -> (module, config overrides). Order is the order of tables and plots.
_REGISTRY: dict[str, tuple[str, dict[str, Any]]] = {
    "input": ("jaxdenoise.methods.input", {}),
    "gaussian": ("jaxdenoise.methods.gaussian", {}),
    "oidn": ("jaxdenoise.methods.oidn", {}),
    "oidn-balanced": ("jaxdenoise.methods.oidn", {"quality": "balanced"}),  # OIDN's own speed presets:
    "oidn-fast": ("jaxdenoise.methods.oidn", {"quality": "fast"}),          # its error-against-time curve
    "lbf": ("jaxdenoise.methods.lbf", {"filter": "bilateral"}),
    "lbf-nlm": ("jaxdenoise.methods.lbf", {"filter": "nlm"}),
    "bilateral": ("jaxdenoise.methods.bilateral", {"filter": "bilateral"}),
    "nlm": ("jaxdenoise.methods.bilateral", {"filter": "nlm"}),
    "poisson-l2": ("jaxdenoise.methods.poisson", {"norm": "l2"}),
    "poisson-l1": ("jaxdenoise.methods.poisson", {"norm": "l1"}),
    "demc": ("jaxdenoise.methods.demc", {"keep_exact": True, "exact_window": 3, "match_level": 8.0,
                                         "match_max_gain": 1.1, "match_spike": 4.0, "refine_sigma": 3.0,
                                         "refine_range": 0.4, "refine_albedo": 0.03, "refine_normal": 0.1}),
    "demc-paper": ("jaxdenoise.methods.demc", {"recipe": "paper", "train_spps": (4,), "exposure": "none",
                                               "level_weight": 0.0}),
    "rae": ("jaxdenoise.methods.rae", {"outlier_clamp": 8.0, "match_level": 8.0, "match_max_gain": 2.0,
                                       "match_spike": 8.0, "keep_exact": True, "exact_window": 3,
                                       "taa_alpha": 0.25, "taa_window": 3, "taa_tolerance": 0.0,
                                       "refine_sigma": 3.0, "refine_range": 0.4, "refine_albedo": 0.03,
                                       "refine_normal": 0.1, "accumulate_samples": 4.0,
                                       "accumulate_tolerance": 0.02, "accumulate_clamp": 8.0,
                                       "keep_background": True, "match_frames": 2.0, "match_tolerance": 0.0,
                                       "match_output_cut": True}),
    "rae-paper": ("jaxdenoise.methods.rae", {"recipe": "paper", "train_spps": (1,), "exposure": "none",
                                             "input_transform": "power", "rate_input": False}),
    "gradnet": ("jaxdenoise.methods.gradnet", {}),
}

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"


class MethodError(JaxdenoiseError):
    """Unknown method, unavailable method, or parameters that cannot be used."""


@dataclasses.dataclass(frozen=True)
class Method:
    """A registered method: its module and its resolved config."""

    name: str
    module: ModuleType
    config: Any

    @property
    def jittable(self) -> bool:
        return getattr(self.module, "JITTABLE", True)

    @property
    def trainable(self) -> bool:
        return isinstance(self.module, Trainable)

    @property
    def recurrent(self) -> bool:
        return isinstance(self.module, Causal)

    @property
    def temporal(self) -> str:
        """How the sequence driver runs it: ``"causal"`` (state carried frame to frame),
        ``"windowed"`` (frame t reads t - back .. t + ahead) or ``"frame"`` (frame by frame)."""
        if self.recurrent:
            return "causal"
        if isinstance(self.module, Windowed) and tuple(self.module.window(self.config)) != (0, 0):
            return "windowed"
        return "frame"

    def needs(self) -> frozenset[str]:
        return frozenset(self.module.needs(self.config)) | {"color"}

    def required(self) -> frozenset[str]:
        fn = getattr(self.module, "required", None)
        return (frozenset(fn(self.config)) | {"color"}) if fn else self.needs()

    def requirements(self) -> str | None:
        """None if the method can run here, else the reason it cannot."""
        fn = getattr(self.module, "requirements", None)
        return fn() if fn else None

    def init(self, key) -> Any:
        return self.module.init(key, self.config)

    def apply(self, params: Any, buffers) -> Any:
        return self.module.apply(params, buffers, self.config)

    def loss(self, params: Any, batch) -> Any:
        if not self.trainable:
            raise MethodError(f"method '{self.name}' has no parameters to train")
        return self.module.loss(params, batch, self.config)

    @property
    def weights_dir(self) -> Path | None:
        name = getattr(self.module, "WEIGHTS", None)
        if name is None:
            return None
        if callable(name):
            name = name(self.config)
        return WEIGHTS_DIR / name

    def with_config(self, **overrides: Any) -> "Method":
        return dataclasses.replace(self, config=dataclasses.replace(self.config, **overrides))


def register(name: str, module: str, **config_overrides: Any) -> None:
    """Register ``name`` as ``module`` (import path) with config overrides; replaces an earlier one."""
    _REGISTRY[name] = (module, dict(config_overrides))


def names() -> list[str]:
    """Every registered method name, in table order."""
    return list(_REGISTRY)


def get(name: str, config: Any = None, **overrides: Any) -> Method:
    """Resolve a registered method; ``config`` replaces the default, ``overrides`` adjust fields."""
    if name not in _REGISTRY:
        raise MethodError(f"unknown method '{name}'; registered: {', '.join(_REGISTRY)}")
    modname, defaults = _REGISTRY[name]
    module = importlib.import_module(modname)
    if config is None:
        config = module.Config(**defaults)
    elif not isinstance(config, module.Config):
        raise MethodError(f"method '{name}' expects a {modname}.Config, got {type(config).__name__}")
    if overrides:
        config = dataclasses.replace(config, **overrides)
    return Method(name=name, module=module, config=config)


def available() -> dict[str, str | None]:
    """name -> None if it can run here, else the reason it cannot."""
    return {n: get(n).requirements() for n in names()}


def parse_list(spec: str, *, allow: Callable[[str], bool] | None = None) -> list[str]:
    """Parse a comma-separated method list ('all' = every available one); unknown names fail."""
    if spec.strip() == "all":
        return [n for n, why in available().items() if why is None and (allow is None or allow(n))]
    out = [s.strip() for s in spec.split(",") if s.strip()]
    for n in out:
        get(n)  # raises for unknown names
    return out
