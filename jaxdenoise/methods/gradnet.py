"""GradNet: unsupervised deep screened-Poisson reconstruction of Guo, Li, Zhang, Xu 2019 ("GradNet:
Unsupervised Deep Screened Poisson Reconstruction for Gradient-Domain Rendering"), registered as
``gradnet``.

Inputs (Sec. 4.1, 5.1): the noisy base image ``I_b`` (``color``), the gradients ``dx``, ``dy``
(data_gen's convention ``I[x+1] - I[x]``), and the features albedo, normal mapped by ``(N + 1)/2``,
depth scaled linearly to [0, 1] (divided by the frame's largest finite depth): 7 feature channels.
The largest depth is that of the whole frame in training as at inference: declared by
`frame_stats`, computed by the training pipeline on each whole render and carried by its crops
(`jaxdenoise.pipeline`); `inputs` uses the carried value when given, else the array's own (at
inference, the whole frame).
HDR images enter through the mu-law of Eq. 6 (mu = 16, sign-preserving on the gradients:
`jaxdenoise.color.mu_law`) and the output leaves through its inverse.

Network (Sec. 4.4, Fig. 4):

- a **data branch** on ``T(I_b)`` and the features (10 channels) and a **gradient branch** on
  ``T(dx), T(dy)`` (6 channels), each three 3x3 stride-2 convolutions with the channels doubling
  (``Config.widths``, ours);
- their outputs concatenated and fed to **4 residual blocks** (two 3x3 convs, a leaky ReLU between
  them, a residual connection);
- a **decoder** of 4x4 stride-2 deconvolutions with the **dual skip connections** of Eq. 12: level
  ``l`` deconvolves the concatenation of the previous decoder tensor and the data- and
  gradient-branch tensors of the same resolution; three deconvolutions bring the 1/8 resolution back
  to full resolution; the last one's 24 channels are joined with the two branches' full-resolution
  inputs and a 3x3 conv without activation, **zero-initialised**, gives the 3 output channels
  (``Config.input_skip``, ours: the U-Net input level; without it, the network first built here,
  the last deconvolution gives the output and the network did not learn: docs/methods/gradnet.md);
- the output is *added* to ``T(I_b)`` (ours: Fig. 4 draws ``I_b`` and a ``+`` at the output; a
  residual to the base image also starts training from the base, docs/methods/gradnet.md);
- a **G-branch** of three 3x3 convs on the data-branch input producing, per pixel, the 7 x 3
  first-order derivatives ``G`` used by L_1st (input and width ours), the last without activation;
- leaky ReLU slope 0.01 everywhere else; He initialisation (Sec. 5.2) except the output conv.

Losses (Sec. 4.3), all unsupervised (no reference is read), all in the mu-law domain: ``L_data``
(Eq. 8), ``L_grad`` (Eq. 9), ``L_1st`` (Eq. 10: 4-neighbourhood, ``w_ij = exp(-|T(I_b,i) -
T(I_b,j)|^2 / (2 sigma_b^2))``, sigma_b^2 = 1/18, ``I_b`` mu-law compressed: our reading,
docs/methods/gradnet.md), and the G-branch's Eq. 11 on the base image; ``L_all = L_grad +
alpha L_data + lambda L_1st`` with alpha = 1 and the lambda schedule of Eq. 14 restated in steps.
The autoencoder and the G-branch are separate parameter groups updated in alternation by the
trainer (step t updates group t mod 2). Post-processing (Sec. 4.5, Eq. 13):
``I <- (I_b * k) / (I * k) . I`` with a Gaussian ``k`` (radius 45, sigma 15), on by default.
Any input size (padded to a multiple of 8 and cropped back).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import nn
from ..buffers import EMISSION_FIELD, PRIMALS, Buffers
from ..color import inv_log_transform, inv_mu_law, log_transform, mu_law
from ..filters import gaussian
from ..errors import JaxdenoiseError
from ..pipeline import carried_stat, carried_stats

__all__ = ["Config", "needs", "init", "apply", "forward", "loss", "loss_terms", "make_dataset", "batch",
           "param_groups", "group_train", "inputs", "frame_stats", "depth_max", "predict", "g_branch",
           "features", "postprocess", "lambda_at", "validation_loss",
           "first_order_weights", "first_order_loss", "grad_loss", "num_params", "is_illegal", "output_terms", "TRAIN", "WEIGHTS", "FEATURES"]
# Pixels of context a tile needs on each side (`jaxdenoise.tiling`): the smallest margin whose max
# |tiled - whole| / (|whole| + 0.01) on a real frame is below 5e-3 (docs/results/tiling/, re-measured at
# 0.9.24: 4.3e-4 and RelMSE -0.00 % at 64 px, against 4.3e-2 at 32).
TILE_MARGIN = 64

FEATURES: tuple[str, ...] = ("albedo", "normal", "depth")  # 3 + 3 + 1 = 7 channels (Sec. 4.3.3)
N_FEAT = 7
STRIDE = 8  # three stride-2 convolutions


def _training(default: Any) -> Any:
    """A config field that shapes training only (`jaxdenoise.train`: ``init_from`` may differ in it)."""
    return dataclasses.field(default=default, metadata={"training": True})


@dataclasses.dataclass(frozen=True)
class Config:
    """GradNet hyperparameters; paper values cited, our choices marked (docs/methods/gradnet.md)."""

    widths: tuple[int, ...] = (24, 48, 96)  # channels of the three stride-2 convs per branch (ours)
    res_blocks: int = 4  # Sec. 4.4
    g_width: int = 32  # the G-branch's hidden width (ours)
    slope: float = 0.01  # leaky ReLU (Sec. 4.4)
    mu: float = 16.0  # Eq. 6 (Sec. 4.2)
    compression: str = "mu-law"  # "mu-law" (Eq. 6) or "log" (log(1 + |I|): the Fig. 17 comparison)
    # The loss (Sec. 4.3) and its schedule: training-only, so weights fine-tune under other values.
    first_order: bool = _training(True)  # False: L_data + L_grad only (the Fig. 12 ablation)
    alpha: float = _training(1.0)  # Eq. 7 (Sec. 5.2)
    sigma_b2: float = _training(1.0 / 18.0)  # w_ij bandwidth (Sec. 4.3.3)
    lambda_start: float = _training(0.1)  # Eq. 14
    lambda_growth: float = _training(1.1)  # Eq. 14
    lambda_max: float = _training(2.0)  # Eq. 14
    lambda_epochs: int = _training(5)  # Eq. 14: lambda = 0 up to this epoch
    # The residual block (Sec. 4.4 / Fig. 4): True applies an LReLU after the skip sum as well as between
    # the two convs (our first reading); False only between them (Fig. 4's caption: one LReLU per block).
    res_act_after_sum: bool = True
    # Eq. 10's w_ij: on the compressed base T(I_b) ("compressed", our first reading) or on I_b itself
    # ("hdr": the equation writes no T there). Training-only (the loss).
    weights_domain: str = _training("compressed")
    residual_output: bool = True  # output = T(I_b) + decoder (ours, docs/methods/gradnet.md)
    input_skip: bool = True  # the decoder's last level joins the full-resolution inputs (ours, docs/methods/gradnet.md)
    head_width: int = 0  # > 0: a full-resolution hidden layer beside the output conv (ours, docs/methods/gradnet.md)
    postprocess: bool = True  # Eq. 13 (Sec. 4.5); off for the ablation
    pp_radius: int = 45  # Sec. 4.5
    pp_sigma: float = 15.0  # Sec. 4.5
    # Training (Sec. 5.1-5.2, restated for this machine; docs/methods/gradnet.md):
    train_spps: tuple[int, ...] = (64,)  # the paper's 64-spp G-PT renders (16/64/256 measured worse: docs/methods/gradnet.md)
    train_crop: int = 64  # the paper's patches are 256x256 (out of reach here)
    train_batch: int = 8  # the paper's 32 (out of reach on 2 CPU cores)
    epoch_patches: int = 2560  # patches per "epoch" (ours; the paper: 11,785); sets Eq. 14 and the lr decay
    # What I_b of the training renders must be (the header's ``primal``, data_gen --primal): "gpt", the
    # G-PT primal of Kettunen's tracer that the paper trains on (Sec. 5.1), or "base" (the plain
    # path-traced base: the shipped weights up to 0.9.1). A render of the other kind is refused.
    train_primal: str = "gpt"

    def __post_init__(self) -> None:
        if len(self.widths) != 3 or any(int(w) < 1 for w in self.widths):
            raise JaxdenoiseError(f"gradnet: config.widths must be 3 positive ints (three stride-2 convs), got {self.widths}")
        if int(self.head_width) < 0 or (self.head_width and not self.input_skip):
            raise JaxdenoiseError(f"gradnet: config.head_width must be >= 0 and needs input_skip, got {self.head_width}")
        if self.weights_domain not in ("compressed", "hdr"):
            raise JaxdenoiseError(f"gradnet: config.weights_domain must be 'compressed' or 'hdr', got {self.weights_domain!r}")
        if self.train_primal not in PRIMALS:
            raise JaxdenoiseError(f"gradnet: config.train_primal must be one of {PRIMALS}, got {self.train_primal!r}")
        if self.compression not in ("mu-law", "log"):
            raise JaxdenoiseError(f"gradnet: config.compression must be 'mu-law' or 'log', got {self.compression!r}")
        for name in ("mu", "sigma_b2", "pp_sigma", "epoch_patches", "train_batch", "train_crop"):
            if not getattr(self, name) > 0:
                raise JaxdenoiseError(f"gradnet: config.{name} must be > 0, got {getattr(self, name)!r}")


def _epoch_steps(config: Config) -> int:
    """Trainer steps per epoch: each epoch is ``epoch_patches`` patches for the autoencoder, and the
    trainer alternates it with the G-branch (two steps per autoencoder batch)."""
    return max(1, 2 * int(math.ceil(config.epoch_patches / config.train_batch)))


# Adam beta1 0.5, beta2 0.999, x0.95 every other epoch (Sec. 5.2); the schedule counts each group's own
# updates (one per autoencoder batch), so "every other epoch" is 2 x epoch_patches / batch. The paper's
# lr 1e-4 is raised to 1e-3 with the gradient norm clipped to 1 (ours: at 1e-4 a CPU-sized run stays at
# the base image; docs/methods/gradnet.md has the measurement). 32,000 steps = 50 epochs.
TRAIN: dict[str, Any] = {"optimizer": "adam", "learning_rate": 1e-3, "adam_b1": 0.5, "adam_b2": 0.999,
                         "schedule": "step", "schedule_every": 640, "schedule_factor": 0.95, "steps": 32000,
                         "clip_norm": 1.0, "checkpoint_every": 200}
WEIGHTS = "gradnet"


def param_groups(config: Config) -> dict:
    """The autoencoder and the G-branch, trained in alternation (Sec. 5.2)."""
    ae = ("data", "grad", "res", "dec") + (("out",) if config.input_skip else ()) + (("head",) if config.head_width else ())
    return {"autoencoder": ae, "gbranch": ("gbranch",)}


def group_train(config: Config) -> dict:
    """The lr decay of Sec. 5.2 in each group's own update count: x0.95 every other epoch."""
    every = max(1, _epoch_steps(config))  # two epochs of one group's updates = one epoch of trainer steps x 2 / 2
    return {g: {"schedule_every": every} for g in ("autoencoder", "gbranch")}


def needs(config: Config) -> frozenset[str]:
    return frozenset({"color", "dx", "dy", *FEATURES})


# -- inputs ----------------------------------------------------------------------------------------

def compress(x: jax.Array, config: Config) -> jax.Array:
    """The range compressor T (Eq. 6, sign-preserving)."""
    return mu_law(x, config.mu) if config.compression == "mu-law" else log_transform(x)


def decompress(y: jax.Array, config: Config) -> jax.Array:
    return inv_mu_law(y, config.mu) if config.compression == "mu-law" else inv_log_transform(y)


HDR_MAX = 1e8  # the brightest radiance the network's output may decode to (float32-safe differences)


def to_hdr(y: jax.Array, config: Config) -> jax.Array:
    """The network's compressed output back to HDR, clamped to ``|I| <= HDR_MAX`` first: T^-1 grows
    exponentially (mu-law: ``17 ** y``), so an overshooting output would otherwise overflow to Inf
    and its gradient to NaN (measured: lr 1e-3 runs diverged within 500 steps without it)."""
    c = math.log1p(config.mu * HDR_MAX) / math.log1p(config.mu) if config.compression == "mu-law" \
        else math.log1p(HDR_MAX)
    return decompress(jnp.clip(y, -c, c), config)


def _clean(x: jax.Array) -> jax.Array:
    return jnp.where(jnp.isfinite(x), x, 0.0)


def emission(buffers: Any) -> jax.Array | None:
    """The directly seen emission that the frame's ``dx``/``dy`` leave out (a `Buffers` field or a
    batch entry; non-finite values read as 0), or None where they hold it. GradNet reconstructs
    ``color - emission`` from them (its I_b) and adds the emission back (`apply`), as Kettunen et al.'s
    reconstruction does; a training render without the layer is filled with 0 (`make_dataset`)."""
    e = getattr(buffers, EMISSION_FIELD, None) if isinstance(buffers, Buffers) else buffers.get(EMISSION_FIELD)
    return None if e is None else _clean(jnp.asarray(e, jnp.float32))


def depth_max(depth: jax.Array) -> jax.Array:
    """The largest depth of each image ``(..., H, W, 1)`` (non-finite and negative values read as
    0): ``(..., 1)``."""
    return jnp.max(jnp.maximum(_clean(depth), 0.0), axis=(-3, -2, -1), keepdims=True)[..., 0, 0, :]


def frame_stats(config: Config) -> dict:
    """The per-frame statistics of `inputs` (`jaxdenoise.methods.protocol`): ``depth_max``, the
    whole frame's largest depth (`depth_max`), which the training pipeline computes on every whole
    render and carries with its crops."""
    return {"depth_max": lambda frame: depth_max(jnp.asarray(frame["depth"], jnp.float32))}


def features(albedo: jax.Array, normal: jax.Array, depth: jax.Array, dmax: Any = None) -> jax.Array:
    """The 7 feature channels in [0, 1] (Sec. 5.1): albedo, ``(N + 1) / 2``, depth divided by
    ``dmax`` (``(..., 1)``, one per image: the whole frame's `depth_max`), by default the image's own
    largest finite depth (per image: any leading axes)."""
    albedo = jnp.clip(_clean(albedo), 0.0, None)
    normal = (jnp.clip(_clean(normal), -1.0, 1.0) + 1.0) * 0.5
    dmax = depth_max(depth) if dmax is None else jnp.asarray(dmax, jnp.float32)
    depth = jnp.maximum(_clean(depth), 0.0)
    depth = depth / jnp.maximum(dmax[..., None, None, :], 1e-12)
    return jnp.concatenate([albedo, normal, depth], -1)


def inputs(buffers: Any, config: Config) -> dict:
    """Compressed inputs of a `Buffers` or a batch dict: ``tb`` = T(I_b) (negative and non-finite
    radiance clamped to 0 first), ``tdx``, ``tdy`` = T(dx), T(dy) (sign-preserving), ``feat`` (7),
    and the HDR ``base``/``dx``/``dy`` the losses compare against. The depth is scaled by the largest
    depth of a training crop's whole render where the batch carries it (``stat.depth_max``,
    `frame_stats`), else by the array's own (at inference, the whole frame). Where the frame's
    gradients leave the directly seen emission out (`emission`), I_b is ``color - emission``."""
    get = (lambda f: getattr(buffers, f)) if isinstance(buffers, Buffers) else (lambda f: buffers[f])
    base = _clean(jnp.asarray(get("color"), jnp.float32))
    e = emission(buffers)
    if e is not None:
        base = base - e
    base = jnp.maximum(base, 0.0)
    dx = _clean(jnp.asarray(get("dx"), jnp.float32))
    dy = _clean(jnp.asarray(get("dy"), jnp.float32))
    feat = features(*(jnp.asarray(get(f), jnp.float32) for f in FEATURES), carried_stat(buffers, "depth_max"))
    return {"base": base, "dx": dx, "dy": dy, "feat": feat, "tb": compress(base, config),
            "tdx": compress(dx, config), "tdy": compress(dy, config)}


# -- network ---------------------------------------------------------------------------------------

def _act(config: Config):
    return nn.LeakyRelu(config.slope)


def _he(config: Config):
    return nn.he_normal_init(2.0 / (1.0 + config.slope ** 2))


def layers(config: Config) -> dict:
    """The architecture (Guo 2019 Fig. 4, Sec. 4.4) as named stax layers: ``data`` / ``grad`` (the two
    encoders' stride-2 levels), ``res``, ``dec``, ``gbranch``, and ``out`` / ``head`` where configured;
    `forward` runs them (experiments/profile_gradnet.py times each)."""
    w = [int(v) for v in config.widths]
    he = _he(config)

    def down(c):
        return nn.serial(nn.Conv(c, 3, stride=2, w_init=he), _act(config))

    cat = 2 * w[2]
    res = nn.residual(nn.serial(nn.Conv(cat, 3, w_init=he), _act(config), nn.Conv(cat, 3, w_init=he)))
    last = (nn.serial(nn.ConvTranspose(w[0], 4, stride=2, w_init=he), _act(config)) if config.input_skip
            else nn.ConvTranspose(3, 4, stride=2, w_init=he))
    layers = {
        "data": [down(c) for c in w],
        "grad": [down(c) for c in w],
        "res": [nn.serial(res, _act(config)) if config.res_act_after_sum else nn.serial(res)
                for _ in range(config.res_blocks)],
        "dec": [nn.serial(nn.ConvTranspose(w[1], 4, stride=2, w_init=he), _act(config)),
                nn.serial(nn.ConvTranspose(w[0], 4, stride=2, w_init=he), _act(config)),
                last],
        "gbranch": nn.serial(nn.Conv(config.g_width, 3, w_init=he), _act(config),
                             nn.Conv(config.g_width, 3, w_init=he), _act(config),
                             nn.Conv(N_FEAT * 3, 3, w_init=he)),
    }
    if config.input_skip:  # zero-initialised: training starts exactly at T(I_b) (He init diverged, measured)
        layers["out"] = nn.Conv(3, 3, w_init=lambda key, shape: jnp.zeros(shape, jnp.float32))
    if config.head_width:  # nonlinear in the full-resolution inputs; zero-initialised last conv (adds 0 at start)
        layers["head"] = nn.serial(nn.Conv(int(config.head_width), 3, w_init=he), _act(config),
                                   nn.Conv(3, 3, w_init=lambda key, shape: jnp.zeros(shape, jnp.float32)))
    return layers


def init(key, config: Config) -> dict:
    L = layers(config)
    w = [int(v) for v in config.widths]
    keys = iter(jax.random.split(key, 16 + config.res_blocks))
    s = 32
    params: dict = {"data": {}, "grad": {}, "res": {}, "dec": {}}
    cd, cg = 3 + N_FEAT, 6
    for i in range(3):
        params["data"][str(i)] = L["data"][i][0](next(keys), (-1, s, s, cd))[1]
        params["grad"][str(i)] = L["grad"][i][0](next(keys), (-1, s, s, cg))[1]
        cd = cg = w[i]
        s //= 2
    for i in range(config.res_blocks):
        params["res"][str(i)] = L["res"][i][0](next(keys), (-1, 4, 4, 2 * w[2]))[1]
    cins = (2 * w[2] + 2 * w[2], w[1] + 2 * w[1], w[0] + 2 * w[0])  # Eq. 12: decoder + both branches
    for i in range(3):
        params["dec"][str(i)] = L["dec"][i][0](next(keys), (-1, 4, 4, cins[i]))[1]
    params["gbranch"] = L["gbranch"][0](next(keys), (-1, 8, 8, 3 + N_FEAT))[1]
    if config.input_skip:  # decoder + data-branch input + gradient-branch input
        params["out"] = L["out"][0](next(keys), (-1, 8, 8, w[0] + 3 + N_FEAT + 6))[1]
    if config.head_width:
        params["head"] = L["head"][0](next(keys), (-1, 8, 8, w[0] + 3 + N_FEAT + 6))[1]
    return params


def num_params(config: Config) -> int:
    shapes = jax.eval_shape(lambda k: init(k, config), jax.random.PRNGKey(0))
    return int(sum(np.prod(s.shape) for s in jax.tree_util.tree_leaves(shapes)))


def forward(params: dict, x: dict, config: Config) -> jax.Array:
    """The autoencoder on prepared inputs (`inputs`, H and W multiples of 8): the output image in the
    mu-law domain."""
    L = layers(config)
    hd = jnp.concatenate([x["tb"], x["feat"]], -1)
    hg = jnp.concatenate([x["tdx"], x["tdy"]], -1)
    skips_d, skips_g = [], []
    for i in range(3):
        hd = L["data"][i][1](params["data"][str(i)], hd)
        hg = L["grad"][i][1](params["grad"][str(i)], hg)
        skips_d.append(hd)
        skips_g.append(hg)
    h = jnp.concatenate([hd, hg], -1)
    for i in range(config.res_blocks):
        h = L["res"][i][1](params["res"][str(i)], h)
    for i in range(3):  # Eq. 12: Deconv(h_{l-1} + h_ED + h_EG) at the resolution of h_{l-1}
        lvl = 2 - i
        h = L["dec"][i][1](params["dec"][str(i)], jnp.concatenate([h, skips_d[lvl], skips_g[lvl]], -1))
    if config.input_skip:
        c = jnp.concatenate([h, x["tb"], x["feat"], x["tdx"], x["tdy"]], -1)
        h = L["out"][1](params["out"], c)
        if config.head_width:
            h = h + L["head"][1](params["head"], c)
    return x["tb"] + h if config.residual_output else h


def g_branch(params: dict, x: dict, config: Config) -> jax.Array:
    """Per-pixel first-order derivatives ``G``: ``(..., H, W, 7, 3)``."""
    g = layers(config)["gbranch"][1](params["gbranch"], jnp.concatenate([x["tb"], x["feat"]], -1))
    return g.reshape(g.shape[:-1] + (N_FEAT, 3))


def predict(params: dict, buffers: Any, config: Config) -> tuple[jax.Array, jax.Array, dict]:
    """``(T(I_hat), G, inputs)`` at the frame's own size (padded to a multiple of 8 for the network
    and cropped back)."""
    xp, size = _padded(buffers, config)
    y = nn.crop_to(forward(params, xp, config), size)
    return y, _g_cropped(params, xp, size, config), inputs(buffers, config)


def _g_cropped(params: dict, xp: dict, size: tuple[int, int], config: Config) -> jax.Array:
    """`g_branch` on padded inputs, cropped back to the frame's ``size``: ``(..., H, W, 7, 3)``."""
    g = g_branch(params, xp, config)
    g = nn.crop_to(g.reshape(g.shape[:-2] + (N_FEAT * 3,)), size)
    return g.reshape(g.shape[:-1] + (N_FEAT, 3))


def _padded(buffers, config):
    x = inputs(buffers, config)
    size = x["base"].shape[-3:-1]
    return {k: nn.pad_to_multiple(v, STRIDE)[0] for k, v in x.items()}, size


def _blur(x: jax.Array, config: Config) -> jax.Array:
    """The Gaussian of Sec. 4.5 (radius ``pp_radius``, sigma ``pp_sigma``) over the two image axes of
    ``(..., H, W, C)``: `jaxdenoise.filters.gaussian` (separable shifted-slice sums, the kernel
    renormalized at the border) with the leading axes folded into the channels."""
    lead = x.shape[:-3]
    h, w, c = x.shape[-3:]
    y = jnp.moveaxis(x.reshape((-1, h, w, c)), 0, 2).reshape((h, w, -1))
    y = gaussian(y, config.pp_sigma, radius=int(config.pp_radius))
    return jnp.moveaxis(y.reshape((h, w, -1, c)), 2, 0).reshape(lead + (h, w, c))


def postprocess(out: jax.Array, base: jax.Array, config: Config) -> jax.Array:
    """Eq. 13: ``out <- (base * k) / (out * k) . out``, per channel, with the Gaussian ``k`` of
    Sec. 4.5 (at the border both blurs are renormalized by the same in-image kernel mass, which the
    ratio cancels). Guard: where ``out * k`` is below 1e-6 times its channel's mean (or non-finite),
    ``out`` is kept. Both images are blurred in one call."""
    both = _blur(jnp.concatenate([base, out], -1), config)
    num, den = both[..., :base.shape[-1]], both[..., base.shape[-1]:]
    floor = 1e-6 * jnp.mean(jnp.abs(den), axis=(-3, -2), keepdims=True) + 1e-12
    ratio = num / jnp.where(den > floor, den, 1.0)
    ok = (den > floor) & jnp.isfinite(ratio)
    return jnp.where(ok, ratio * out, out)


def _run(params: dict, buffers: Any, config: Config, post: bool) -> jax.Array:
    x, size = _padded(buffers, config)
    y = nn.crop_to(forward(params, x, config), size)
    out = jnp.maximum(to_hdr(y, config), 0.0)
    if post:
        base = nn.crop_to(x["base"], size)
        out = postprocess(out, base, config)
    e = emission(buffers)
    return out if e is None else out + e


def apply(params: dict, buffers: Buffers, config: Config) -> jax.Array:
    """Reconstruct one frame or a batch (leading axes): HDR ``(..., H, W, 3)``."""
    return _run(params, buffers, config, config.postprocess)


# -- losses (Sec. 4.3) -----------------------------------------------------------------------------

def _neighbours():
    # (axis, shift): the right, left, lower and upper neighbour of every pixel.
    return ((-2, 1), (-2, -1), (-3, 1), (-3, -1))


def _shifted(a: jax.Array, axis: int, s: int) -> tuple[jax.Array, jax.Array]:
    """``(a_j, a_i)`` for the pairs (i, j = i + s along ``axis``) inside the image."""
    n = a.shape[axis]
    take = lambda lo, hi: jax.lax.slice_in_dim(a, lo, hi, axis=axis)  # noqa: E731
    return (take(1, n), take(0, n - 1)) if s > 0 else (take(0, n - 1), take(1, n))


def first_order_weights(tb: jax.Array, config: Config) -> list[jax.Array]:
    """``w_ij = exp(-|T(I_b,i) - T(I_b,j)|^2 / (2 sigma_b^2))`` (squared L2 over the colour channels)
    for the 4 neighbour directions of `_neighbours` (each ``(..., H', W', 1)``), from the compressed
    base ``tb``; with ``weights_domain = "hdr"`` the same on ``I_b = T^-1(tb)``."""
    if config.weights_domain == "hdr":
        tb = decompress(tb, config)
    out = []
    for axis, s in _neighbours():
        bj, bi = _shifted(tb, axis, s)
        out.append(jnp.exp(-jnp.sum(jnp.square(bi - bj), -1, keepdims=True) / (2.0 * config.sigma_b2)))
    return out


def first_order_loss(t_img: jax.Array, G: jax.Array, feat: jax.Array, w: list[jax.Array]) -> jax.Array:
    """Eq. 10 / 11: ``1/(N |N_i|) sum_i sum_j w_ij |T_j - T_i - G_i^T (F_j - F_i)|_1`` over the pairs
    inside the image."""
    total, count = 0.0, 0
    for (axis, s), wij in zip(_neighbours(), w):
        tj, ti = _shifted(t_img, axis, s)
        fj, fi = _shifted(feat, axis, s)
        _, Gi = _shifted(G.reshape(G.shape[:-2] + (N_FEAT * 3,)), axis, s)
        pred = jnp.einsum("...fc,...f->...c", Gi.reshape(Gi.shape[:-1] + (N_FEAT, 3)), fj - fi)
        total = total + jnp.sum(wij * jnp.sum(jnp.abs(tj - ti - pred), -1, keepdims=True))
        count += int(np.prod(wij.shape))
    return total / count


def grad_loss(out_hdr: jax.Array, x: dict, config: Config) -> jax.Array:
    """Eq. 9: ``|T(grad_x I) - T(I_dx)| + |T(grad_y I) - T(I_dy)|`` per pixel (L1 over the colour
    channels), averaged; HDR forward differences, the last column / row (no neighbour) excluded."""
    gx = out_hdr[..., :, 1:, :] - out_hdr[..., :, :-1, :]
    gy = out_hdr[..., 1:, :, :] - out_hdr[..., :-1, :, :]
    lx = jnp.abs(compress(gx, config) - x["tdx"][..., :, :-1, :]).sum(-1).mean()
    ly = jnp.abs(compress(gy, config) - x["tdy"][..., :-1, :, :]).sum(-1).mean()
    return lx + ly


def lambda_at(step: Any, config: Config) -> float:
    """Eq. 14 in trainer steps: epoch = 1 + (autoencoder patches seen) // ``epoch_patches``;
    lambda = 0 up to epoch 5, then ``min(0.1 * 1.1 ** (epoch - 5), 2)``."""
    epoch = 1 + int(step) // _epoch_steps(config)
    if epoch <= config.lambda_epochs:
        return 0.0
    k = epoch - config.lambda_epochs
    if k * math.log(config.lambda_growth) >= math.log(config.lambda_max / config.lambda_start):
        return float(config.lambda_max)  # (also keeps growth ** k from overflowing)
    return float(min(config.lambda_start * config.lambda_growth ** k, config.lambda_max))


def loss_terms(params: dict, batch: dict, config: Config) -> dict:
    """Every term on a batch (no reference read): ``data`` (Eq. 8), ``grad`` (Eq. 9), ``first``
    (Eq. 10, with ``G`` from the G-branch held fixed), ``g_branch`` (Eq. 11)."""
    y, G, x = predict(params, batch, config)
    return output_terms(y, G, x, config)


def output_terms(y: jax.Array, G: jax.Array, x: dict, config: Config) -> dict:
    """`loss_terms` of a given compressed output ``y`` (``(y, G, x)`` as `predict` returns them)."""
    w = first_order_weights(x["tb"], config)
    return {
        "data": jnp.abs(y - x["tb"]).sum(-1).mean(),
        "grad": grad_loss(to_hdr(y, config), x, config),
        "first": first_order_loss(y, jax.lax.stop_gradient(G), x["feat"], w),
        "g_branch": first_order_loss(x["tb"], G, x["feat"], w),
    }


def loss(params: dict, batch: dict, config: Config, group: str | None = None):
    """``L_all = L_grad + alpha L_data + lambda L_1st`` (Eq. 7) for the autoencoder, Eq. 11 for the
    G-branch; ``lambda`` comes with the batch (`batch`: Eq. 14 of the step). ``group=None`` gives
    their sum (for reporting)."""
    lam = jnp.asarray(batch.get("lambda", 0.0), jnp.float32)
    if group == "gbranch":
        xp, size = _padded(batch, config)
        x = inputs(batch, config)
        return first_order_loss(x["tb"], _g_cropped(params, xp, size, config), x["feat"],
                            first_order_weights(x["tb"], config))
    t = loss_terms(params, batch, config)
    l_all = t["grad"] + config.alpha * t["data"] + (lam * t["first"] if config.first_order else 0.0)
    if group == "autoencoder":
        return l_all
    if group is not None:
        raise JaxdenoiseError(f"gradnet: unknown parameter group {group!r}; expected 'autoencoder' or 'gbranch'")
    return l_all + t["g_branch"]


def validation_loss(params: dict, buffers: Any, config: Config) -> jax.Array:
    """The unsupervised score `jaxdenoise.train` can select weights by (``select="loss"``): Eq. 7's
    ``L_all`` of one whole frame (or batch) at the end of Eq. 14's schedule (``lambda_max``; 0 without
    the first-order loss), on the network's output before Eq. 13. Reads no reference: what a user
    without references can choose by (docs/methods/gradnet.md)."""
    t = loss_terms(params, buffers, config)
    lam = float(config.lambda_max) if config.first_order else 0.0
    return t["grad"] + config.alpha * t["data"] + lam * t["first"]


# -- training data ---------------------------------------------------------------------------------

def is_illegal(render: dict) -> bool:
    """Whether a training render holds an illegal value: NaN/Inf anywhere in the fields GradNet reads,
    or negative base radiance (gradients are signed) (Sec. 5.1, footnote 1)."""
    vals = np.concatenate([np.asarray(render[f]) for f in ("color", "dx", "dy", *FEATURES, EMISSION_FIELD)
                           if f in render], -1)
    return bool(not np.all(np.isfinite(vals)) or np.any(np.asarray(render["color"]) < 0))


def check_primal(data_dir, primals: list | None, want: str) -> None:
    """Refuse training renders whose I_b is not ``want`` (`Config.train_primal`): ``primals`` are the
    header ``primal`` values of the renders (`pipeline.Cache.primals`; None in a header: a render made
    before data_gen recorded it, when the base was the only I_b; None for the whole list: an export
    written before its summary recorded them)."""
    if primals is None:
        raise JaxdenoiseError(f"{data_dir}: this export does not say which I_b its renders hold (written before "
                              "exports recorded the header's primal): export it again (experiments/export_training.py)")
    found = sorted({p or "base" for p in primals})
    if found != [want]:
        raise JaxdenoiseError(
            f"{data_dir}: the training renders' I_b is {found} (header 'primal'); gradnet's train_primal is {want!r}. "
            "Render with `python -m data_gen dataset ... --primal gpt` (the paper's G-PT primal, Sec. 5.1), or train "
            "on base renders with --train-primal base")


def make_dataset(data_dir, config: Config, *, progress: bool = True):
    """The gradient-domain training renders at ``train_spps``, from a data_gen folder (decoded once
    into the pipeline cache, bad values zeroed and counted per render) or from an export of this
    function's result (`pipeline.Cache.export`, which may leave the reference out), without the
    renders that hold an illegal value (`is_illegal`, or values the cache had to zero: dropped and
    counted, ``dataset.dropped``). The references the folder contract carries are never read."""
    from ..pipeline import open_training_data

    # A render whose gradients hold the directly seen emission (before data_gen 0.7.0) reads as one with
    # an emission layer of 0: the same I_b and gradients.
    ds = open_training_data(data_dir, ("dx", "dy", *FEATURES, EMISSION_FIELD), spps=config.train_spps,
                            progress=progress, reference=False, repair="zero", stats=frame_stats(config),
                            fill={EMISSION_FIELD: 0.0})
    check_primal(data_dir, ds.primals(config.train_spps), config.train_primal)
    spps = {float(s) for s in config.train_spps}
    frames = getattr(ds, "frames", None)  # a cache counts the values it had to zero (a folder's illegal renders)
    pool, keep = [], []
    for i in range(len(ds)):
        r = ds.render(i)
        if float(r["spp"]) in spps:
            pool.append(i)
            if not is_illegal(r) and not (frames and frames[i].get("repaired")):
                keep.append(i)
    if not pool:
        raise JaxdenoiseError(f"{data_dir}: no render at spp {list(config.train_spps)}")
    if not keep:
        raise JaxdenoiseError(f"{data_dir}: every one of {len(pool)} renders at spp {list(config.train_spps)} has an "
                         "illegal value (NaN/Inf or negative radiance)")
    out = ds.subset(keep)
    out.dropped = {"renders": len(pool), "dropped": len(pool) - len(keep)}
    if progress:
        print(f"gradnet: {len(keep)} training renders, {len(pool) - len(keep)} dropped for illegal values")
    return out


def batch(dataset, step: int, config: Config, rng: np.random.Generator) -> dict:
    """``train_batch`` random ``train_crop`` crops (quarter turns, mirror, colour modulation: the
    pipeline's augmentations keep dx, dy consistent), without the reference, with the per-frame
    statistics of each crop's whole render (`frame_stats`), and Eq. 14's lambda."""
    b = dataset.crops(config.train_batch, config.train_crop, rng, spps=config.train_spps)
    out = {**{k: b[k] for k in ("color", "dx", "dy", *FEATURES, EMISSION_FIELD) if k in b}, **carried_stats(b)}
    out["lambda"] = np.float32(lambda_at(step, config))
    return out
