"""Transfer functions as forward/inverse pairs (docs/architecture.md "Layout": ``color.py``).

Every function is pure ``jax.numpy``, jittable, elementwise, and accepts numpy or jax arrays of
any shape. The range compressors (`gamma`, `log_transform`, `mu_law`) are extended to negative
inputs as odd functions, ``f(-x) = -f(x)``, so each one is a bijection of the real line and its
inverse is exact even for the slightly negative radiance that gradient-domain reconstructions and
linear filters can produce.

A `Transfer` record bundles a pair (``forward``, ``inverse``) under a name, so a method config can
name its transform (``"mu-law"``) and look the pair up with `transfer`.

Demodulation (`demodulate` / `remodulate`) divides the noisy colour by the first-hit albedo so a
network or filter sees untextured illumination (Chaitanya et al. 2017, Sec. 3.2 and Sec. 5.1
"untextured lighting"; Bako et al. 2017, Sec. 4.1, whose ``albedo + eps`` with ``eps = 0.00316`` is
the default here).

Exposure (`color_mean`, `exposure_level`, `exposure_scale`): a network that should answer a frame
``k`` times brighter with an output ``k`` times brighter (``f(k x) = k f(x)``, what OIDN's
``inputScale`` offers) scales the colour to `EXPOSURE_LEVEL` by a whole-frame statistic that is
homogeneous of degree 1 and scales the output back (`demc` and `rae` with ``exposure = "frame"``).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
from .arrays import quantile_lower
from .errors import JaxdenoiseError

# Default mu of the mu-law compressor: Guo et al. 2019, Sec. 4.2, "we empirically set mu = 16".
MU_DEFAULT = 16.0
# Display gamma of the tone map used by the metrics (docs/architecture.md "Error against run time").
GAMMA_DEFAULT = 2.2
# Albedo epsilon of Bako et al. 2017, Sec. 4.1 (``c / (albedo + 0.00316)``).
ALBEDO_EPS_DEFAULT = 0.00316
# ``exposure = "frame"`` (ours, docs/methods/demc.md): the level a frame's colour is scaled to, and the
# quantile of the luminance above which pixels are clipped when the level is measured.
EXPOSURE_LEVEL = 0.2
EXPOSURE_CLIP_QUANTILE = 0.999


def _float(x: Any) -> jnp.ndarray:
    """``x`` as a floating jax array (integers become float32; float16/32/64 keep their type)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    return x


def _odd(f: Callable[[jnp.ndarray], jnp.ndarray], x: jnp.ndarray) -> jnp.ndarray:
    """Extend ``f`` (defined on x >= 0, f(0) = 0) to the real line as an odd function.

    The inner ``where`` feeds each branch only arguments it is defined on, so neither branch can
    produce NaN in the forward pass or in the gradient (the "double where" guard); at x = 0 the
    gradient is the right derivative of ``f`` at 0.
    """
    pos = x >= 0
    return jnp.where(pos, f(jnp.where(pos, x, 0.0)), -f(jnp.where(pos, 0.0, -x)))


def _safe_pow(a: jnp.ndarray, p: Any) -> jnp.ndarray:
    """``a ** p`` for a >= 0 with a finite gradient at a = 0.

    For 0 < p < 1 the derivative ``p * a ** (p - 1)`` is infinite at 0, and jax's pow rule would
    give ``0 * inf = NaN`` downstream; the value is exact (0 ** p = 0) and the gradient at exactly 0
    is set to 0 by evaluating the power only where a > 0.
    """
    nz = a > 0
    return jnp.where(nz, jnp.power(jnp.where(nz, a, 1.0), p), 0.0)


# -- gamma ---------------------------------------------------------------------------------------
def gamma(x: Any, g: float = GAMMA_DEFAULT) -> jnp.ndarray:
    """Display encoding ``sign(x) |x| ** (1 / g)`` (the ``** (1/2.2)`` of the metrics' tone map)."""
    x = _float(x)
    return _odd(lambda a: _safe_pow(a, 1.0 / g), x)


def inv_gamma(y: Any, g: float = GAMMA_DEFAULT) -> jnp.ndarray:
    """Inverse of `gamma`: ``sign(y) |y| ** g``."""
    y = _float(y)
    return _odd(lambda a: _safe_pow(a, g), y)


# -- log -----------------------------------------------------------------------------------------
def log_transform(x: Any) -> jnp.ndarray:
    """``sign(x) log(1 + |x|)``, the logarithmic range compressor (Bako et al. 2017, Sec. 4.1).

    ``log1p`` keeps it accurate near 0; it is the mu = 1 case of `mu_law` up to the factor log 2
    (Guo et al. 2019, Sec. 4.2).
    """
    return _odd(jnp.log1p, _float(x))


def inv_log_transform(y: Any) -> jnp.ndarray:
    """Inverse of `log_transform`: ``sign(y) (exp(|y|) - 1)``."""
    return _odd(jnp.expm1, _float(y))


# -- mu-law --------------------------------------------------------------------------------------
def mu_law(x: Any, mu: float = MU_DEFAULT) -> jnp.ndarray:
    """mu-law range compression, Guo et al. 2019 Eq. 6: ``T(I) = sign(I) log(1 + mu |I|) / log(1 + mu)``."""
    if not mu > 0:
        raise JaxdenoiseError(f"mu_law: 'mu' must be > 0, got {mu}")
    scale = 1.0 / jnp.log1p(mu)
    return _odd(lambda a: jnp.log1p(mu * a) * scale, _float(x))


def inv_mu_law(y: Any, mu: float = MU_DEFAULT) -> jnp.ndarray:
    """Inverse of `mu_law` (Eq. 6 solved for I): ``sign(y) ((1 + mu) ** |y| - 1) / mu``."""
    if not mu > 0:
        raise JaxdenoiseError(f"inv_mu_law: 'mu' must be > 0, got {mu}")
    lg = jnp.log1p(mu)
    return _odd(lambda a: jnp.expm1(a * lg) / mu, _float(y))


# -- sRGB ----------------------------------------------------------------------------------------
def srgb(x: Any) -> jnp.ndarray:
    """The sRGB transfer function (IEC 61966-2-1): ``12.92 x`` up to 0.0031308, else
    ``1.055 x ** (1 / 2.4) - 0.055``; extended to x < 0 as an odd function. The encoding of every
    8-bit image the library writes (`jaxdenoise.io.write_display`)."""
    def encode(a):
        lin = a <= 0.0031308  # the power branch sees only its own arguments: finite gradients at 0
        return jnp.where(lin, 12.92 * a, 1.055 * jnp.power(jnp.where(lin, 1.0, a), 1.0 / 2.4) - 0.055)

    return _odd(encode, _float(x))


def inv_srgb(y: Any) -> jnp.ndarray:
    """Inverse of `srgb`: ``y / 12.92`` up to 0.04045, else ``((y + 0.055) / 1.055) ** 2.4``."""
    def decode(a):
        lin = a <= 0.04045
        return jnp.where(lin, a / 12.92, jnp.power((jnp.where(lin, 1.0, a) + 0.055) / 1.055, 2.4))

    return _odd(decode, _float(y))


# -- tone map used by the metrics ------------------------------------------------------------------
def tonemap(x: Any, g: float = GAMMA_DEFAULT) -> jnp.ndarray:
    """``clip(x, 0, 1) ** (1 / g)``: the display mapping under which SSIM and PSNR are measured.

    Not invertible above 1 (clipped); the gradient is finite everywhere (0 outside [0, 1] and at 0).
    """
    return gamma(jnp.clip(_float(x), 0.0, 1.0), g)


# -- albedo demodulation ---------------------------------------------------------------------------
def _demod_dtype(color: jnp.ndarray, albedo: jnp.ndarray) -> Any:
    # At least float32: dividing by (albedo + eps) multiplies values by up to 1 / eps (~316), which
    # overflows float16 (max 65504) for radiance above ~200.
    return jnp.promote_types(jnp.promote_types(color.dtype, albedo.dtype), jnp.float32)


def demodulate(color: Any, albedo: Any, eps: float = ALBEDO_EPS_DEFAULT) -> jnp.ndarray:
    """Untextured illumination ``color / (albedo + eps)`` (Chaitanya et al. 2017, Sec. 3.2).

    ``eps`` guards zero albedo (black textures, sky / background pixels where the first hit has no
    albedo): without it the division gives inf or NaN (0 / 0) at exactly the pixels that carry no
    texture; with it those pixels are scaled by 1 / eps and `remodulate` undoes the scaling
    exactly. ``albedo`` broadcasts against ``color`` (one channel or three). Computed and returned
    in at least float32 (see the comment in ``_demod_dtype``).
    """
    if not eps > 0:
        raise JaxdenoiseError(f"demodulate: 'eps' must be > 0 (it guards zero albedo), got {eps}")
    color, albedo = _float(color), _float(albedo)
    dt = _demod_dtype(color, albedo)
    # Negative albedo is not physical; clamping at 0 keeps the denominator >= eps > 0.
    return color.astype(dt) / (jnp.maximum(albedo.astype(dt), 0.0) + eps)


def remodulate(illum: Any, albedo: Any, eps: float = ALBEDO_EPS_DEFAULT) -> jnp.ndarray:
    """Inverse of `demodulate`: ``illum * (albedo + eps)``."""
    if not eps > 0:
        raise JaxdenoiseError(f"remodulate: 'eps' must be > 0 (it must match demodulate's), got {eps}")
    illum, albedo = _float(illum), _float(albedo)
    dt = _demod_dtype(illum, albedo)
    return illum.astype(dt) * (jnp.maximum(albedo.astype(dt), 0.0) + eps)


# -- named pairs -----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Transfer:
    """A named forward/inverse pair: ``inverse(forward(x)) == x`` up to rounding."""

    name: str
    forward: Callable[..., jnp.ndarray]
    inverse: Callable[..., jnp.ndarray]

    def __call__(self, x: Any) -> jnp.ndarray:
        return self.forward(x)


def _identity(x: Any) -> jnp.ndarray:
    return _float(x)


IDENTITY = Transfer("identity", _identity, _identity)
GAMMA = Transfer("gamma", gamma, inv_gamma)
LOG = Transfer("log", log_transform, inv_log_transform)
MU_LAW = Transfer("mu-law", mu_law, inv_mu_law)
SRGB = Transfer("srgb", srgb, inv_srgb)

TRANSFERS: dict[str, Transfer] = {t.name: t for t in (IDENTITY, GAMMA, LOG, MU_LAW, SRGB)}


def radiance(c: Any) -> jnp.ndarray:
    """``c`` as float32 radiance: non-finite and negative values as 0 (how the networks and the
    exposure statistic read a colour buffer)."""
    c = jnp.asarray(c, jnp.float32)
    return jnp.where(jnp.isfinite(c), jnp.maximum(c, 0.0), 0.0)


def luminance(c: Any) -> jnp.ndarray:
    """Rec. 709 luminance of ``(..., 3)`` linear RGB: ``(...)``."""
    return 0.2126 * c[..., 0] + 0.7152 * c[..., 1] + 0.0722 * c[..., 2]


def color_mean(color: Any) -> jnp.ndarray:
    """The per-channel mean colour of a frame with every pixel whose luminance is above the frame's
    `EXPOSURE_CLIP_QUANTILE` scaled down to it (hue kept: a few fireflies or a small light do not set
    it); ``(..., H, W, 3)`` -> ``(..., 3)``. Non-finite and negative values count as 0. The training
    pipeline carries it with every crop (a per-frame statistic) and multiplies it by the crop's colour
    modulation (`jaxdenoise.pipeline.RADIANCE_STATS`), so a modulated crop is normalised by its
    modulated frame's level."""
    c = radiance(color)
    lum = luminance(c)
    flat = lum.reshape(lum.shape[:-2] + (-1,))
    clip = quantile_lower(flat, EXPOSURE_CLIP_QUANTILE)[..., None, None]  # jnp.quantile's "lower", 35x faster
    keep = jnp.where(lum > clip, clip / jnp.where(lum > clip, lum, 1.0), 1.0)
    return jnp.mean(c * keep[..., None], axis=(-3, -2))


def exposure_level(color: Any) -> jnp.ndarray:
    """The exposure statistic: the luminance of `color_mean`, i.e. the mean luminance of the frame
    with pixels above its `EXPOSURE_CLIP_QUANTILE` luminance clipped there; ``(..., H, W, 3)`` ->
    ``(..., 1)``. Homogeneous of degree 1 (a frame k times brighter has a k times larger level), so
    a method that scales by it has ``f(k x) = k f(x)`` up to rounding."""
    return luminance(color_mean(color))[..., None]


def exposure_scale(color: Any, carried_mean: Any = None) -> jnp.ndarray:
    """The factor that brings a frame to `EXPOSURE_LEVEL`: ``EXPOSURE_LEVEL / level`` with the level
    the luminance of ``carried_mean`` (a training crop's whole-frame `color_mean`) when given, else
    `exposure_level` of ``color`` itself (at inference, the whole frame); 1 for a black frame. Shaped
    ``(..., 1, 1, 1)`` to broadcast against the colour, and held constant in the gradient."""
    if carried_mean is None:
        level = exposure_level(color)
    else:
        level = luminance(jnp.asarray(carried_mean, jnp.float32))[..., None]
    level = jnp.asarray(level, jnp.float32)
    scale = jnp.where(level > 1e-12, EXPOSURE_LEVEL / jnp.maximum(level, 1e-12), 1.0)
    return jax.lax.stop_gradient(scale)[..., None, None]


def transfer(name: str) -> Transfer:
    """The registered pair called ``name`` (one of `TRANSFERS`)."""
    try:
        return TRANSFERS[name]
    except KeyError:
        raise JaxdenoiseError(f"unknown transfer '{name}'; known: {', '.join(TRANSFERS)}") from None


__all__ = [
    "ALBEDO_EPS_DEFAULT", "GAMMA_DEFAULT", "MU_DEFAULT", "Transfer", "TRANSFERS", "IDENTITY", "GAMMA",
    "LOG", "MU_LAW", "SRGB", "transfer", "srgb", "inv_srgb", "gamma", "inv_gamma", "log_transform", "inv_log_transform", "mu_law",
    "inv_mu_law", "tonemap", "demodulate", "remodulate", "radiance", "luminance", "color_mean", "exposure_level",
    "exposure_scale", "EXPOSURE_LEVEL", "EXPOSURE_CLIP_QUANTILE",
]
