"""DEMC: the dual-encoder Monte Carlo denoiser of Yang, Liu, Huo, Wang, Chen 2019 ("DEMC: A Deep
Dual-Encoder Network for Denoising Monte Carlo Rendering"), registered as ``demc``; its ablations
of Sec. 4.4 are variants of the same module (``Config.variant``): ``"semc"`` (one encoder on the
noisy colour concatenated with the fused detail map, widened to DEMC's parameter count, Fig. 4) and
``"nosn"`` (DEMC without the feature-fusion sub-network: the feature encoder reads the 12 feature
channels directly, Fig. 10 "DEMCnoSN").

Network (Sec. 3.2, Fig. 3):

- **feature fusion sub-network**: four 3x3 conv blocks on the 12 feature channels (shading normal,
  world position, first- and second-hit albedo, Sec. 3.1), the first and last conv + ReLU, the two
  middle ones conv + batch normalization + ReLU; its 3-channel output is the *detail map*;
- **two encoders**, one on the gamma-compressed noisy colour (Eq. 4), one on the detail map; each
  has five down-sampling units of three 3x3 convs + ReLU followed by 2x2 max pooling; the output of
  a unit's convs (before pooling) is its level's skip tensor;
- a **latent stage** (two 3x3 convs + ReLU) on the colour encoder's pooled output ("the
  representation of the noisy images will be used to feed into the decoder network", Sec. 3.2);
- a **decoder** of five 4x4 stride-2 deconvolutions + ReLU initialised as bilinear up-sampling; after
  each, the **skip connection** of Eq. 2: the decoder, feature-encoder and colour-encoder tensors of
  the level are concatenated and fused by a 1x1 conv + ReLU initialised by Eq. 3 (identity on the
  decoder block, zero on the encoder blocks, zero bias: a fresh fusion passes the decoder through);
- a 3x3 output conv to 3 channels, the inverse of Eq. 4 back to HDR.

Inputs and loss (Sec. 4.2): colour compressed by Eq. 4, ``x^(1/gamma)``, gamma 2.2 (negative and
non-finite radiance clamped to 0 first); the 12 features z-score normalized with the training set's
mean and standard deviation (``params["norm"]``, stored with the weights, not trained), except the
world position, normalized per frame by default (``position_norm``; docs/methods/demc.md says why
and what was measured). The per-frame mean and standard deviation of the position are those of the
whole frame in training as at inference: they are declared by `frame_stats`, computed by the
training pipeline on each whole render and carried by its crops (`jaxdenoise.pipeline`), and
`inputs` uses the carried values when given, else computes them from its array (at inference the
whole frame). With ``exposure = "frame"`` (ours, the default; the paper's input is ``"none"``) the
colour is first scaled to `jaxdenoise.color.EXPOSURE_LEVEL` by the frame's
`jaxdenoise.color.exposure_level` (a whole-frame statistic) and the output scaled back, so
``f(k x) = k f(x)``. The output mapped back by ``max(y, 0)^gamma``; loss = RelMSE in HDR with eps =
1e-3 (Eq. 5), plus (ours, ``level_weight``, 4 by default; 0 for the paper's recipe) the same
term on 8x8 block means, which keeps the colour level (docs/methods/demc.md). Xavier initialisation
of the encoder, latent and fusion convs (Sec. 4.2). The paper's channel widths are not legible:
ours are ``Config.widths`` (docs/methods/demc.md gives the parameter count). Any input size: padded
to a multiple of 32 and cropped back. At inference (ours, `demc`'s shipped settings, `apply`): exact
pixels kept (``keep_exact``), a feature-guided cross-bilateral refinement of the output
(``refine_sigma``, `jaxdenoise.filters.refine`), the colour level put at the input's (``match_level``).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import nn
from ..buffers import Buffers
from .. import color as color_ops
from ..color import gamma
from ..nn.state import call
from ..errors import JaxdenoiseError
from ..filters import (check_exact_window, check_match_settings, check_refine_settings, exact_mask, match_to_input,
                       refine)
from ..pipeline import carried_stat, carried_stats

__all__ = ["Config", "needs", "required", "keep_exact_pixels", "exact_pixels", "match_input_level",
           "refine_output", "init",
           "init_from_data", "apply", "forward", "loss", "relative_loss", "make_dataset", "batch", "inputs",
           "frame_stats", "position_moments", "exposure_scale", "num_params", "widths_of", "FEATURES", "TRAIN",
           "FROZEN", "WEIGHTS"]
# Pixels of context a tile needs on each side (`jaxdenoise.tiling`): the smallest margin whose max
# |tiled - whole| / (|whole| + 0.01) on a real frame is below 5e-3 (docs/results/tiling/, re-measured at
# 0.9.24: 7.8e-4 and RelMSE +0.00 % at 128 px, 6.0e-3 and -0.01 % at 96, 8.1e-2 and -0.15 % at 64; the
# 0.8.x weights: 1.3e-3 / 1.9e-3 at 128, 1.0e-2 / 1.4e-2 at 96); the paper-recipe weights needed 96.
TILE_MARGIN = 128

EXPOSURES = ("none", "frame")
RECIPES = ("", "paper")
SKIP_INITS = ("decoder", "all")
LOSS_SCALES = ("reference", "output")

# The 12 feature channels of Sec. 3.1, in the order they are stacked.
FEATURES: tuple[str, ...] = ("normal", "position", "albedo", "albedo2")
VARIANTS = ("demc", "semc", "nosn")


@dataclasses.dataclass(frozen=True)
class Config:
    """DEMC hyperparameters; paper values cited, our choices marked (docs/methods/demc.md)."""

    variant: str = "demc"  # "demc" (Fig. 3), "semc" (Fig. 4), "nosn" (Fig. 10 DEMCnoSN)
    widths: tuple[int, ...] = (24, 32, 48, 64, 96)  # channels of the five down-sampling units (ours)
    fusion_width: int = 24  # channels inside the fusion sub-network (ours)
    convs_per_unit: int = 3  # "three convolutional layers followed by a max-pooling layer" (Sec. 3.2)
    latent_convs: int = 2  # the latent stage (ours: the count is not stated)
    gamma: float = 2.2  # Eq. 4 (Sec. 4.2)
    eps: float = 1e-3  # Eq. 5 (Sec. 4.2)
    position_norm: str = "frame"  # "frame" (per-frame z-score) or "global" (training-set z-score)
    bn_momentum: float = 0.9  # running statistics of the fusion sub-network's BatchNorm (ours)
    xavier_gain: float = 1.0  # Xavier (Sec. 4.2) = 1; 2 is the ReLU-compensated variant (measured, demc.md)
    # "frame": the colour scaled to EXPOSURE_LEVEL by a frame statistic (ours, `exposure_level`); "none":
    # as the paper. Weights may be fine-tuned across a change of it (it changes no parameter's shape).
    exposure: str = dataclasses.field(default="frame", metadata={"fine_tune": True})
    # Training data (Sec. 4.1: 4-spp inputs; ours: 1-64); crop and batch are ours, sized to the machine.
    train_spps: tuple[int, ...] = (1, 4, 16, 64)  # ours; the paper's recipe trains at 4 (`recipe`)
    # The training recipe the weights folder is named after: "" (the default weights: every rate,
    # exposure "frame") or "paper" (Sec. 4.1: 4 spp, the paper's input; registered as "demc-paper").
    recipe: str = dataclasses.field(default="", metadata={"training": True})
    # Eq. 3's reading (the equation is garbled in the text, docs/methods/demc.md): "decoder" inits each
    # skip fusion as [I, 0, 0] (identity on the decoder block, zero on the encoder blocks); "all" as
    # [I, I, I] (the sum of the three blocks, Mao et al.'s additive skips). Zero bias either way.
    skip_init: str = dataclasses.field(default="decoder", metadata={"training": True})
    # The loss's per-pixel scale: "reference" is Eq. 5 (divided by r^2 + eps); "output" divides by the
    # output's own (y^2 + eps), held constant in the gradient (Lehtinen et al. 2018's relative MSE for
    # noisy targets: its stationary point is the conditional mean, where Eq. 5's is darker).
    loss_scale: str = dataclasses.field(default="reference", metadata={"training": True})
    # A level term beside Eq. 5 (ours, issue 33): `level_weight` times the same relative MSE between
    # `level_pool` x `level_pool` block means of output and reference; 0 = Eq. 5 alone. A block's mean
    # is nearly fixed by the input, so its reference-weighted error has no pull toward dark
    # references, and it counteracts the per-pixel term's (docs/methods/demc.md).
    level_weight: float = dataclasses.field(default=4.0, metadata={"training": True})
    level_pool: int = dataclasses.field(default=8, metadata={"training": True})
    # The level term's scale (ours, issue 33): "reference" divides a block's error by the reference
    # block's square (as Eq. 5); "output" by the output block's, held constant in the gradient, so the
    # term's optimum is the mean of the block means an input admits (at 1 spp still uncertain) while
    # the per-pixel term stays Eq. 5.
    level_scale: str = dataclasses.field(default="reference", metadata={"training": True})
    # Pixels whose samples all agreed (ours, issue 33; docs/methods/demc.md "Exact pixels"): with
    # `keep_exact`, a pixel of a frame of >= 2 spp whose colour variance is 0 in every channel and whose
    # colour is not black keeps its input (a directly seen emitter, a constant background): its
    # estimate has no noise to remove. Reads `color_var` where the frame has it; inference only.
    # A frame with no variance to read (1 spp, or none written) has its pixels kept instead where the
    # whole `exact_window` x `exact_window` square around them has bit-for-bit the same lit colour
    # (0: not at all): independent samples of a noisy estimate never agree so, a directly seen
    # uniform emitter's interior or a constant background does.
    keep_exact: bool = dataclasses.field(default=False, metadata={"fine_tune": True})
    exact_window: int = dataclasses.field(default=0, metadata={"fine_tune": True})
    # The colour level at inference (ours, issue 33; docs/methods/demc.md "Colour level at inference"):
    # with `match_level` > 0 the output's level, averaged by a Gaussian of that many pixels, is put at
    # the noisy input's (`jaxdenoise.filters.match_to_input`: the input with its outliers cut at
    # `match_spike` times their 3x3 median luminance, in the exposure-scaled units), the gain limited
    # to [1 / `match_max_gain`, `match_max_gain`] (0: no limit); 0: the network's own level. With
    # `match_spike_by_rate` the cut scales with the frame's noise: `match_spike` is one sample's factor
    # and a frame of n spp is cut at 1 + (match_spike - 1) / sqrt(n) (a frame without `spp`: match_spike).
    # Inference only.
    match_level: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    match_spike: float = dataclasses.field(default=4.0, metadata={"fine_tune": True})
    match_max_gain: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})  # 0: no limit
    match_spike_by_rate: bool = dataclasses.field(default=False, metadata={"fine_tune": True})
    # Refinement (ours, issue 33; docs/methods/demc.md "Refinement"): with `refine_sigma` > 0 the output
    # (exact pixels kept) goes through `jaxdenoise.filters.refine`, a cross-bilateral pass guided by the
    # first-hit albedo and normal (bandwidths `refine_albedo`, `refine_normal`) with a range term relative
    # to the pixels' brightness (`refine_range`) over a Gaussian of `refine_sigma` pixels, before the level
    # match; 0: off. Inference only.
    refine_sigma: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    refine_range: float = dataclasses.field(default=0.4, metadata={"fine_tune": True})
    refine_albedo: float = dataclasses.field(default=0.03, metadata={"fine_tune": True})
    refine_normal: float = dataclasses.field(default=0.1, metadata={"fine_tune": True})
    train_crop: int = 96
    train_batch: int = 32


# Adam (Sec. 4.2; the learning-rate range is not legible: 1e-4 with a slow exponential decay, ours).
TRAIN: dict[str, Any] = {"optimizer": "adam", "learning_rate": 1e-4, "schedule": "exponential",
                         "schedule_every": 10000, "schedule_factor": 0.5, "steps": 2000, "checkpoint_every": 100}
FROZEN: tuple[str, ...] = ("norm",)


def WEIGHTS(config: Config) -> str:
    name = "demc" if config.variant == "demc" else f"demc-{config.variant}"
    return f"{name}-{config.recipe}" if config.recipe else name


def _check(config: Config) -> None:
    if config.variant not in VARIANTS:
        raise JaxdenoiseError(f"demc: config.variant is {config.variant!r}; expected one of {VARIANTS}")
    if len(config.widths) != 5 or any(int(w) < 1 for w in config.widths):
        raise JaxdenoiseError(f"demc: config.widths must be five positive channel counts (five down-sampling "
                         f"units, Sec. 3.2), got {config.widths}")
    if config.position_norm not in ("frame", "global"):
        raise JaxdenoiseError(f"demc: config.position_norm is {config.position_norm!r}; expected 'frame' or 'global'")
    if config.recipe not in RECIPES:
        raise JaxdenoiseError(f"demc: config.recipe is {config.recipe!r}; expected one of {RECIPES}")
    if config.skip_init not in SKIP_INITS:
        raise JaxdenoiseError(f"demc: config.skip_init is {config.skip_init!r}; expected one of {SKIP_INITS}")
    if config.loss_scale not in LOSS_SCALES:
        raise JaxdenoiseError(f"demc: config.loss_scale is {config.loss_scale!r}; expected one of {LOSS_SCALES}")
    if config.level_scale not in LOSS_SCALES:
        raise JaxdenoiseError(f"demc: config.level_scale is {config.level_scale!r}; expected one of {LOSS_SCALES}")
    if not config.level_weight >= 0 or int(config.level_pool) < 1:
        raise JaxdenoiseError(f"demc: config.level_weight must be >= 0 and config.level_pool >= 1, got "
                              f"{config.level_weight!r} and {config.level_pool!r}")
    if config.exposure not in EXPOSURES:
        raise JaxdenoiseError(f"demc: config.exposure is {config.exposure!r}; expected one of {EXPOSURES}")
    if not config.gamma > 0:
        raise JaxdenoiseError(f"demc: config.gamma must be > 0, got {config.gamma}")
    if config.refine_sigma:
        check_refine_settings("demc: config.", config.refine_sigma, config.refine_range, config.refine_albedo,
                              config.refine_normal)
    check_match_settings("demc: config.", config.match_level, config.match_spike, config.match_max_gain,
                         config.match_spike_by_rate)
    check_exact_window("demc: config.exact_window", config.exact_window)


def needs(config: Config) -> frozenset[str]:
    """The noisy colour and the four features of Sec. 3.1; with ``keep_exact`` the colour variance."""
    return frozenset({"color", *FEATURES} | ({"color_var"} if config.keep_exact else set()))


def required(config: Config) -> frozenset[str]:
    """`needs` without the colour variance (a 1-spp frame has none; `keep_exact` then does nothing)."""
    return needs(config) - {"color_var"}


# -- network -------------------------------------------------------------------------------------

def _relu():
    return nn.Relu()


def _conv(c, k=3, gain=1.0, **kw):
    return nn.Conv(c, k, w_init=nn.glorot_uniform_init(gain), **kw)


def _fusion(config: Config):
    f, g = config.fusion_width, config.xavier_gain
    return nn.serial(_conv(f, gain=g), _relu(),
                     _conv(f, gain=g, bias=False), nn.BatchNorm(config.bn_momentum), _relu(),
                     _conv(f, gain=g, bias=False), nn.BatchNorm(config.bn_momentum), _relu(),
                     _conv(3, gain=g), _relu())


def _unit(c: int, n: int, gain: float):
    layers = []
    for _ in range(n):
        layers += [_conv(c, gain=gain), _relu()]
    return nn.serial(*layers)


def widths_of(config: Config) -> tuple[int, ...]:
    """The encoder widths actually built: ``config.widths``, or for SEMC the same widths scaled so
    that the single-encoder network has DEMC's parameter count (Sec. 4.4, Fig. 4)."""
    _check(config)
    if config.variant != "semc":
        return tuple(int(w) for w in config.widths)
    return _semc_widths(config)


@functools.lru_cache(maxsize=16)
def _semc_widths(config: Config) -> tuple[int, ...]:
    target = num_params(dataclasses.replace(config, variant="demc"))
    best = None
    for s in np.arange(1.0, 2.0, 0.005):
        ws = tuple(max(1, int(round(w * s))) for w in config.widths)
        n = _count(config, ws)
        if best is None or abs(n - target) < abs(best[1] - target):
            best = (ws, n)
    return best[0]


def _layers(config: Config, widths: tuple[int, ...]) -> dict:
    L = len(widths)
    dual = config.variant in ("demc", "nosn")
    ways = 3 if dual else 2
    g = config.xavier_gain
    skip = (1.0,) + ((0.0,) if config.skip_init == "decoder" else (1.0,)) * (ways - 1)  # Eq. 3
    layers = {"enc_c": [_unit(w, config.convs_per_unit, g) for w in widths],
              "latent": _unit(widths[-1], config.latent_convs, g),
              "up": [nn.serial(nn.ConvTranspose(widths[i], 4, stride=2, w_init=nn.bilinear_init(2)), _relu())
                     for i in range(L)],
              "fuse": [nn.serial(nn.Conv(widths[i], 1, w_init=nn.identity_init(skip)),
                                 _relu()) for i in range(L)],
              "out": _conv(3, gain=g)}
    if dual:
        layers["enc_f"] = [_unit(w, config.convs_per_unit, g) for w in widths]
    if config.variant != "nosn":
        layers["fusion"] = _fusion(config)
    return layers


def _init_net(key, config: Config, widths: tuple[int, ...]) -> dict:
    layers = _layers(config, widths)
    L = len(widths)
    keys = iter(jax.random.split(key, 4 * L + 4))
    params: dict = {}
    cf = 12 if config.variant == "nosn" else 3
    if "fusion" in layers:
        params["fusion"] = layers["fusion"][0](next(keys), (-1, 32, 32, 12))[1]
    cin_c = 6 if config.variant == "semc" else 3
    enc_c, enc_f, c_prev_c, c_prev_f = {}, {}, cin_c, cf
    for i, w in enumerate(widths):
        enc_c[str(i)] = layers["enc_c"][i][0](next(keys), (-1, 32, 32, c_prev_c))[1]
        c_prev_c = w
        if "enc_f" in layers:
            enc_f[str(i)] = layers["enc_f"][i][0](next(keys), (-1, 32, 32, c_prev_f))[1]
            c_prev_f = w
    params["enc_c"] = enc_c
    if enc_f:
        params["enc_f"] = enc_f
    params["latent"] = layers["latent"][0](next(keys), (-1, 1, 1, widths[-1]))[1]
    ways = 3 if "enc_f" in layers else 2
    up, fuse = {}, {}
    c = widths[-1]
    for i in reversed(range(L)):
        up[str(i)] = layers["up"][i][0](next(keys), (-1, 1, 1, c))[1]
        fuse[str(i)] = layers["fuse"][i][0](next(keys), (-1, 2, 2, ways * widths[i]))[1]
        c = widths[i]
    params["up"], params["fuse"] = up, fuse
    params["out"] = layers["out"][0](next(keys), (-1, 32, 32, widths[0]))[1]
    return params


def _count(config: Config, widths: tuple[int, ...]) -> int:
    shapes = jax.eval_shape(lambda k: _init_net(k, config, widths), jax.random.PRNGKey(0))
    return int(sum(np.prod(s.shape) for s in jax.tree_util.tree_leaves(shapes)))


def num_params(config: Config) -> int:
    """Trainable parameters plus BatchNorm running statistics, without ``norm`` (12 x 2 values)."""
    return _count(config, widths_of(config))


def init(key, config: Config) -> dict:
    """Fresh params; ``norm`` holds identity statistics until `init_from_data` measures them."""
    params = _init_net(key, config, widths_of(config))
    params["norm"] = {"mean": jnp.zeros((12,), jnp.float32), "std": jnp.ones((12,), jnp.float32)}
    return params


def forward(params: dict, x_color: jax.Array, x_feat: jax.Array, config: Config, train: bool = False):
    """The network on prepared inputs (`inputs`): ``(..., H, W, 3)`` compressed colour and
    ``(..., H, W, 12)`` normalized features, H and W multiples of 32; returns the network's linear
    output in the compressed domain (and, with ``train``, the BatchNorm updates)."""
    widths = widths_of(config)
    layers = _layers(config, widths)
    L = len(widths)
    updates: dict = {}
    if "fusion" in layers:
        detail = call(layers["fusion"][1], params["fusion"], x_feat, train, updates, "fusion")
    else:
        detail = x_feat
    pool = nn.MaxPool(2)[1]
    h_c = jnp.concatenate([x_color, detail], -1) if config.variant == "semc" else x_color
    h_f = detail
    skips_c, skips_f = [], []
    for i in range(L):
        h_c = layers["enc_c"][i][1](params["enc_c"][str(i)], h_c)
        skips_c.append(h_c)
        h_c = pool({}, h_c)
        if "enc_f" in layers:
            h_f = layers["enc_f"][i][1](params["enc_f"][str(i)], h_f)
            skips_f.append(h_f)
            h_f = pool({}, h_f)
    g = layers["latent"][1](params["latent"], h_c)
    for i in reversed(range(L)):
        g = layers["up"][i][1](params["up"][str(i)], g)
        parts = [g, skips_f[i], skips_c[i]] if skips_f else [g, skips_c[i]]
        g = layers["fuse"][i][1](params["fuse"][str(i)], jnp.concatenate(parts, -1))
    y = layers["out"][1](params["out"], g)
    return (y, updates) if train else y


def _getter(buffers: Any, optional: bool = False):
    """A field reader for a `Buffers` or a dict frame; ``optional``: None for a field it lacks."""
    if isinstance(buffers, Buffers):
        return lambda f: getattr(buffers, f, None)
    return buffers.get if optional else (lambda f: buffers[f])


def position_moments(p: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mean and standard deviation of the world position ``(..., H, W, 3)`` over the image, per
    channel: two ``(..., 3)`` arrays (the standard deviation with 1e-8 under the root)."""
    mu = jnp.mean(p, axis=(-3, -2), keepdims=True)
    sd = jnp.sqrt(jnp.mean(jnp.square(p - mu), axis=(-3, -2), keepdims=True) + 1e-8)
    return mu[..., 0, 0, :], sd[..., 0, 0, :]


def frame_stats(config: Config) -> dict:
    """The per-frame statistics of `inputs` (`jaxdenoise.methods.protocol`): with ``position_norm =
    "frame"`` the world position's mean and standard deviation over the whole frame
    (`position_moments`), with ``exposure = "frame"`` the colour's `color_mean`; the training
    pipeline computes them on every whole render and carries them with its crops."""
    _check(config)
    stats = {}
    if config.exposure == "frame":
        stats["color_mean"] = lambda frame: color_ops.color_mean(_getter(frame)("color"))
    if config.position_norm != "frame":
        return stats

    def moments(frame):  # the position as `inputs` reads it (float32, non-finite values 0)
        p = jnp.asarray(_getter(frame)("position"), jnp.float32)
        return position_moments(jnp.where(jnp.isfinite(p), p, 0.0))

    return {**stats, "position_mean": lambda frame: moments(frame)[0],
            "position_std": lambda frame: moments(frame)[1]}


def exposure_scale(buffers: Any, config: Config) -> jax.Array:
    """The factor `inputs` multiplies the colour by (1 with ``exposure = "none"``): `EXPOSURE_LEVEL`
    over the frame's `jaxdenoise.color.exposure_level` (that of a crop's carried ``color_mean``, else
    the array's own), `jaxdenoise.color.exposure_scale`."""
    if config.exposure == "none":
        return jnp.ones((), jnp.float32)
    return color_ops.exposure_scale(_getter(buffers)("color"), carried_stat(buffers, "color_mean"))


def inputs(params: dict, buffers: Any, config: Config) -> tuple[jax.Array, jax.Array]:
    """Eq. 4 on the colour and the z-score of the features (Sec. 4.2) for a `Buffers` or a batch dict
    with the same field names; any leading axes. The world position's per-frame mean and standard
    deviation (``position_norm = "frame"``) are those a training crop carries (``stat.position_mean``,
    ``stat.position_std``: its whole render's, `frame_stats`), else those of the array itself (at
    inference, the whole frame)."""
    get = _getter(buffers)
    color = color_ops.radiance(get("color")) * exposure_scale(buffers, config)
    x_color = gamma(color, config.gamma)  # color ** (1 / gamma), with a finite gradient at 0 (Dr.Jit bridge)
    feats = jnp.concatenate([jnp.asarray(get(f), jnp.float32) for f in FEATURES], -1)
    feats = jnp.where(jnp.isfinite(feats), feats, 0.0)
    sg = jax.lax.stop_gradient  # statistics, never trained (FROZEN)
    mean, std = sg(params["norm"]["mean"]), sg(params["norm"]["std"])
    x_feat = (feats - mean) / jnp.maximum(std, 1e-6)
    if config.position_norm == "frame":
        p = feats[..., 3:6]
        mu, sd = carried_stat(buffers, "position_mean"), carried_stat(buffers, "position_std")
        if mu is None or sd is None:
            mu, sd = position_moments(p)
        mu = jnp.asarray(mu, jnp.float32)[..., None, None, :]
        sd = jnp.asarray(sd, jnp.float32)[..., None, None, :]
        x_feat = x_feat.at[..., 3:6].set((p - mu) / jnp.maximum(sd, 1e-3))
    return x_color, x_feat


def _decompress(y: jax.Array, config: Config) -> jax.Array:
    return jnp.power(jnp.maximum(y, 0.0), config.gamma)


def _run(params, buffers, config, train=False):
    x_color, x_feat = inputs(params, buffers, config)
    x_color, size = nn.pad_to_multiple(x_color, 32)
    x_feat, _ = nn.pad_to_multiple(x_feat, 32)
    out = forward(params, x_color, x_feat, config, train=train)
    unscale = 1.0 / exposure_scale(buffers, config)  # back to the frame's own exposure
    if train:
        y, updates = out
        return _decompress(nn.crop_to(y, size), config) * unscale, updates
    return _decompress(nn.crop_to(out, size), config) * unscale


def apply(params: dict, buffers: Buffers, config: Config) -> jax.Array:
    """Denoise one frame or a batch (leading axes): HDR ``(..., H, W, 3)`` (inference mode: the
    BatchNorm running statistics); with ``keep_exact``, `keep_exact_pixels`; with ``refine_sigma``,
    `refine_output`; with ``match_level``, `match_input_level` (exact pixels kept before and after, so
    a network's error on them moves no level around them)."""
    out = _run(params, buffers, config)
    exact = None
    if config.keep_exact:
        exact, color = exact_pixels(buffers, config.exact_window, out.dtype)
        out = jnp.where(exact, color, out)
    if config.refine_sigma:
        out = refine_output(out, buffers, config)
    if config.match_level:
        out = match_input_level(out, buffers, config)
    if exact is not None and (config.refine_sigma or config.match_level):
        out = jnp.where(exact, color, out)
    return out


def refine_output(out: jax.Array, buffers: Any, config: Config) -> jax.Array:
    """``out`` through `jaxdenoise.filters.refine` with ``config``'s ``refine_*`` settings, guided by
    the frame's albedo and normal, in the exposure-scaled units of `inputs` (so ``f(k x) = k f(x)``
    still holds). Any leading axes."""
    scale = exposure_scale(buffers, config)
    get = _getter(buffers)
    return refine(out * scale, get("albedo"), get("normal"), sigma=config.refine_sigma,
                  range_sigma=config.refine_range, albedo_sigma=config.refine_albedo,
                  normal_sigma=config.refine_normal) / scale


def match_input_level(out: jax.Array, buffers: Any, config: Config) -> jax.Array:
    """``out`` with its level, low-passed by a Gaussian of ``config.match_level`` pixels, put at the
    input colour's (`Config.match_level`): `jaxdenoise.filters.match_to_input` (spike factor
    ``config.match_spike``, by the frame's ``spp`` with ``match_spike_by_rate``, floor
    `jaxdenoise.color.EXPOSURE_LEVEL`) on output and input in the exposure-scaled units of `inputs`,
    so ``f(k x) = k f(x)`` still holds. Any leading axes."""
    scale = exposure_scale(buffers, config)  # (..., 1, 1, 1)
    get = _getter(buffers, optional=True)
    color = color_ops.radiance(get("color")) * scale
    spp = get("spp") if config.match_spike_by_rate else None
    return match_to_input(out * scale, color, config.match_level, spike=config.match_spike,
                          floor=color_ops.EXPOSURE_LEVEL, max_gain=config.match_max_gain or float("inf"),
                          spp=spp) / scale


def keep_exact_pixels(out: jax.Array, buffers: Any, window: int = 0) -> jax.Array:
    """``out`` with the input's colour where the frame says a pixel's estimate is exact
    (`Config.keep_exact`): in a frame of ``spp`` >= 2 with ``color_var``, a pixel whose variance is 0
    in every channel (its samples all agreed); in any other frame, with ``window`` > 0, a pixel whose
    ``window`` x ``window`` square (the frame's border repeated outward) holds bit-for-bit its colour
    in every pixel (independent samples agreed). Kept pixels are lit (not black) and finite. By the Buffers
    contract (``color_var``: the variance of the pixel's samples) the first rule keeps exact
    estimates; a renderer that writes 0 for an unknown variance would have every lit pixel kept."""
    exact, c = exact_pixels(buffers, window, out.dtype)
    return jnp.where(exact, c, out)


def exact_pixels(buffers: Any, window: int = 0, dtype: Any = jnp.float32) -> tuple[jax.Array, jax.Array]:
    """The mask ``(..., H, W, 1)`` of the pixels `keep_exact_pixels` keeps
    (`jaxdenoise.filters.exact_mask` of the frame's ``color``, ``color_var`` and ``spp``), and the
    colour (as ``dtype``) they keep."""
    get = _getter(buffers, optional=True)
    c = jnp.asarray(get("color"), dtype)
    return exact_mask(c, get("color_var"), get("spp"), window=window), c


def loss(params: dict, batch: dict, config: Config):
    """Eq. 5: RelMSE in HDR, ``mean((y - r)^2 / (r^2 + eps))`` over pixels and channels, with the
    fusion sub-network's BatchNorm in training mode (its new running statistics as aux updates).
    With ``loss_scale = "output"`` the denominator is ``sg(y)^2 + eps`` (``sg``: no gradient): a
    reference-weighted loss is minimised below the mean of the references an input admits (dark
    ones weigh more), an output-weighted one at their mean (docs/methods/demc.md)."""
    out, updates = _run(params, batch, config, train=True)
    return relative_loss(out, batch["reference"], config), {"updates": updates}


def relative_loss(out: jax.Array, ref: jax.Array, config: Config) -> jax.Array:
    """The loss of `loss` on HDR output and reference ``(..., H, W, 3)``: ``mean((y - r)^2 / (s^2 +
    eps))`` with ``s`` the reference (Eq. 5) or, for ``loss_scale = "output"``, the output without
    its gradient; plus ``level_weight`` times the same term on ``level_pool``-pixel block means, scaled
    as ``level_scale`` says (`Config.level_weight`, `Config.level_scale`)."""
    def rel(y, r, kind):
        scale = r if kind == "reference" else jax.lax.stop_gradient(y)
        return jnp.mean(jnp.square(y - r) / (jnp.square(scale) + config.eps))

    value = rel(out, ref, config.loss_scale)
    if config.level_weight:
        blocks = [nn.block_means(a, config.level_pool) for a in (out, ref)]
        value = value + config.level_weight * rel(*blocks, config.level_scale)
    return value


# -- training data ---------------------------------------------------------------------------------

def make_dataset(data_dir, config: Config, *, progress: bool = True):
    """The training renders at ``train_spps`` with their references: a data_gen folder (decoded
    once into the pipeline cache) or an export ``.npz`` (`jaxdenoise.pipeline.open_training_data`)."""
    from ..pipeline import open_training_data

    _check(config)
    return open_training_data(data_dir, FEATURES, spps=config.train_spps, progress=progress,
                              stats=frame_stats(config))


def batch(dataset, step: int, config: Config, rng: np.random.Generator) -> dict:
    """``train_batch`` random ``train_crop`` crops at ``train_spps``, augmented as the pipeline does
    (quarter turns, mirror, colour modulation; world-space features unchanged), with the per-frame
    statistics of each crop's whole render (`frame_stats`)."""
    b = dataset.crops(config.train_batch, config.train_crop, rng, spps=config.train_spps)
    return {**{k: b[k] for k in ("color", *FEATURES, "reference")}, **carried_stats(b)}


def init_from_data(key, config: Config, dataset) -> dict:
    """`init` with the features' training-set mean and standard deviation (Sec. 4.2: z-score),
    measured on 64 unaugmented crops drawn with a fixed seed."""
    params = init(key, config)
    b = dataset.crops(64, max(config.train_crop, 64), np.random.default_rng(12345), spps=config.train_spps,
                      augment=False)
    feats = np.concatenate([np.asarray(b[f], np.float64) for f in FEATURES], -1).reshape(-1, 12)
    params["norm"] = {"mean": jnp.asarray(feats.mean(0), jnp.float32),
                      "std": jnp.asarray(np.maximum(feats.std(0), 1e-6), jnp.float32)}
    return params
