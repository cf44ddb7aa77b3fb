"""RAE: the recurrent denoising autoencoder of Chaitanya, Kaplanyan, Schied, Salvi, Lefohn,
Nowrouzezahrai, Aila 2017 ("Interactive Reconstruction of Monte Carlo Image Sequences using a
Recurrent Denoising Autoencoder"), registered as ``rae`` (causal: ``init_state`` / ``step``).

Inputs (Sec. 3.2, 4.1): 7 channels per pixel: the noisy colour demodulated by the first-hit
albedo (`jaxdenoise.color.demodulate`, its safe epsilon), the view-space shading normal's x and y,
the linear (view-axis) depth, and the roughness; the view-space quantities come from the frame's
camera (`jaxdenoise.view`). Our choices (docs/methods/rae.md): the demodulated colour is raised to
the power 0.2 like the loss's images (Sec. 4.4 says the implementation "raises both the input and
target images into power 0.2"), and the linear depth is divided by its mean over the frame's
surface pixels (no absolute scale carries across scenes). That mean is a statistic of each whole
frame, in training as at inference: it is one value per frame of a sequence (each frame's own, as
`step` computes it frame by frame at inference; not one per sequence), declared by `frame_stats`,
computed by the training pipeline on each whole render and carried by every frame of a sequence
crop (`jaxdenoise.pipeline`); `inputs` uses the carried value when given, else computes it from its
array (at inference, the whole frame).

Ours for rates beyond the paper's 1 spp (issue 34; the paper's recipe is ``rae-paper``, ``recipe =
"paper"``): with ``exposure = "frame"`` (the default) the colour is first scaled to
`jaxdenoise.color.EXPOSURE_LEVEL` by the frame's exposure level (another whole-frame statistic) and
the output divided by the same factor, so ``f(k x) = k f(x)``; with ``rate_input`` (the default) an
eighth channel holds ``log2(spp) / RATE_SCALE`` (per pixel on an adaptively sampled frame);
``input_transform = "linear"`` feeds the demodulated colour without the power (measured, not kept);
``outlier_clamp`` (8 for ``rae``, 0 in `Config`) cuts isolated input spikes
(`jaxdenoise.filters.clamp_outliers`), in place of the paper's path-space regularization (Sec. 3.1)
that kept them out of its inputs. ``keep_exact`` (on for ``rae``) keeps the input where a frame's samples
all agreed (`jaxdenoise.filters.exact_mask`: a directly seen light), as `demc` does, and ``keep_background``
(on for ``rae``) where no sample found a surface (the environment seen directly). Each output frame then
goes through ``refine_sigma``'s feature-guided cross-bilateral pass (`jaxdenoise.filters.refine`, as
`demc`), the output clamp (``output_clamp``, off for ``rae``: isolated peaks cut), TAA over a sequence (``taa_alpha``,
Sec. 5.4) and the level match (``match_level``; over a sequence its gain averaged over frames, ``match_frames``):
`step`.

Network (Sec. 4.1-4.2, Fig. 2): five encoder stages (widths 32, 43, 57, 76, 101) of a 3x3 conv and
a recurrent block (`jaxdenoise.nn.RecurrentBlock`: a conv on the input, concatenation with the
hidden state, two more convs; output = new hidden state) before 2x2 max pooling; a bottleneck of
a conv, a recurrent block (101) and a conv; five decoder stages of 2x2 nearest up-sampling,
concatenation with the encoder stage's recurrent output (the skip) and two 3x3 convs; a linear 3x3
output conv. Leaky ReLU 0.1 after every other conv; He initialisation. 36 convolutions: 7 encoder,
10 decoder, 1 output, 6 x 3 recurrent. The output is the illumination in the 0.2-power domain,
mapped back (``y^5``, odd extension) and remodulated by the albedo. Any resolution (padded to a
multiple of 32 and cropped back).

Loss (Sec. 4.4): on 7-frame sequences, per frame ``0.8 L_s + 0.1 L_g + 0.1 L_t`` with ``L_s`` the L1
of the remodulated prediction and the target, both raised to 0.2; ``L_g`` the L1 of their HFEN
(Laplacian of Gaussian, sigma 1.5); ``L_t`` the L1 of their temporal differences; frames weighted
by (0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1), back-propagated through time over an unrolled
loop (a rolled ``lax.scan`` is ~25x slower to differentiate on a CPU: `jaxdenoise.nn.audit`).
Ours (issue 34, ``level_weight``, 0 by default): a level term on 8x8 block means added to each frame's
loss (`Config.level_weight`, docs/methods/rae.md).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import color, metrics, nn, view
from ..buffers import SAMPLE_COUNT_FIELD, Buffers
from ..errors import JaxdenoiseError
from ..filters import (accumulate_step, check_exact_window, check_match_settings, check_refine_settings,
                       check_taa_settings, clamp_outliers, exact_mask, input_gain, refine, taa_init, taa_step)
from ..pipeline import carried_stat, carried_stats

__all__ = ["Config", "needs", "required", "init", "apply", "init_state", "step", "loss", "run_sequence", "inputs",
           "make_dataset", "batch", "frame_stats", "normalized_depth", "surface_mean", "exposure_scale",
           "rate_channel", "sample_count", "crop_projection", "INPUT_TRANSFORMS", "EXPOSURES", "RECIPES", "RATE_SCALE",
           "loss_terms", "log_kernel", "num_params", "TRAIN", "WEIGHTS", "AUX"]
# Pixels of context a tile needs on each side (`jaxdenoise.tiling`): the smallest margin whose max
# |tiled - whole| / (|whole| + 0.01) on a real frame is below 5e-3 (docs/results/tiling/, re-measured at
# 0.9.24: 4.1e-3 and RelMSE +0.01 % at 128 px, against 8.9e-3 and -0.04 % at 96).
TILE_MARGIN = 128

# The auxiliary inputs of Sec. 3.2 and their channels (Fig. 3's ladder drops them in this order).
AUX: dict[str, int] = {"normal": 2, "depth": 1, "roughness": 1}


@dataclasses.dataclass(frozen=True)
class Config:
    """RAE hyperparameters; paper values cited, our choices marked (docs/methods/rae.md)."""

    widths: tuple[int, ...] = (32, 43, 57, 76, 101)  # encoder stages, x4/3 each (Sec. 5.1, Fig. 2)
    bottleneck: int = 101  # Fig. 2
    decoder_widths: tuple[int, ...] | None = None  # illegible in Fig. 2: None mirrors the encoder (ours)
    slope: float = 0.1  # leaky ReLU (Sec. 4.1)
    aux: tuple[str, ...] = ("normal", "depth", "roughness")  # auxiliary inputs (Sec. 3.2; Fig. 3 ladder)
    power: float = 0.2  # Sec. 4.4: images raised to 0.2 before the loss (and the input: ours)
    loss_weights: tuple[float, float, float] = (0.8, 0.1, 0.1)  # w_s, w_g, w_t (Sec. 4.4)
    frame_weights: tuple[float, ...] = (0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1.0)  # Sec. 4.4
    hfen_sigma: float = 1.5  # Sec. 4.4
    albedo_eps: float = color.ALBEDO_EPS_DEFAULT
    # A frame without roughness: data_gen leaves the buffer out when every BSDF of the scene has the
    # same roughness (its shot.json says which); in our procedural scenes that is an all-diffuse
    # scene, roughness 1 (data_gen.integrator's rule). Documented constant, docs/methods/rae.md.
    missing_roughness: float = 1.0
    # What the network sees of the colour (issue 34, docs/methods/rae.md "Input transform, exposure and
    # rate"): "power" is the paper's (the demodulated colour raised to `power`, Sec. 4.4); "linear" the
    # demodulated colour itself (scaled by the exposure). The loss and the output stay in the
    # `power` domain either way. A fine-tune may change it (no parameter changes shape).
    input_transform: str = dataclasses.field(default="power", metadata={"fine_tune": True})
    # "frame": the colour scaled to `jaxdenoise.color.EXPOSURE_LEVEL` by the frame's exposure level
    # before the transform and the output scaled back, so f(k x) = k f(x); "none": as the paper.
    exposure: str = dataclasses.field(default="frame", metadata={"fine_tune": True})
    # The sampling rate as an extra input channel, log2(spp) / RATE_SCALE (per pixel where the frame has
    # a sample-count map): one more input channel (ours; the paper trains and tests at 1 spp).
    rate_input: bool = True
    # Outlier suppression (ours, issue 34; docs/methods/rae.md "Outliers"): a pixel's colour luminance
    # (after the exposure scaling) is limited to `outlier_clamp` times the larger of the frame's level
    # (`jaxdenoise.color.EXPOSURE_LEVEL`) and the brightest of its 8 neighbours, hue kept; 0 = off. It
    # stands in for the paper's path-space regularization (Sec. 3.1), which removed "sparse
    # high-intensity outliers" from its inputs at a small bias; our renders have them.
    outlier_clamp: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    # Single-sample spikes (ours, issue 34's halo check; docs/methods/rae.md "Single-sample spikes"): with
    # `outlier_clamp` on and `outlier_rel_sd` > 0, a pixel of a frame of >= 2 spp whose relative standard error
    # (the channel mean of sqrt(color_var) over the channel mean of the colour; one non-zero sample among n
    # gives exactly 1) is at least this value is limited to `outlier_clamp` times its brightest neighbour
    # alone, without the frame-level floor; 0 = off. Inference only (training crops carry no variance);
    # inert on 1-spp frames, which have none.
    outlier_rel_sd: float = 0.0
    # The colour level at inference (ours, issue 34; docs/methods/rae.md "Colour level at inference";
    # DEMC's, `jaxdenoise.methods.demc.Config.match_level`): with `match_level` > 0 each output frame's
    # level, low-passed by a Gaussian of that many pixels, is put at its noisy input's
    # (`jaxdenoise.filters.match_to_input`, outliers cut at `match_spike` x their 3x3 median, the gain within
    # [1 / `match_max_gain`, `match_max_gain`], 0: no limit); needs exposure "frame". With
    # `match_spike_by_rate`, `match_spike` is one sample's factor and a frame of n spp is cut at
    # 1 + (match_spike - 1) / sqrt(n) (a frame without `spp`: match_spike). The recurrent
    # state is not touched; inference only (training's loss reads the network's own output).
    match_level: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    match_spike: float = dataclasses.field(default=4.0, metadata={"fine_tune": True})
    match_max_gain: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    match_spike_by_rate: bool = dataclasses.field(default=False, metadata={"fine_tune": True})
    # With `match_output_cut` the target is cut again at the same factor times the larger of the frame's level and
    # the output's brightest neighbour (`input_gain`'s `output_cut`): a small light the network drew dark no
    # longer brightens its whole neighbourhood through the gain.
    match_output_cut: bool = dataclasses.field(default=False, metadata={"fine_tune": True})
    # The level match over time (ours, issue 34; docs/methods/rae.md "The level match over time"): with
    # `match_frames` > 1 the match's gain is averaged over the previous frames' gains, reprojected through the
    # world positions and cameras (`jaxdenoise.filters.accumulate_step`, taps off the tangent plane by more
    # than `match_tolerance` of the depth dropped, no clamp), so the noisy input's low-pass flickers less into
    # the output; the target and the gain together span at most `match_frames` frames (a pixel whose input
    # the accumulation averaged over n frames keeps `match_frames` / n frames of gains); 0 or 1: each frame's
    # own gain. Carried in the state after TAA's; a single frame (`apply`) and a frame without `world_to_ndc`
    # get their own gain; without the match (`match_level` 0) it does nothing. Inference only.
    match_frames: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    match_tolerance: float = dataclasses.field(default=0.02, metadata={"fine_tune": True})
    # Exact pixels (ours, issue 34; DEMC's, `jaxdenoise.methods.demc.Config.keep_exact`): with
    # `keep_exact` the output keeps the input's colour where `jaxdenoise.filters.exact_mask` says the
    # estimate is exact (a frame of >= 2 spp: `color_var` 0 in every channel; else, with `exact_window`
    # > 0, the whole `exact_window` x `exact_window` square agreeing bit for bit), before and after the
    # level match, so the network's error on a directly seen light moves no level around it. The
    # recurrent state is not touched; inference only.
    keep_exact: bool = dataclasses.field(default=False, metadata={"fine_tune": True})
    exact_window: int = dataclasses.field(default=0, metadata={"fine_tune": True})
    # Background (ours, issue 34; docs/methods/rae.md "Background"): with `keep_background` a pixel whose
    # every sample found no surface (a zero `normal`, `jaxdenoise.view.has_hit`: the environment seen
    # directly or through delta bounces) keeps its input's colour, where and when `keep_exact` keeps exact
    # pixels (before and after TAA and the level match). The recurrent state is not touched; inference only.
    keep_background: bool = dataclasses.field(default=False, metadata={"fine_tune": True})
    # Input accumulation (ours, issue 34; docs/methods/rae.md "Input accumulation"): with `accumulate_samples`
    # S > 0 each frame's noisy colour (its outliers cut first when `outlier_clamp` is on) is averaged with the
    # previous frames' reprojected through the world positions and cameras (`jaxdenoise.filters.accumulate_step`:
    # a running mean of at most S / spp frames per pixel, so a frame of S spp or more keeps no history; no
    # luminance weights; taps off the pixel's tangent plane by more than `accumulate_tolerance` of the depth
    # dropped; the history's luminance limited to `accumulate_clamp` x the larger of the frame's level and
    # the current 3x3 maximum) before the network, whose rate channel then reads each pixel's samples times
    # the frames averaged; the level match's target is that mean. Carried in the state after the recurrent
    # one (before TAA's); a single frame (`apply`) and a frame without `world_to_ndc` get none. Inference only.
    accumulate_samples: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    accumulate_tolerance: float = dataclasses.field(default=0.02, metadata={"fine_tune": True})
    accumulate_clamp: float = dataclasses.field(default=4.0, metadata={"fine_tune": True})
    # Temporal anti-aliasing (Sec. 5.4: "we apply TAA as a supplemental post-process pass to all
    # methods. Our method also benefits from TAA"; its settings are not given, ours: docs/methods/rae.md
    # "Temporal anti-aliasing"): with `taa_alpha` > 0 each output frame of a sequence is blended with the
    # previous frames' result reprojected through the world positions and the cameras
    # (`jaxdenoise.filters.taa_step`: a running mean capped at 1 / `taa_alpha` frames, colours weighted
    # by Karis's 1 / (1 + luminance / the frame's level), the history clamped to the frame's `taa_window`
    # x `taa_window` neighbourhood, and with `taa_tolerance` > 0 taps off the pixel's tangent plane by
    # more than that fraction of the depth dropped), before the level match (which puts the result at the
    # input's level: the weights favour darker colours); the history carries TAA's result, not the match's.
    # Carried in the state beside the recurrent one; a single frame (`apply`) is unchanged, and a frame
    # without `world_to_ndc` (not required) gets no TAA.
    taa_alpha: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    taa_window: int = dataclasses.field(default=3, metadata={"fine_tune": True})
    taa_tolerance: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    # Refinement (ours, issue 34; DEMC's, `jaxdenoise.methods.demc.Config.refine_sigma`; docs/methods/rae.md
    # "Refinement"): with `refine_sigma` > 0 each output frame (exact pixels kept) goes through
    # `jaxdenoise.filters.refine`, a cross-bilateral pass guided by the first-hit albedo and normal, before
    # TAA and the level match; 0: off. The recurrent state is not touched; inference only.
    refine_sigma: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    refine_range: float = dataclasses.field(default=0.4, metadata={"fine_tune": True})
    refine_albedo: float = dataclasses.field(default=0.03, metadata={"fine_tune": True})
    refine_normal: float = dataclasses.field(default=0.1, metadata={"fine_tune": True})
    # Output clamp (ours, issue 34's halo check; docs/methods/rae.md "Output clamp"): with `output_clamp` > 0
    # each output frame's luminance (after the refinement, before TAA and the level match; exposure-scaled)
    # is limited to `output_clamp` times the largest luminance at Chebyshev distance `output_clamp_radius`
    # (`jaxdenoise.filters.clamp_outliers` with ``radius``): a peak narrower than 2 r - 1 pixels that the
    # network let through from an input spike is cut, a line, edge or corner passes; 0: off.
    output_clamp: float = dataclasses.field(default=0.0, metadata={"fine_tune": True})
    output_clamp_radius: int = dataclasses.field(default=3, metadata={"fine_tune": True})
    # The training recipe the weights folder is named after: "" (the default weights) or "paper"
    # (Sec. 5.3: 1-spp fly-throughs, the paper's input; registered as "rae-paper").
    recipe: str = dataclasses.field(default="", metadata={"training": True})
    # Training data (Sec. 4.3, 5.3: 1-spp inputs, the "paper" recipe; ours: 1-16), 7-frame sequences,
    # batch 4; crop ours (CPU).
    train_spps: tuple[int, ...] = (1, 4, 16)
    # A level term beside Sec. 4.4's loss (ours, issue 34; DEMC's `level_weight`, docs/methods/rae.md):
    # `level_weight` times the RelMSE (eps `level_eps`) between `level_pool` x `level_pool` block means of
    # the HDR prediction and target, per frame, frame-weighted like the other terms; 0 = the paper's loss.
    # The L1 of 0.2-powered images is least at the power domain's median, below the mean of a skewed
    # target (a dark level); a block's mean has no such pull.
    level_weight: float = dataclasses.field(default=0.0, metadata={"training": True})
    level_pool: int = dataclasses.field(default=8, metadata={"training": True})
    level_eps: float = dataclasses.field(default=1e-3, metadata={"training": True})
    # A spike term (ours, issue 34's halo check; docs/methods/rae.md "A spike term"): `spike_weight` times
    # the mean over pixels of max(0, p - k M)^2 / ((k M)^2 + `level_eps`), p the prediction's channel mean,
    # M the target's largest channel mean in the `spike_window` square around the pixel, k `spike_factor`:
    # only light drawn above k times anything the target has nearby is charged (the L1 of 0.2-powered
    # values charges an output of 50 over a target of 5 only 0.8); 0 = off.
    spike_weight: float = dataclasses.field(default=0.0, metadata={"training": True})
    spike_factor: float = dataclasses.field(default=4.0, metadata={"training": True})
    spike_window: int = dataclasses.field(default=9, metadata={"training": True})
    # Training on accumulated inputs (ours, issue 34; docs/methods/rae.md "Input accumulation"): with
    # `train_accumulate` p > 0 and `accumulate_samples` on, each training sequence crop of fewer spp than
    # `accumulate_samples` is, with probability p, given the colour `step` would accumulate (the same filter and
    # settings, reprojected within the crop: `crop_projection`) and the rate channel its samples; such a crop
    # is not played backwards (accumulation runs forward in time). 0: the colour as rendered.
    train_accumulate: float = dataclasses.field(default=0.0, metadata={"training": True})
    train_frames: int = 7
    train_crop: int = 64
    train_batch: int = 4
    stop_probability: float = 0.1  # camera stops (Sec. 4.3; rate ours)


# Adam 1e-3, betas 0.9 / 0.99, tenfold geometric ramp-up then 1/sqrt(t) (Sec. 5.3), in steps.
TRAIN: dict[str, Any] = {"optimizer": "adam", "learning_rate": 1e-3, "adam_b1": 0.9, "adam_b2": 0.99,
                         "schedule": "rampup_rsqrt", "schedule_every": 200, "schedule_factor": 10.0,
                         "steps": 2000, "checkpoint_every": 50}


INPUT_TRANSFORMS = ("power", "linear")
EXPOSURES = ("none", "frame")
RECIPES = ("", "paper")
# The rate channel: log2(spp) / RATE_SCALE (0 at 1 spp, 1 at 16, 1.5 at 64).
RATE_SCALE = 4.0


def WEIGHTS(config: Config) -> str:
    return f"rae-{config.recipe}" if config.recipe else "rae"


def _check(config: Config) -> None:
    bad = [a for a in config.aux if a not in AUX]
    if bad:
        raise JaxdenoiseError(f"rae: config.aux has unknown {bad}; expected some of {list(AUX)}")
    if len(config.widths) != 5:
        raise JaxdenoiseError(f"rae: config.widths must give the five encoder stages, got {config.widths}")
    if config.decoder_widths is not None and len(config.decoder_widths) != 5:
        raise JaxdenoiseError(f"rae: config.decoder_widths must give five decoder stages, got {config.decoder_widths}")
    if not config.outlier_clamp >= 0 or (config.outlier_clamp and config.exposure != "frame"):
        raise JaxdenoiseError(f"rae: config.outlier_clamp must be >= 0 (0: off) and needs exposure 'frame' (the "
                              f"frame's level sets its floor), got {config.outlier_clamp!r} with {config.exposure!r}")
    if not (np.isfinite(config.outlier_rel_sd) and config.outlier_rel_sd >= 0) or (config.outlier_rel_sd
                                                                                   and not config.outlier_clamp):
        raise JaxdenoiseError(f"rae: config.outlier_rel_sd must be a finite number >= 0 (0: off) and needs "
                              f"outlier_clamp (whose floor it drops), got {config.outlier_rel_sd!r} with "
                              f"outlier_clamp {config.outlier_clamp!r}")
    check_match_settings("rae: config.", config.match_level, config.match_spike, config.match_max_gain,
                         config.match_spike_by_rate)
    if config.match_level and config.exposure != "frame":
        raise JaxdenoiseError(f"rae: config.match_level needs exposure 'frame' (the frame's level sets the cut's "
                              f"floor), got match_level {config.match_level} with {config.exposure!r}")
    f, t = config.match_frames, config.match_tolerance
    if not all(isinstance(v, (int, float)) and 0 <= v < float("inf") for v in (f, t)):
        raise JaxdenoiseError(f"rae: config.match_frames (0: off) and config.match_tolerance (a fraction of the depth) "
                              f"must be finite numbers >= 0, got {f!r} and {t!r}")
    check_exact_window("rae: config.exact_window", config.exact_window)
    if config.taa_alpha:
        check_taa_settings("rae: config.", config.taa_alpha, config.taa_window, config.taa_tolerance)
    a, t, k = config.accumulate_samples, config.accumulate_tolerance, config.accumulate_clamp
    if not all(isinstance(v, (int, float)) and 0 <= v < float("inf") for v in (a, t, k)):
        raise JaxdenoiseError(f"rae: config.accumulate_samples (0: off), config.accumulate_tolerance (a fraction of "
                              f"the depth) and config.accumulate_clamp (0: off) must be finite numbers >= 0, got "
                              f"{a!r}, {t!r} and {k!r}")
    if config.refine_sigma:
        check_refine_settings("rae: config.", config.refine_sigma, config.refine_range, config.refine_albedo,
                              config.refine_normal)
    if not config.output_clamp >= 0 or (config.output_clamp and config.exposure != "frame"):
        raise JaxdenoiseError(f"rae: config.output_clamp must be >= 0 (0: off) and needs exposure 'frame' (the "
                              f"frame's level sets its floor), got {config.output_clamp!r} with {config.exposure!r}")
    r = config.output_clamp_radius
    if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 1:
        raise JaxdenoiseError(f"rae: config.output_clamp_radius must be an int >= 1, got {r!r}")
    w = config.spike_window
    if not config.spike_weight >= 0 or not config.spike_factor > 0 or isinstance(w, bool) \
            or not isinstance(w, (int, np.integer)) or w < 1 or w % 2 == 0:
        raise JaxdenoiseError(f"rae: config.spike_weight must be >= 0, config.spike_factor > 0 and config.spike_window "
                              f"an odd int >= 1, got {config.spike_weight!r}, {config.spike_factor!r} and {w!r}")
    if not 0 <= config.train_accumulate <= 1 or (config.train_accumulate and not config.accumulate_samples):
        raise JaxdenoiseError(f"rae: config.train_accumulate must be in [0, 1] and needs config.accumulate_samples "
                              f"> 0, got {config.train_accumulate!r} with {config.accumulate_samples!r}")
    if not config.level_weight >= 0 or int(config.level_pool) < 1 or not config.level_eps > 0:
        raise JaxdenoiseError(f"rae: config.level_weight must be >= 0, config.level_pool >= 1 and config.level_eps "
                              f"> 0, got {config.level_weight!r}, {config.level_pool!r} and {config.level_eps!r}")
    for name, allowed in (("input_transform", INPUT_TRANSFORMS), ("exposure", EXPOSURES), ("recipe", RECIPES)):
        if getattr(config, name) not in allowed:
            raise JaxdenoiseError(f"rae: config.{name} is {getattr(config, name)!r}; expected one of {allowed}")


def needs(config: Config) -> frozenset[str]:
    """Colour and albedo (demodulation), and what the auxiliary inputs are derived from: the world
    normal and position with the frame's camera (view-space normal, linear depth), roughness."""
    _check(config)
    out = {"color", "albedo"}
    if "normal" in config.aux or "depth" in config.aux:
        out |= {"normal", "world_to_camera"}
    if "depth" in config.aux:
        out.add("position")
    if "roughness" in config.aux:
        out.add("roughness")
    if config.rate_input or config.accumulate_samples:
        out.add("spp")
    if config.keep_exact:
        out.add("color_var")
    if config.keep_background:
        out.add("normal")
    if config.taa_alpha or config.accumulate_samples or _gain_history(config):
        out |= {"position", "normal", "world_to_ndc"}
    if config.refine_sigma:
        out.add("normal")
    return frozenset(out)


def required(config: Config) -> frozenset[str]:
    """`needs` without roughness (a frame that lacks it gets ``config.missing_roughness``), the colour
    variance (a 1-spp frame has none; ``keep_exact`` then uses its window rule) and the camera's
    projection (a frame without ``world_to_ndc`` is denoised without TAA)."""
    return needs(config) - {"roughness", "color_var", "world_to_ndc"}


def in_channels(config: Config) -> int:
    return 3 + sum(AUX[a] for a in config.aux) + int(config.rate_input)


# -- network -------------------------------------------------------------------------------------

def _layers(config: Config) -> dict:
    gain = 2.0 / (1.0 + config.slope ** 2)
    conv = lambda c: nn.Conv(c, 3, w_init=nn.he_normal_init(gain))
    act = nn.LeakyRelu(config.slope)
    dec = config.decoder_widths or tuple(config.widths)
    return {"enc": [conv(w) for w in config.widths],
            "rb": [nn.RecurrentBlock(w, slope=config.slope, w_init=nn.he_normal_init(gain))
                   for w in (*config.widths, config.bottleneck)],
            "b_in": conv(config.bottleneck), "b_out": conv(config.bottleneck),
            "dec": [nn.serial(conv(d), act, conv(d), act) for d in dec],
            "out": nn.Conv(3, 3, w_init=nn.he_normal_init(1.0)), "act": act}


def init(key, config: Config) -> dict:
    _check(config)
    L = _layers(config)
    keys = iter(jax.random.split(key, 32))
    shape = (-1, 64, 64, in_channels(config))
    p: dict = {"enc": {}, "rb": {}, "dec": {}}
    skips = []
    for i, w in enumerate(config.widths):
        shape, p["enc"][str(i)] = L["enc"][i][0](next(keys), shape)
        shape, p["rb"][str(i)] = L["rb"][i][0](next(keys), shape)
        skips.append(shape)
        shape = shape[:-3] + (shape[-3] // 2, shape[-2] // 2, shape[-1])
    shape, p["b_in"] = L["b_in"][0](next(keys), shape)
    shape, p["rb"]["5"] = L["rb"][5][0](next(keys), shape)
    shape, p["b_out"] = L["b_out"][0](next(keys), shape)
    for i in reversed(range(5)):
        cat = skips[i][:-1] + (shape[-1] + skips[i][-1],)
        shape, p["dec"][str(i)] = L["dec"][i][0](next(keys), cat)
    _, p["out"] = L["out"][0](next(keys), shape)
    return p


def num_params(config: Config) -> int:
    shapes = jax.eval_shape(lambda k: init(k, config), jax.random.PRNGKey(0))
    return int(sum(np.prod(s.shape) for s in jax.tree_util.tree_leaves(shapes)))


def _state_shapes(config: Config, lead: tuple[int, ...], h: int, w: int) -> list[tuple[int, ...]]:
    hp, wp = -(-h // 32) * 32, -(-w // 32) * 32
    return [lead + (hp >> i, wp >> i, c) for i, c in enumerate((*config.widths, config.bottleneck))]


def _forward(params: dict, x: jax.Array, hidden: tuple, config: Config) -> tuple[tuple, jax.Array]:
    """One frame through the network: padded input ``(..., Hp, Wp, C)``; returns the new hidden
    states and the linear 3-channel output."""
    L = _layers(config)
    act = L["act"][1]
    pool, up = nn.MaxPool(2)[1], nn.Upsample(2, "nearest")[1]
    new, skips = [], []
    for i in range(5):
        x = act({}, L["enc"][i][1](params["enc"][str(i)], x))
        x = L["rb"][i][1](params["rb"][str(i)], x, hidden[i])
        new.append(x)
        skips.append(x)
        x = pool({}, x)
    x = act({}, L["b_in"][1](params["b_in"], x))
    x = L["rb"][5][1](params["rb"]["5"], x, hidden[5])
    new.append(x)
    x = act({}, L["b_out"][1](params["b_out"], x))
    for i in reversed(range(5)):
        x = L["dec"][i][1](params["dec"][str(i)], jnp.concatenate([up({}, x), skips[i]], -1))
    return tuple(new), L["out"][1](params["out"], x)


# -- inputs ----------------------------------------------------------------------------------------

def _get(b, f, optional: bool = False):
    """Field ``f`` of a `Buffers` or a dict frame; ``optional``: None where the frame lacks it."""
    if optional:
        return getattr(b, f, None) if isinstance(b, Buffers) else b.get(f)
    return getattr(b, f) if isinstance(b, Buffers) else b[f]


def _linear_depth(frame: Any) -> jax.Array:
    """The linear depth ``(..., H, W, 1)`` of a frame: ``depth_linear`` if a dict carries it already
    derived, else from the world position and the camera (`jaxdenoise.view.linear_depth`)."""
    if isinstance(frame, dict) and "depth_linear" in frame:
        d = frame["depth_linear"]
    else:
        d = view.linear_depth(_get(frame, "position"), _get(frame, "normal"), _get(frame, "world_to_camera"))
    return jnp.asarray(d, jnp.float32)


def frame_stats(config: Config) -> dict:
    """The per-frame statistics of `inputs` (`jaxdenoise.methods.protocol`), which the training
    pipeline computes on every whole render (each frame of a sequence its own) and carries with its
    crops: with the depth input ``depth_mean``, the mean linear depth over the whole frame's surface
    pixels (`surface_mean`); with ``exposure = "frame"`` the colour's ``color_mean``
    (`jaxdenoise.color.color_mean`)."""
    _check(config)
    stats = {}
    if "depth" in config.aux:
        stats["depth_mean"] = lambda frame: surface_mean(_linear_depth(frame))
    if config.exposure == "frame":
        stats["color_mean"] = lambda frame: color.color_mean(_get(frame, "color"))
    return stats


def exposure_scale(frame: Any, config: Config) -> jax.Array:
    """What `inputs` multiplies the colour by and the output is divided by: 1 with ``exposure =
    "none"``, else `jaxdenoise.color.exposure_scale` of the frame (of a crop's carried whole-frame
    ``color_mean`` when it has one), ``(..., 1, 1, 1)``."""
    if config.exposure == "none":
        return jnp.ones((), jnp.float32)
    return color.exposure_scale(_get(frame, "color"), carried_stat(frame, "color_mean"))


def sample_count(frame: Any, owner: str = "config.rate_input") -> jax.Array:
    """The frame's samples per pixel: its sample-count map (``spp_map``, adaptive sampling) ``(..., H, W,
    1)`` when it has one, else its ``spp`` (a scalar, or one per frame of a batch) as ``(..., 1, 1, 1)``;
    a frame with neither is refused, naming ``owner`` (what needs it)."""
    fields = frame.to_dict() if isinstance(frame, Buffers) else frame
    if fields.get(SAMPLE_COUNT_FIELD) is not None:
        return jnp.asarray(fields[SAMPLE_COUNT_FIELD], jnp.float32)
    if fields.get("spp") is None:
        raise JaxdenoiseError(f"rae: {owner} needs the frame's sample count ('spp'); it is never guessed")
    spp = jnp.asarray(fields["spp"], jnp.float32)
    return spp.reshape(spp.shape + (1,) * 3)


def rate_channel(frame: Any, shape: tuple[int, ...]) -> jax.Array:
    """The rate input ``log2(spp) / RATE_SCALE`` broadcast to ``shape`` (``(..., H, W, 1)``), from
    `sample_count` (per pixel where the frame has a sample-count map)."""
    return jnp.broadcast_to(jnp.log2(jnp.maximum(sample_count(frame), 1.0)) / RATE_SCALE, shape)


def _cut_outliers(c: Any, config: Config, frame: Any = None) -> Any:
    """The exposure-scaled colour ``c`` with ``config.outlier_clamp``'s isolated spikes cut
    (`jaxdenoise.filters.clamp_outliers`, floor the exposure level; with ``outlier_rel_sd`` and ``frame``, the
    frame ``c`` was read from, no floor on its `single_sample` pixels); ``c`` when off."""
    if not config.outlier_clamp:
        return c
    alone = single_sample(frame, config.outlier_rel_sd) if frame is not None and config.outlier_rel_sd else None
    return clamp_outliers(c, config.outlier_clamp, color.EXPOSURE_LEVEL, unfloored=alone)


def single_sample(frame: Any, rel_sd: float) -> jax.Array | None:
    """The pixels of a frame (a `Buffers` or a dict) of >= 2 samples whose relative standard error, the channel
    mean of sqrt(``color_var``) over the channel mean of ``color``, is at least ``rel_sd``: ``(..., H, W)``
    booleans, None where the frame has no ``color_var`` or no sample count (`Config.outlier_rel_sd`)."""
    fields = frame.to_dict() if isinstance(frame, Buffers) else frame
    var = fields.get("color_var")
    if var is None or (fields.get("spp") is None and fields.get(SAMPLE_COUNT_FIELD) is None):
        return None
    mean = jnp.mean(color.radiance(fields["color"]), -1)
    sd = jnp.mean(jnp.sqrt(jnp.maximum(jnp.asarray(var, jnp.float32), 0.0)), -1)
    rel = jnp.where(mean > 0, sd / jnp.where(mean > 0, mean, 1.0), 0.0)
    return (rel >= rel_sd) & (sample_count(fields, "config.outlier_rel_sd")[..., 0] >= 2)


def inputs(frame: Any, config: Config, scale: Any = None) -> jax.Array:
    """The 7 input channels (fewer with ``config.aux``, one more with ``rate_input``) of a frame or a
    batch (`Buffers` or a dict of the same names; a dict may carry ``normal_view`` / ``depth_linear``
    already derived, and each frame's whole-render statistics (`frame_stats`: ``stat.depth_mean``,
    ``stat.color_mean``), which then stand in for the array's own). ``scale``: the frame's
    `exposure_scale` when the caller has it already (it divides the output by the same factor)."""
    get = lambda f: _get(frame, f)
    scale = exposure_scale(frame, config) if scale is None else scale
    c = _cut_outliers(color.radiance(get("color")) * scale, config, frame)
    demod = color.demodulate(c, _albedo(get("albedo")), config.albedo_eps)
    parts = [color.gamma(demod, 1.0 / config.power) if config.input_transform == "power" else demod]
    has = (lambda f: f in frame) if isinstance(frame, dict) else (lambda f: False)
    if "normal" in config.aux:
        nv = get("normal_view") if has("normal_view") else view.view_normals(get("normal"), get("world_to_camera"))
        parts.append(jnp.asarray(nv, jnp.float32)[..., :2])
    if "depth" in config.aux:
        parts.append(normalized_depth(_linear_depth(frame), carried_stat(frame, "depth_mean")))
    if "roughness" in config.aux:
        rough = get("roughness") if (has("roughness") or not isinstance(frame, dict)) else None
        if rough is None:
            rough = jnp.full(c.shape[:-1] + (1,), config.missing_roughness, jnp.float32)
        parts.append(jnp.clip(jnp.asarray(rough, jnp.float32), 0.0, 1.0))
    if config.rate_input:
        parts.append(rate_channel(frame, c.shape[:-1] + (1,)))
    x = jnp.concatenate(parts, -1)
    return jnp.where(jnp.isfinite(x), x, 0.0)


def surface_mean(d: jax.Array) -> jax.Array:
    """The mean of the linear depth ``(..., H, W, 1)`` over the image's surface pixels (``d > 0``):
    ``(..., 1)``, 0 for an image without any."""
    hit = d > 0
    mean = jnp.sum(jnp.where(hit, d, 0.0), axis=(-3, -2), keepdims=True) / \
        jnp.maximum(jnp.sum(hit, axis=(-3, -2), keepdims=True), 1)
    return mean[..., 0, 0, :]


def normalized_depth(d: jax.Array, mean: Any = None) -> jax.Array:
    """Linear depth divided by ``mean`` (``(..., 1)``, one per image: the whole frame's
    `surface_mean`), by default its mean over the image's own surface pixels; 0 off the surface."""
    mean = surface_mean(d) if mean is None else jnp.asarray(mean, jnp.float32)
    return jnp.where(d > 0, d / jnp.maximum(mean[..., None, None, :], 1e-12), 0.0)


# An albedo below half an 8-bit step in every channel is "no texture" (ours, docs/methods/rae.md).
UNTEXTURED = 0.5 / 255.0


def _albedo(albedo: Any) -> jax.Array:
    """The albedo that (de)modulates (ours, docs/methods/rae.md): clipped to [0, 1] (data_gen's
    albedo is ``eval_diffuse_reflectance``, which exceeds 1 on glossy conductors, and an export
    stores albedo as 8 bits of [0, 1]), and 1 where every channel is below `UNTEXTURED` (emitters,
    the background and black materials have no texture to divide out: dividing by ``0 + eps``
    would scale a visible light 316x above its neighbours, and a network's blur across that edge
    comes back as outliers 100-1000x the reference). The same value divides and multiplies back."""
    a = jnp.clip(jnp.asarray(albedo, jnp.float32), 0.0, 1.0)
    return jnp.where(jnp.max(a, axis=-1, keepdims=True) < UNTEXTURED, 1.0, a)


def _output(y: jax.Array, albedo: Any, scale: Any, config: Config) -> jax.Array:
    """Network output (0.2-power illumination) -> HDR image, remodulated (Sec. 3.2) and divided by
    the `exposure_scale` the input was multiplied by."""
    return color.remodulate(color.inv_gamma(y, 1.0 / config.power), _albedo(albedo), config.albedo_eps) / scale


# -- the causal surface ----------------------------------------------------------------------------

def init_state(buffers: Buffers, config: Config) -> tuple:
    """Zero hidden states of the six recurrent blocks for frames of ``buffers``' size (a `Buffers` or a
    dict frame), then with ``accumulate_samples`` the input's history, with ``taa_alpha`` TAA's and with
    ``match_frames`` the level match's gains' (`jaxdenoise.filters.taa_init`: none yet)."""
    shape = tuple(np.shape(_get(buffers, "color")))
    hidden = tuple(jnp.zeros(s, jnp.float32) for s in _state_shapes(config, shape[:-3], shape[-3], shape[-2]))
    histories = (config.accumulate_samples, config.taa_alpha, _gain_history(config))
    return hidden + tuple(taa_init(shape[:-1] + (3,)) for on in histories if on)


def step(params: dict, state: tuple, buffers: Buffers, config: Config) -> tuple[tuple, jax.Array]:
    """Denoise the next frame of a sequence; returns the new state and the HDR image."""
    scale = exposure_scale(buffers, config)
    n_hidden = len(config.widths) + 1
    hidden, histories = tuple(state[:n_hidden]), list(state[n_hidden:])
    gains = histories.pop() if _gain_history(config) else None
    taa = histories.pop() if config.taa_alpha else None
    acc = histories.pop() if config.accumulate_samples else None
    c = color.radiance(_get(buffers, "color"))
    projection = _get(buffers, "world_to_ndc", optional=True)
    target, frame, length = c, buffers, 1.0
    if config.accumulate_samples and projection is not None:  # without its projection: the history kept
        fields = buffers.to_dict() if isinstance(buffers, Buffers) else dict(buffers)
        spp = sample_count(fields, "config.accumulate_samples")
        cut = _cut_outliers(c * scale, config, buffers) / scale
        acc, target, length = accumulate_step(acc, cut, _get(buffers, "position"), _get(buffers, "normal"), projection,
                                              frames=config.accumulate_samples / jnp.maximum(spp, 1.0),
                                              tolerance=config.accumulate_tolerance, clamp=config.accumulate_clamp)
        # the accumulated colour, whose variance the frame's `color_var` no longer gives (its cut already made)
        frame = {k: v for k, v in fields.items() if k != "color_var"}
        frame |= {"color": target, SAMPLE_COUNT_FIELD: spp * length}
    x, size = nn.pad_to_multiple(inputs(frame, config, scale), 32)
    hidden, y = _forward(params, x, hidden, config)
    hidden = hidden + ((acc,) if config.accumulate_samples else ())
    out = jnp.maximum(_output(nn.crop_to(y, size), _get(buffers, "albedo"), scale, config), 0.0)
    kept = None
    if config.keep_exact:  # exact pixels kept before TAA and the level match, and after them
        kept = exact_mask(_get(buffers, "color"), _get(buffers, "color_var", optional=True),
                          _get(buffers, "spp", optional=True), window=config.exact_window)
    if config.keep_background:  # the environment seen directly: its input is nearly noise-free
        bg = ~view.has_hit(_get(buffers, "normal"))
        kept = bg if kept is None else kept | bg
    if kept is not None:
        out = jnp.where(kept, c, out)
    if config.refine_sigma:  # in the exposure-scaled units, so f(k x) = k f(x) still holds
        out = refine(out * scale, _get(buffers, "albedo"), _get(buffers, "normal"), sigma=config.refine_sigma,
                     range_sigma=config.refine_range, albedo_sigma=config.refine_albedo,
                     normal_sigma=config.refine_normal) / scale
    if config.output_clamp:  # before TAA, so its history carries no peak; floor: 0.1 % of the frame's level
        out = clamp_outliers(out * scale, config.output_clamp, 1e-3 * color.EXPOSURE_LEVEL,
                             radius=config.output_clamp_radius) / scale
    if config.taa_alpha:  # before the match, which puts TAA's result at the input's level
        if projection is not None:  # a frame without its camera's projection: no TAA, the history kept
            taa, out = taa_step(taa, out, _get(buffers, "position"), _get(buffers, "normal"), projection,
                                alpha=config.taa_alpha, window=config.taa_window, tolerance=config.taa_tolerance)
        hidden = hidden + (taa,)
    if config.match_level:
        spp = _get(buffers, "spp", optional=True) if config.match_spike_by_rate else None
        gain = input_gain(out * scale, target * scale, config.match_level, spike=config.match_spike,
                          floor=color.EXPOSURE_LEVEL, max_gain=config.match_max_gain or float("inf"), spp=spp,
                          output_cut=config.match_output_cut)
        if _gain_history(config):
            if projection is not None:  # a frame without its camera's projection: its own gain, the history kept
                gains, gain, _ = accumulate_step(gains, gain, _get(buffers, "position"), _get(buffers, "normal"),
                                                 projection, frames=config.match_frames / length,
                                                 tolerance=config.match_tolerance, clamp=0.0)
            hidden = hidden + (gains,)
        out = out * gain
    if kept is not None and (config.match_level or config.taa_alpha or config.refine_sigma or config.output_clamp):
        out = jnp.where(kept, c, out)
    return hidden, out


def apply(params: dict, buffers: Buffers, config: Config) -> jax.Array:
    """A single frame (or a batch of independent frames): the first step from a zero state. TAA and the
    input accumulation are left out: without a history each returns the frame as it is."""
    config = dataclasses.replace(config, taa_alpha=0.0, accumulate_samples=0.0, match_frames=0.0)
    return step(params, init_state(buffers, config), buffers, config)[1]


def _gain_history(config: Config) -> bool:
    """Whether ``config`` carries the level match's gains from frame to frame (``match_frames`` > 1)."""
    return bool(config.match_level and config.match_frames > 1)


# -- loss --------------------------------------------------------------------------------------------

def log_kernel(sigma: float) -> np.ndarray:
    """Laplacian of Gaussian, ``-(1 / (pi s^4)) (1 - r^2 / (2 s^2)) exp(-r^2 / (2 s^2))`` on a
    ``2 ceil(3 s) + 1`` square, shifted to zero sum (a constant image has no high frequency)."""
    r = int(math.ceil(3 * sigma))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64)
    q = (xx ** 2 + yy ** 2) / (2 * sigma ** 2)
    k = -(1.0 / (math.pi * sigma ** 4)) * (1 - q) * np.exp(-q)
    return (k - k.mean()).astype(np.float32)


def _hfen(img: jax.Array, sigma: float) -> jax.Array:
    """The LoG response of each channel (zero padding at the border), any leading axes."""
    k = jnp.asarray(log_kernel(sigma))
    c = img.shape[-1]
    w = jnp.tile(k[:, :, None, None], (1, 1, 1, c))
    flat = img.reshape((-1,) + img.shape[-3:])
    y = jax.lax.conv_general_dilated(flat, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                     feature_group_count=c)
    return y.reshape(img.shape)


def loss_terms(pred: jax.Array, target: jax.Array, config: Config) -> dict:
    """Per-frame ``L_s``, ``L_g``, ``L_t`` of ``(B, T, H, W, 3)`` HDR sequences (``L_t`` of frame 0 is 0),
    and with ``level_weight`` the level term (`Config.level_weight`): the RelMSE of ``level_pool``-pixel
    block means (`jaxdenoise.metrics.relmse_per_image`, eps ``level_eps``) in HDR; with ``spike_weight``
    the spike term (`Config.spike_weight`)."""
    p = color.gamma(pred, 1.0 / config.power)
    t = color.gamma(jnp.maximum(target, 0.0), 1.0 / config.power)
    ls = jnp.mean(jnp.abs(p - t), axis=(0, 2, 3, 4))
    lg = jnp.mean(jnp.abs(_hfen(p, config.hfen_sigma) - _hfen(t, config.hfen_sigma)), axis=(0, 2, 3, 4))
    dt = jnp.abs((p[:, 1:] - p[:, :-1]) - (t[:, 1:] - t[:, :-1]))
    lt = jnp.concatenate([jnp.zeros((1,)), jnp.mean(dt, axis=(0, 2, 3, 4))])
    terms = {"spatial": ls, "hfen": lg, "temporal": lt}
    if config.level_weight:
        blocks = [nn.block_means(a, config.level_pool) for a in (pred, target)]
        terms["level"] = jnp.mean(metrics.relmse_per_image(*blocks, config.level_eps), axis=0)
    if config.spike_weight:
        w = int(config.spike_window)
        near = config.spike_factor * jax.lax.reduce_window(jnp.maximum(target, 0.0).mean(-1), -jnp.inf, jax.lax.max,
                                                           (1, 1, w, w), (1, 1, 1, 1), "SAME")
        over = jnp.maximum(pred.mean(-1) - near, 0.0)
        terms["spike"] = jnp.mean(over ** 2 / (near ** 2 + config.level_eps), axis=(0, 2, 3))
    return terms


def run_sequence(params: dict, x: jax.Array, albedo: jax.Array, config: Config, scale: Any = None) -> jax.Array:
    """The training-time pass: ``(B, T, H, W, C)`` inputs through the network frame by frame from a
    zero state, in an unrolled loop (back-propagation through time stays fast: module docstring);
    returns the ``(B, T, H, W, 3)`` HDR predictions (not clamped, so the loss keeps its gradient).
    ``scale`` is each frame's `exposure_scale`, ``(B, T, 1, 1, 1)`` (None: 1)."""
    scale = jnp.ones(x.shape[:2] + (1, 1, 1), x.dtype) if scale is None else scale
    b, t, h, w = x.shape[:4]
    xp, size = nn.pad_to_multiple(x, 32)
    state = tuple(jnp.zeros(s, x.dtype) for s in _state_shapes(config, (b,), h, w))
    outs = []
    for k in range(t):
        state, y = _forward(params, xp[:, k], state, config)
        outs.append(_output(nn.crop_to(y, size), albedo[:, k], scale[:, k], config))
    return jnp.stack(outs, axis=1)


def frame_weights(config: Config, t: int) -> tuple[float, ...]:
    """The loss weights of a ``t``-frame sequence (Sec. 4.4 gives seven, rising to 1 at the last
    frame so that frames with more temporal context count more): the last ``t`` of them for up to
    seven frames; a longer sequence keeps the seven for its first frames and weighs every later one
    by the last weight (1: a frame with at least six frames of context). docs/methods/rae.md."""
    w = tuple(config.frame_weights)
    return w[len(w) - t:] if t <= len(w) else w + (w[-1],) * (t - len(w))


def loss(params: dict, batch: dict, config: Config):
    """Sec. 4.4 on a batch of sequences ``{"x": (B, T, H, W, C), "albedo", "reference": (B, T, H, W, 3)}``
    (and ``"scale"``, each frame's `exposure_scale`, with ``exposure = "frame"``): the frames run
    through the network in order from a zero state (an unrolled loop), and the frame-weighted
    combination of the three terms is returned (with the terms as aux)."""
    pred = run_sequence(params, batch["x"], batch["albedo"], config, batch.get("scale"))
    t = pred.shape[1]
    terms = loss_terms(pred, batch["reference"], config)
    fw = jnp.asarray(frame_weights(config, t), jnp.float32)
    ws, wg, wt = config.loss_weights
    per_frame = ws * terms["spatial"] + wg * terms["hfen"] + wt * terms["temporal"]
    if config.level_weight:
        per_frame = per_frame + config.level_weight * terms["level"]
    if config.spike_weight:
        per_frame = per_frame + config.spike_weight * terms["spike"]
    value = jnp.sum(fw * per_frame) / jnp.sum(fw)
    return value, {"terms": {k: jnp.sum(fw * v) / jnp.sum(fw) for k, v in terms.items()}}


# -- training data -------------------------------------------------------------------------------

_SOURCE = ("albedo", "normal", "position", "roughness")


def make_dataset(data_dir, config: Config, *, progress: bool = True):
    """The fly-through sequences of ``data_dir`` (``scene/frame_XXXX/``) at ``train_spps``, decoded
    once (`jaxdenoise.pipeline.open_training_data`), or an export of sequence crops."""
    from ..pipeline import open_training_data

    _check(config)
    fields = [f for f in _SOURCE if f in needs(config)]
    return open_training_data(data_dir, fields, spps=config.train_spps, progress=progress,
                              fill={"roughness": config.missing_roughness}, stats=frame_stats(config))


@functools.partial(jax.jit, static_argnums=1)
def _view_inputs(seq: dict, config: Config) -> dict:
    """The view-space inputs of a batch of sequence crops (``(B, T, H, W, .)`` with their cameras)."""
    out = {}
    if "normal" in config.aux:
        out["normal_view"] = view.view_normals(seq["normal"], seq["world_to_camera"])
    if "depth" in config.aux:
        out["depth_linear"] = view.linear_depth(seq["position"], seq["normal"], seq["world_to_camera"])
    return out


_inputs = jax.jit(inputs, static_argnums=1)
_scale = jax.jit(exposure_scale, static_argnums=1)


def _derive(seq: dict, config: Config) -> dict:
    """Add the view-space inputs of a batch of crops (before augmentation: a quarter turn of the
    image then turns the view-space normal with it, `jaxdenoise.pipeline.augment`) and drop what they
    came from; the per-frame statistics of the whole renders stay."""
    out = {k: np.asarray(seq[k]) for k in ("color", "albedo", "reference", "spp", SAMPLE_COUNT_FIELD) if k in seq}
    out.update({k: np.asarray(v) for k, v in carried_stats(seq).items()})
    if "roughness" in config.aux:
        out["roughness"] = np.asarray(seq["roughness"])
    cam = {k: seq[k] for k in ("normal", "position", "world_to_camera") if k in seq}
    out.update({k: np.asarray(v) for k, v in _view_inputs(cam, config).items()})
    return out


def crop_projection(position: np.ndarray, normal: np.ndarray, world_to_ndc: np.ndarray, *,
                    min_pixels: int = 16, reach: float = 3.0) -> np.ndarray | None:
    """The ``(4, 4)`` matrix ``A`` such that ``A @ world_to_ndc`` projects world points to the NDC of a
    square crop of a frame (`jaxdenoise.filters.reproject`'s convention for an image of the crop's size),
    for a crop whose window in the frame is not recorded: fitted (least squares) from where the crop's
    own surface pixels' world ``position`` ``(c, c, 3)`` project through the frame's ``world_to_ndc``,
    NDC x against the column and NDC y against the row (each a line: the projection of a pixel's sample
    lies in or near that pixel), then again over the pixels within ``reach`` pixels of the first fit (a
    pixel filter wider than the pixel draws samples from up to 2-3 pixels away; the library's renders do).
    The same ``A`` holds for every frame of a sequence crop (one window in screen space). None with fewer
    than ``min_pixels`` surface pixels in front of the camera or fewer than 90 % of them within ``reach``
    pixels of the fit (a crop whose positions do not project into it: a mirror's or glass's first hits)."""
    c = position.shape[0]
    q = position @ world_to_ndc[:3, :3].T + world_to_ndc[:3, 3]
    w = position @ world_to_ndc[3, :3] + world_to_ndc[3, 3]
    ok = np.any(normal != 0, axis=-1) & (w > 1e-6)
    ndc = q[..., :2] / np.where(ok, w, 1.0)[..., None]
    ok &= np.all(np.isfinite(ndc) & (np.abs(ndc) < 4.0), axis=-1)
    if ok.sum() < min_pixels:
        return None
    rows, cols = (v + 0.5 for v in np.nonzero(ok))
    nx, ny = ndc[..., 0][ok], ndc[..., 1][ok]
    ax, bx = np.polyfit(cols, nx, 1)
    ay, by = np.polyfit(rows, ny, 1)
    if not (ax > 0 and ay < 0):
        return None
    inl = (np.abs(ax * cols + bx - nx) <= reach * ax) & (np.abs(ay * rows + by - ny) <= -reach * ay)
    if inl.sum() < max(min_pixels, 0.9 * ok.sum()):
        return None
    ax, bx = np.polyfit(cols[inl], nx[inl], 1)
    ay, by = np.polyfit(rows[inl], ny[inl], 1)
    a = np.eye(4, dtype=np.float64)  # crop NDC x = 2 (x - bx) / (ax c) - 1, y = 1 - 2 (y - by) / (ay c)
    a[0, 0], a[0, 3] = 2.0 / (ax * c), -2.0 * bx / (ax * c) - 1.0
    a[1, 1], a[1, 3] = -2.0 / (ay * c), 1.0 + 2.0 * by / (ay * c)
    return a


@functools.partial(jax.jit, static_argnums=(5,))
def _accumulate_crop(color_: jax.Array, position: jax.Array, normal: jax.Array, world_to_ndc: jax.Array,
                     cap: jax.Array, config: Config) -> tuple[jax.Array, jax.Array]:
    """What `step` accumulates over one sequence crop ``(T, c, c, .)`` (``world_to_ndc`` already in the
    crop's NDC, ``cap`` the frames to keep per frame ``(T,)``): ``(colour (T, c, c, 3), length (T, c, c, 1))``."""
    state, out, lengths = taa_init(color_.shape[1:]), [], []
    for t in range(color_.shape[0]):
        state, mean, length = accumulate_step(state, color_[t], position[t], normal[t], world_to_ndc[t],
                                              frames=cap[t], tolerance=config.accumulate_tolerance,
                                              clamp=config.accumulate_clamp)
        out.append(mean)
        lengths.append(length)
    return jnp.stack(out), jnp.stack(lengths)


def _accumulated(seq: dict, config: Config, rng: np.random.Generator) -> tuple[dict, list[bool]]:
    """``seq`` (un-augmented sequence crops) with ``train_accumulate``'s share of its crops of fewer spp than
    ``accumulate_samples`` given `step`'s accumulated colour (outliers cut first, as `step` does), and a
    per-pixel ``spp_map`` on every crop (the samples averaged); and which crops were accumulated."""
    out = dict(seq)
    colour = np.array(seq["color"], np.float32)
    spp = np.asarray(seq["spp"], np.float32)  # (B, T)
    spp_map = np.broadcast_to(spp[..., None, None, None], colour.shape[:-1] + (1,)).copy()
    done = []
    for i in range(colour.shape[0]):
        a = None
        if rng.random() < config.train_accumulate and spp[i, 0] < config.accumulate_samples:
            a = crop_projection(np.asarray(seq["position"][i, 0]), np.asarray(seq["normal"][i, 0]),
                                np.asarray(seq["world_to_ndc"][i, 0], np.float64))
        if a is None:
            done.append(False)
            continue
        frame = {"color": colour[i], **{k: v[i] for k, v in carried_stats(seq).items()}}
        scale = np.asarray(_scale(frame, config))
        cut = np.asarray(_cut_outliers(colour[i] * scale, config)) / scale
        cams = np.einsum("ij,tjk->tik", a, np.asarray(seq["world_to_ndc"][i], np.float64)).astype(np.float32)
        mean, length = _accumulate_crop(cut, seq["position"][i], seq["normal"][i], cams,
                                        config.accumulate_samples / np.maximum(spp[i], 1.0), config)
        colour[i], spp_map[i] = np.asarray(mean), spp[i][:, None, None, None] * np.asarray(length)
        done.append(True)
    out["color"], out[SAMPLE_COUNT_FIELD] = colour, spp_map
    return out, done


def batch(dataset, step: int, config: Config, rng: np.random.Generator) -> dict:
    """``train_batch`` sequence crops of ``train_frames`` frames (Sec. 4.3: camera stops, backward
    playback, quarter turns, mirrors, colour modulation), as network inputs. Computed on the host's
    CPU (jitted there), beside an accelerator's training step."""
    from ..pipeline import augment

    seq = dataset.sequences(config.train_batch, config.train_crop, rng, frames=config.train_frames,
                            stop_probability=config.stop_probability, augment=False)
    with jax.default_device(jax.local_devices(backend="cpu")[0]):
        done = [False] * config.train_batch
        if config.train_accumulate:
            seq, done = _accumulated(seq, config, rng)
        derived = _derive(seq, config)
        items = [augment({k: v[i] for k, v in derived.items()}, rng, reverse=not done[i])
                 for i in range(config.train_batch)]
        stacked = {k: np.stack([it[k] for it in items]) for k in items[0]}
        scale = _scale(stacked, config)
        x = np.asarray(_inputs(stacked, config, scale))
        out = {"x": x, "albedo": stacked["albedo"], "reference": stacked["reference"]}
        if config.exposure == "frame":
            out["scale"] = np.asarray(scale)
    return out
