"""`bilateral` and `nlm`: non-learned cross-bilateral / cross-non-local-means denoisers.

The filters of Kalantari, Bako & Sen 2015 (Eq. 1-2 with the distances of Eq. 11-12, and the cross
NLM of Appendix Eq. 16-17) with one global value per bandwidth instead of the network's per-pixel
output: the baseline that shows what LBF's learning buys. Registered as ``bilateral``
(``filter="bilateral"``) and ``nlm`` (``filter="nlm"``).

Pipeline (the LBF pipeline without the network): optional NL-means prefilter of each feature and its
variance (Sec. 3.2, 11 x 11 window, 7 x 7 patches), the cross filter over the features the frame has,
optional spike removal (Sec. 4.3). A feature listed in ``Config.features`` that the frame lacks is
left out of the weights (its term is 0); a feature present without its variance uses the
variance floor ``delta`` of Eq. 12.

Bandwidths are standard deviations ``theta`` (``lambda = 1 / (2 theta^2)``, the paper's auxiliary
parameter); ``None`` switches a term off. The defaults come from the documented search
`experiments/tune_filters.py` on training frames (docs/methods/bilateral.md), never on benchmark
frames.
"""
from __future__ import annotations

import dataclasses
import math

import jax

from ..buffers import Buffers, BuffersError, map_frames, with_variances
from .lbf_features import PAPER_FEATURES
from ..filters import cross_bilateral, cross_nlm, remove_spikes
from ..filters.nlm import prefilter_guides
from ..errors import JaxdenoiseError



# gamma_k found by experiments/tune_filters.py on training frames (docs/results/tune_<filter>.md).
TUNED_FEATURE_SIGMAS = {
    "bilateral": {"position": 1.0, "normal": 0.125, "albedo": 0.0625, "albedo2": 0.0625, "visibility": 8.0},
    "nlm": {"position": 1.0, "normal": 0.125, "albedo": 0.0625, "albedo2": 0.0625, "visibility": None},
}
DEFAULT_FEATURE_SIGMA = 1.0  # for a configured feature outside the tuned set


@dataclasses.dataclass(frozen=True)
class Config:
    filter: str = "bilateral"  # "bilateral" (Eq. 2) or "nlm" (Eq. 16)
    radius: int = 10  # window (2 radius + 1)^2; the paper's learned filter uses 55 x 55 (radius 27)
    patch_radius: int = 2  # nlm: 5 x 5 patches (Appendix, Eq. 17)
    sigma_spatial: float | None = 16.0  # bilateral: theta of the screen-space term, pixels (tuned)
    sigma_color: float | None = 3.5  # bilateral: beta (tuned; the paper fixes beta = 7 for LBF, Sec. 4.2)
    sigma_patch: float | None = 4.0  # nlm: rho of the patch term, Eq. 16 (tuned)
    features: tuple[str, ...] = PAPER_FEATURES
    # gamma_k per feature, aligned with `features` (None entries switch a feature off). None: the
    # tuned values TUNED_FEATURE_SIGMAS[filter] (or `sigma_feature` for every feature when set).
    feature_sigmas: tuple[float | None, ...] | None = None
    sigma_feature: float | None = None  # one gamma shared by every feature (stage 1 of the search)
    prefilter: bool = True  # NL-means prefilter of features and their variances (Sec. 3.2)
    spike_removal: bool = True  # Sec. 4.3


def _lam(sigma: float | None, name: str) -> float:
    """lambda = 1 / (2 theta^2) (Kalantari 2015 Appendix); None -> 0 (term off)."""
    if sigma is None:
        return 0.0
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
        raise JaxdenoiseError(f"bilateral: config.{name} is {sigma!r}; expected a finite number > 0 or None")
    return 1.0 / (2.0 * float(sigma) ** 2)


def _check_config(config: Config) -> None:
    if config.filter not in ("bilateral", "nlm"):
        raise JaxdenoiseError(f"bilateral: config.filter is {config.filter!r}; expected 'bilateral' or 'nlm'")
    unknown = [f for f in config.features if f not in Buffers.__dataclass_fields__ or f.endswith("_var")]
    if unknown:
        raise JaxdenoiseError(f"bilateral: config.features has unknown feature buffer(s) {unknown}")


def needs(config: Config) -> frozenset[str]:
    """Colour, its variance, and every configured feature with its variance (optional ones)."""
    return with_variances({"color", *config.features})


def required(config: Config) -> frozenset[str]:
    """Only colour and its variance are required; absent features are left out of the weights."""
    return frozenset({"color", "color_var"})


def init(key, config: Config) -> dict:
    return {}


def prepare(arrays: dict, config: Config) -> dict:
    """The bandwidth-independent part for one (H, W, C) frame: colour, its variance, and the
    (prefiltered) features present in ``arrays`` with their (smoothed) variances."""
    # Sec. 3.2 (11x11 window, 7x7 patch); a feature the frame lacks is left out (its term is 0)
    guides, gvars = prefilter_guides({n: arrays.get(n) for n in config.features},
                                     {n: arrays.get(f"{n}_var") for n in config.features}, prefilter=config.prefilter)
    return {"color": arrays["color"], "color_var": arrays["color_var"], "features": list(guides.values()),
            "feature_vars": list(gvars.values())}


def filter_prepared(prep: dict, lam_spatial, lam_color, lam_patch, lam_features, config: Config) -> jax.Array:
    """Cross filter + optional spike removal of a `prepare`d frame with the given lambdas (scalars,
    possibly traced: `experiments/tune_filters.py` jits this over the bandwidths); ``lam_features``
    has one entry per feature in ``prep["features"]``."""
    feats, fvars = prep["features"], prep["feature_vars"]
    lam_f = list(lam_features)
    if config.filter == "nlm":
        out = cross_nlm(prep["color"], prep["color_var"], feats, fvars, lam_patch, lam_f,
                        radius=config.radius, patch_radius=config.patch_radius)
    else:
        out = cross_bilateral(prep["color"], prep["color_var"], feats, fvars, lam_spatial, lam_color, lam_f,
                              radius=config.radius)
    return remove_spikes(out) if config.spike_removal else out


def lambdas(config: Config, present: tuple[str, ...] | None = None) -> dict:
    """The auxiliary parameters lambda = 1/(2 theta^2) of the configured bandwidths; ``lam_features``
    lists one per feature of ``present`` (default: every configured feature)."""
    sig = config.feature_sigmas
    if sig is not None:
        if len(sig) != len(config.features):
            raise JaxdenoiseError(f"bilateral: config.feature_sigmas has {len(sig)} entries; expected one per "
                             f"feature {config.features}")
        per = dict(zip(config.features, sig))
    elif config.sigma_feature is not None:
        per = {f: config.sigma_feature for f in config.features}
    else:
        tuned = TUNED_FEATURE_SIGMAS.get(config.filter, {})
        per = {f: tuned.get(f, DEFAULT_FEATURE_SIGMA) for f in config.features}
    present = config.features if present is None else present
    return {"lam_spatial": _lam(config.sigma_spatial, "sigma_spatial"),
            "lam_color": _lam(config.sigma_color, "sigma_color"),
            "lam_patch": _lam(config.sigma_patch, "sigma_patch"),
            "lam_features": [_lam(per[f], f"feature_sigmas[{f}]") for f in present]}


def _frame(arrays: dict, config: Config) -> jax.Array:
    """Filter one (H, W, C) frame given a dict of present buffers."""
    present = tuple(f for f in config.features if arrays.get(f) is not None)
    return filter_prepared(prepare(arrays, config), config=config, **lambdas(config, present))


def apply(params: dict, buffers: Buffers, config: Config) -> jax.Array:
    """Denoise a frame ``(H, W, 3)`` or a batch ``(..., H, W, 3)`` of independent frames, one at a time."""
    _check_config(config)
    if not isinstance(buffers, Buffers):
        raise BuffersError(f"bilateral: 'buffers' must be a jaxdenoise.Buffers, got {type(buffers).__name__}")
    buffers.check_needs(required(config), config.filter)
    keep = needs(config)
    return map_frames(lambda b: _frame({k: v for k, v in b.to_dict().items() if k in keep}, config), buffers)
