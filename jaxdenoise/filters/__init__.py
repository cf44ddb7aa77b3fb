"""Pure image filters (docs/architecture.md "Layout": filters/), after Kalantari, Bako & Sen 2015.

All filters take and return ``(H, W, C)`` float arrays, accept scalar or per-pixel ``(H, W)``
parameters, are differentiable in every continuous parameter, keep static sizes (``radius``,
``patch_radius``) keyword-only, and never materialize an ``H x W x window^2`` weight tensor.
See each module's docstring for the exact equations and edge handling. Two helpers that act on a
network's input or output, `clamp_outliers`, `match_level` and `match_to_input` (with their gains,
`level_gain` and `input_gain`), take ``(..., H, W, C)``
arrays with any leading axes and static scalar parameters instead (no per-pixel maps, no parameter
gradients); `check_match_settings` refuses a network config's settings for `match_to_input`.
`exact_mask` (a boolean mask, not a filter) says where a frame's estimate is exact, for a denoiser to keep
its input there; `check_exact_window` refuses a config's window for it. `taa_step` (with `taa_init`,
`reproject`, `TaaState`, `check_taa_settings`) is temporal anti-aliasing over a sequence's outputs: a
state carried from frame to frame, not a filter of one image; `accumulate_step` carries the same state to
average a sequence's noisy inputs over frames (no clamp, no HDR weights). `refine` (with `check_refine_settings`)
is a feature-guided cross-bilateral pass over a network's output, any leading axes, static settings.
"""
from ._common import FilterError
from .bilateral import (DELTA, ZETA, bilateral, cross_bilateral, drop_constant_features,
                        spatiotemporal_cross_bilateral)
from .exact import check_exact_window, exact_mask
from .gaussian import gaussian, gaussian_kernel_1d
from .level import check_match_settings, input_gain, level_gain, match_level, match_to_input
from .nlm import cross_nlm, prefilter_features
from .refine import check_refine_settings, refine
from .spikes import clamp_outliers, remove_spikes
from .taa import TaaState, accumulate_step, check_taa_settings, hdr_weight, reproject, taa_init, taa_step

__all__ = [
    "DELTA",
    "FilterError",
    "TaaState",
    "ZETA",
    "accumulate_step",
    "bilateral",
    "check_exact_window",
    "check_match_settings",
    "check_refine_settings",
    "check_taa_settings",
    "clamp_outliers",
    "cross_bilateral",
    "cross_nlm",
    "drop_constant_features",
    "exact_mask",
    "gaussian",
    "gaussian_kernel_1d",
    "hdr_weight",
    "input_gain",
    "level_gain",
    "match_level",
    "match_to_input",
    "prefilter_features",
    "refine",
    "remove_spikes",
    "reproject",
    "spatiotemporal_cross_bilateral",
    "taa_init",
    "taa_step",
]
