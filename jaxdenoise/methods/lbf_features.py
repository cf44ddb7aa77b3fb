"""Secondary features of Kalantari, Bako, Sen 2015 (Sec. 3.3): the network inputs of LBF.

For each of the K additional primary features (Sec. 3.2: world position, shading normal, first-
and second-hit texture, direct visibility; K = 5 by default) we compute, per pixel:

- feature statistics (4 per feature): the mean and the standard deviation over the pixel's
  samples, and the mean and standard deviation of the pixel-averaged feature over a 7x7 block;
- the Sobel gradient magnitude (1 per feature);
- the mean deviation over a 3x3 block: mean of ``|f_j - mean_3x3(f)|`` (1 per feature);
- the median absolute deviation over a 3x3 block: ``median_j |f_j - median_3x3(f)|`` (1 per
  feature, our reading of the per-pixel MAD noise estimate of Kalantari and Sen 2013);

plus the inverse sampling rate ``1/spp`` (1). With K = 5 this is the paper's 36 features.
As in the paper, each statistic is computed per component (x, y, z of a normal, r, g, b of a
texture) and the components are averaged into one value per feature.

Only per-pixel means and the variance of each pixel mean reach us (`Buffers`), not the samples:
the standard deviation over the pixel's samples is recovered as ``sqrt(var_of_mean * spp)``
(the variance of a mean of n i.i.d. samples is the sample variance / n).

The inputs are the *prefiltered* primary features (Sec. 3.2, computed by
`jaxdenoise.filters`); this module is the pure, jittable arithmetic on them. Border pixels use
edge replication, so any image size (1x1 included) works. The feature order is given by
`feature_names`; `CATEGORIES` names the five groups of Sec. 3.3 used by the ablation of Sec. 6.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import jax
import jax.numpy as jnp

from ..arrays import edge_views, median9, pad_edge
from ..errors import JaxdenoiseError

__all__ = ["PAPER_FEATURES", "CATEGORIES", "feature_names", "feature_categories", "secondary_features", "num_features",
           "box_mean", "sobel_magnitude", "mean_deviation", "median_abs_deviation"]

# The paper's K = 5 additional primary features (Sec. 3.2) as `Buffers` fields: world position,
# shading normal, texture at the first and second hit, direct-light visibility. The default of
# ``lbf`` and of the ``bilateral`` / ``nlm`` baselines.
PAPER_FEATURES: tuple[str, ...] = ("position", "normal", "albedo", "albedo2", "visibility")
# Sec. 3.3 categories in the order the features are stacked (the ablation of Sec. 6 drops one).
CATEGORIES: tuple[str, ...] = ("statistics", "gradient", "mean_deviation", "mad", "sampling_rate")
BLOCK_STATS = 7  # 7x7 block for the block mean / std (Sec. 3.3)
BLOCK_DEV = 3  # 3x3 block for the mean deviation (Sec. 3.3) and, our choice, for the MAD


def num_features(features: Sequence[str]) -> int:
    """7 per additional feature plus the inverse sampling rate (36 for K = 5)."""
    return 7 * len(features) + 1


def feature_names(features: Sequence[str]) -> list[str]:
    """Names of the secondary features in the order `secondary_features` stacks them."""
    names = []
    names += [f"{f}.pixel_mean" for f in features] + [f"{f}.pixel_std" for f in features]
    names += [f"{f}.block_mean" for f in features] + [f"{f}.block_std" for f in features]
    names += [f"{f}.sobel" for f in features]
    names += [f"{f}.mean_dev" for f in features]
    names += [f"{f}.mad" for f in features]
    names += ["inv_spp"]
    return names


def feature_categories(features: Sequence[str]) -> list[str]:
    """The Sec. 3.3 category of every secondary feature, aligned with `feature_names`."""
    k = len(features)
    return (["statistics"] * (4 * k) + ["gradient"] * k + ["mean_deviation"] * k + ["mad"] * k
            + ["sampling_rate"])


def box_mean(x: jax.Array, *, size: int) -> jax.Array:
    """Mean over a size x size block around each pixel (edge-replicated borders), separable."""
    if size % 2 != 1 or size < 1:
        raise JaxdenoiseError(f"box_mean: size must be a positive odd integer, got {size}")
    r = size // 2
    h, w = x.shape[-3], x.shape[-2]
    p = pad_edge(x, r)
    rows = sum(p[..., dy:dy + h, :, :] for dy in range(size)) / size
    return sum(rows[..., :, dx:dx + w, :] for dx in range(size)) / size


def _safe_sqrt(x: jax.Array) -> jax.Array:
    # sqrt has an infinite derivative at 0 and E[x^2] - E[x]^2 can round to a tiny negative value:
    # clamp here, where both happen, so values and gradients stay finite.
    return jnp.sqrt(jnp.maximum(x, 1e-20))


def sobel_magnitude(x: jax.Array) -> jax.Array:
    """Per-channel Sobel gradient magnitude ``sqrt(gx^2 + gy^2)`` (edge-replicated borders)."""
    h, w = x.shape[-3], x.shape[-2]
    p = pad_edge(x, 1)

    def s(dy: int, dx: int) -> jax.Array:
        return p[..., 1 + dy:1 + dy + h, 1 + dx:1 + dx + w, :]

    gx = (s(-1, 1) + 2 * s(0, 1) + s(1, 1)) - (s(-1, -1) + 2 * s(0, -1) + s(1, -1))
    gy = (s(1, -1) + 2 * s(1, 0) + s(1, 1)) - (s(-1, -1) + 2 * s(-1, 0) + s(-1, 1))
    return _safe_sqrt(gx * gx + gy * gy)


def mean_deviation(x: jax.Array, *, size: int = BLOCK_DEV) -> jax.Array:
    """Mean over a block of ``|f_j - block mean|`` (Sec. 3.3, after Hachisuka et al. 2008)."""
    views = edge_views(x, size // 2)  # not stacked (arrays.edge_views)
    mean = sum(views) / len(views)
    return sum(jnp.abs(v - mean) for v in views) / len(views)


def median_abs_deviation(x: jax.Array, *, size: int = BLOCK_DEV) -> jax.Array:
    """Median over a block of ``|f_j - block median|`` (Sec. 3.3, after Kalantari and Sen 2013)."""
    views = edge_views(x, size // 2)
    if len(views) == 9:  # the 3x3 block: a sorting network, equal to jnp.median (arrays.median9)
        med = median9(views)
        return median9(jnp.abs(v - med) for v in views)
    sh = jnp.stack(views)
    return jnp.median(jnp.abs(sh - jnp.median(sh, axis=0)), axis=0)


def secondary_features(feats: Mapping[str, jax.Array], variances: Mapping[str, jax.Array], spp,
                       *, features: Sequence[str]) -> jax.Array:
    """The 7K+1 secondary features of Sec. 3.3, shape (..., H, W, 7K+1), float32.

    ``feats[name]`` is the (prefiltered) pixel-mean feature, shape (..., H, W, C);
    ``variances[name]`` the (smoothed) variance of that pixel mean, shape (..., H, W, 1);
    ``spp`` the samples per pixel (scalar, one per leading frame, or one per pixel, shape (..., H, W),
    for an adaptively sampled frame).
    """
    missing = [f for f in features if f not in feats or f not in variances]
    if missing:
        raise JaxdenoiseError(f"secondary_features: feats/variances lack {missing}; features={list(features)}")
    ref = feats[features[0]] if features else None
    if ref is None:
        raise JaxdenoiseError("secondary_features: 'features' must name at least one additional feature")
    spp = jnp.asarray(spp, jnp.float32)
    # spp of 0 or less is meaningless; clamp so 1/spp and var*spp stay finite.
    spp = jnp.maximum(spp, 1.0)
    lead = ref.shape[:-1]
    spp_img = jnp.broadcast_to(spp.reshape(spp.shape + (1,) * (len(lead) - spp.ndim)), lead)

    def cmean(a: jax.Array) -> jax.Array:  # average the components into one value per pixel
        return jnp.mean(a, axis=-1)

    pix_mean, pix_std, blk_mean, blk_std, sob, mdev, mad = [], [], [], [], [], [], []
    for name in features:
        f = jnp.asarray(feats[name], jnp.float32)
        v = jnp.asarray(variances[name], jnp.float32)
        pix_mean.append(cmean(f))
        # std over the pixel's samples = sqrt(var of the mean * n); var clamped at 0 (negative
        # variances only come from round-off in the renderer's running estimate).
        pix_std.append(_safe_sqrt(jnp.maximum(cmean(v), 0.0) * spp_img))
        m1 = box_mean(f, size=BLOCK_STATS)
        m2 = box_mean(f * f, size=BLOCK_STATS)
        blk_mean.append(cmean(m1))
        blk_std.append(cmean(_safe_sqrt(m2 - m1 * m1)))
        sob.append(cmean(sobel_magnitude(f)))
        mdev.append(cmean(mean_deviation(f)))
        mad.append(cmean(median_abs_deviation(f)))
    cols = pix_mean + pix_std + blk_mean + blk_std + sob + mdev + mad + [1.0 / spp_img]
    return jnp.stack(cols, axis=-1)
