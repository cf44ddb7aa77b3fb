"""LBF: learning-based filtering, Kalantari, Bako, Sen 2015 ("A Machine Learning Approach for
Filtering Monte Carlo Noise"), registered as ``lbf`` (cross-bilateral) and ``lbf-nlm`` (cross
non-local means, the paper's Appendix).

Pipeline per frame (Fig. 4):

1. prefilter the K additional primary features (world position, shading normal, first/second
   hit texture, direct visibility) with non-local means, 11x11 window, 7x7 patches, and smooth
   their variances with the same weights (Sec. 3.2; `jaxdenoise.filters.nlm.prefilter_features`);
2. compute the 7K+1 = 36 secondary features (Sec. 3.3; `lbf_features.secondary_features`);
3. normalize them with the training set's mean and standard deviation (Sec. 4.2, stored in the
   params under ``"norm"``) and run the MLP 36 -> 10 -> K+1 (sigmoid hidden, softplus output,
   Sec. 4.1), whose outputs are the filter's parameters in the auxiliary form
   ``lambda = 1 / (2 theta^2)`` (Appendix);
4. filter: cross-bilateral (Eq. 1-2, 11-12; spatial lambda + K feature lambdas, colour fixed at
   beta = 7, Sec. 4.2) or cross-NLM (Eq. 16-17; patch lambda + K feature lambdas), 55x55 window;
5. remove spikes in the filtered result (Sec. 4.3; not used in training, as in the paper).

A leading axis on `apply`'s input is a batch of independent frames. Sequences go through the
sequence driver (`jaxdenoise.sequence`, `jaxdenoise.denoise_sequence`) as a *windowed* method: the
7-frame spatio-temporal cross-bilateral filter of Sec. 5 with the same network, without retraining
(each frame's parameters come from its own features, `prepare_frame`), frame t emitted once frame
t+3 has arrived, the window clipped at the ends of the sequence (`window`, `apply_window`).
``lbf-nlm`` filters sequences frame by frame (the paper's spatio-temporal extension is for the
cross-bilateral filter only).

The frame's ``spp`` is part of what the method reads (`needs`): the inverse sample count is a
secondary feature and the per-sample standard deviations scale with it; a frame without it is
refused.

Training (Sec. 3.1, 4.2): the loss of Eq. 8, ``n/2 sum_q (c_hat - c)^2 / (c^2 + eps)`` averaged
over pixels, back-propagated through the filter with ``jax.grad``; mini-batches hold one crop per
sampling rate (4, 8, 16, 32, 64 spp) of each training scene, alternating between the noise
instances step by step; RPROP (Adam optional). See `make_dataset`, `batch` and `jaxdenoise.train`.
Choices the paper leaves open are in docs/methods/lbf.md.
"""
from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import nn
from ..buffers import Buffers, BuffersError, map_frames, with_variances
from ..filters import cross_bilateral, cross_nlm, remove_spikes, spatiotemporal_cross_bilateral
from ..filters.nlm import prefilter_guides
from .lbf_features import CATEGORIES, PAPER_FEATURES, feature_categories, num_features, secondary_features
from ..errors import JaxdenoiseError

__all__ = ["Config", "needs", "window", "init", "apply", "prepare_frame", "apply_window", "postprocess", "loss",
           "prepare", "filter_params", "filter_with",
           "make_dataset", "batch", "init_from_data", "WEIGHTS", "TRAIN", "FROZEN"]



@dataclasses.dataclass(frozen=True)
class Config:
    """LBF hyperparameters; defaults are the paper's (section cited per field)."""

    filter: str = "bilateral"  # "bilateral" (Eq. 2) or "nlm" (Appendix Eq. 16)
    features: tuple[str, ...] = PAPER_FEATURES  # the K additional features (Sec. 3.2)
    hidden: tuple[int, ...] = (10,)  # one hidden layer of 10 (Sec. 4.1, Fig. 11)
    radius: int = 27  # 55x55 filter window (Sec. 5)
    beta: float = 7.0  # fixed colour parameter of the cross-bilateral (Sec. 4.2)
    patch_radius: int = 2  # 5x5 NLM patch (Appendix, Eq. 16)
    prefilter: bool = True  # NLM prefilter of the features (Sec. 3.2)
    prefilter_radius: int = 5  # 11x11 window (Sec. 3.2)
    prefilter_patch: int = 3  # 7x7 patch (Sec. 3.2)
    spike_removal: bool = True  # Sec. 4.3
    temporal_radius: int = 3  # 3 frames each side, 7 in all (Sec. 5)
    lam_temporal: float = 0.0  # extra temporal falloff; the paper names none (docs/methods/lbf.md)
    drop_categories: tuple[str, ...] = ()  # Sec. 6 ablation: Sec. 3.3 categories fed as constants
    init_scale: float = 0.5  # initial weights uniform in [-0.5, 0.5] (Sec. 3.1)
    eps: float = 0.01  # Eq. 8
    # Training data (Sec. 4.2): sampling rates of the mini-batch and the crop size (our choice).
    train_spps: tuple[int, ...] = (4, 8, 16, 32, 64)
    train_crop: int = 48
    train_scenes_per_step: int = 2


# Defaults of the generic loop (jaxdenoise.train): RPROP as in Sec. 4.2. ``learning_rate`` is
# RPROP's initial step size Delta_0. Adam: pass optimizer="adam" (and e.g. learning_rate=1e-2).
TRAIN: dict[str, Any] = {"optimizer": "rprop", "learning_rate": 0.02, "steps": 400, "checkpoint_every": 10}
# Normalization statistics travel with the weights but are not trained (jaxdenoise.train).
FROZEN: tuple[str, ...] = ("norm",)


def WEIGHTS(config: Config) -> str:
    """Name of the shipped weights folder under jaxdenoise/weights/."""
    return "lbf-nlm" if config.filter == "nlm" else "lbf"


def _check_config(config: Config) -> None:
    if config.filter not in ("bilateral", "nlm"):
        raise JaxdenoiseError(f"lbf: config.filter is {config.filter!r}; expected 'bilateral' or 'nlm'")
    if not config.features:
        raise JaxdenoiseError("lbf: config.features must name at least one additional feature")
    bad = [c for c in config.drop_categories if c not in CATEGORIES]
    if bad:
        raise JaxdenoiseError(f"lbf: config.drop_categories has unknown {bad}; expected some of {CATEGORIES}")


def needs(config: Config) -> frozenset[str]:
    """Colour, its variance, each configured feature with its variance, and the frame's ``spp``
    (the inverse sample count is a secondary feature and scales the per-sample standard
    deviations, Sec. 3.3): a frame without it is refused, never given a default."""
    return with_variances({"color", *config.features}) | {"spp"}


def window(config: Config) -> tuple[int, int]:
    """Frames before and after t that frame t's filter reads on a sequence (Sec. 5: 3 each side);
    ``lbf-nlm`` and ``temporal_radius = 0`` run frame by frame (``(0, 0)``)."""
    if config.filter == "nlm" or config.temporal_radius == 0:
        return (0, 0)
    return (config.temporal_radius, config.temporal_radius)


# -- network -----------------------------------------------------------------------------------

def _network(config: Config):
    layers = []
    scale = nn.uniform_init(config.init_scale)
    for h in config.hidden:
        layers += [nn.Dense(h, w_init=scale, b_init=scale), nn.Sigmoid()]
    layers += [nn.Dense(len(config.features) + 1, w_init=scale, b_init=scale), nn.Softplus()]
    return nn.serial(*layers)


def init(key, config: Config) -> dict:
    """MLP weights uniform in [-0.5, 0.5] (Sec. 3.1) and identity normalization (mean 0, std 1)."""
    _check_config(config)
    n_in = num_features(config.features)
    net_init, _ = _network(config)
    _, net = net_init(key, (-1, n_in))
    return {"net": net, "norm": {"mean": jnp.zeros((n_in,), jnp.float32), "std": jnp.ones((n_in,), jnp.float32)}}


def _mask(config: Config) -> np.ndarray:
    """1 for the secondary features the network sees, 0 for the categories the ablation drops."""
    cats = feature_categories(config.features)
    return np.array([0.0 if c in config.drop_categories else 1.0 for c in cats], np.float32)


def filter_params(params: dict, x: jax.Array, config: Config) -> jax.Array:
    """Secondary features ``x`` (..., N) -> filter lambdas (..., K+1): index 0 is the spatial (or
    NLM patch) lambda, 1..K the feature lambdas (Appendix: ``lambda = 1/(2 theta^2)``)."""
    norm = jax.lax.stop_gradient(params["norm"])  # training-set statistics, not trained (Sec. 4.2)
    # A feature with zero spread in the training set carries no information; a unit scale keeps
    # the division finite.
    std = jnp.where(norm["std"] > 1e-8, norm["std"], 1.0)
    xn = (x - norm["mean"]) / std * _mask(config)
    _, net_apply = _network(config)
    return net_apply(params["net"], xn)


# -- features ----------------------------------------------------------------------------------

def prepare(buffers: Buffers, config: Config) -> dict:
    """Everything that does not depend on the params, for one (H, W) frame: the prefiltered
    features and smoothed variances (Sec. 3.2), the secondary features (Sec. 3.3), the colour."""
    _check_config(config)
    guides, gvars = prefilter_guides({n: getattr(buffers, n) for n in config.features},
                                     {n: getattr(buffers, f"{n}_var") for n in config.features},
                                     prefilter=config.prefilter, radius=config.prefilter_radius,
                                     patch_radius=config.prefilter_patch)
    guides = {n: jnp.asarray(guides[n], jnp.float32) for n in config.features}
    gvars = {n: jnp.asarray(gvars[n], jnp.float32) for n in config.features}
    if buffers.spp is None:
        raise BuffersError("lbf: the frame has no 'spp'; the secondary features need its sample count "
                           "(Sec. 3.3) and it is never guessed")
    # an adaptively sampled frame's per-pixel counts (the header's spp is their mean; issue 40)
    spp = buffers.spp if buffers.spp_map is None else buffers.spp_map[..., 0]
    x = secondary_features(guides, gvars, spp, features=config.features)
    return {"x": x, "color": jnp.asarray(buffers.color, jnp.float32),
            "color_var": jnp.asarray(buffers.color_var, jnp.float32), "guides": guides, "guide_vars": gvars}


def filter_with(lam: jax.Array, prep: dict, config: Config, *, engine: str = "tiles") -> jax.Array:
    """Run the configured filter of one frame with per-pixel lambdas ``lam`` (H, W, K+1).
    ``engine`` picks the cross-bilateral's window engine (`jaxdenoise.filters.bilateral.ENGINES`:
    the tiled default, or the per-offset one it replaced, for measurements); the NLM has one."""
    feats = [prep["guides"][f] for f in config.features]
    fvars = [prep["guide_vars"][f] for f in config.features]
    lam_f = [lam[..., 1 + k] for k in range(len(config.features))]
    if config.filter == "nlm":
        return cross_nlm(prep["color"], prep["color_var"], feats, fvars, lam[..., 0], lam_f,
                         radius=config.radius, patch_radius=config.patch_radius)
    lam_c = 1.0 / (2.0 * config.beta ** 2)  # fixed beta = 7 (Sec. 4.2) in the auxiliary form
    return cross_bilateral(prep["color"], prep["color_var"], feats, fvars, lam[..., 0], lam_c, lam_f,
                           radius=config.radius, engine=engine)


def postprocess(img: jax.Array, config: Config) -> jax.Array:
    """Spike removal of the filtered image (Sec. 4.3: 3x3 block, 2 standard deviations, replaced by
    the block median) when ``config.spike_removal``; not used in training, as in the paper."""
    return remove_spikes(img, n_std=2.0, block_radius=1) if config.spike_removal else img


def _check_buffers(buffers: Buffers, config: Config) -> None:
    if not isinstance(buffers, Buffers):
        raise BuffersError(f"lbf: 'buffers' must be a jaxdenoise.Buffers, got {type(buffers).__name__}")
    buffers.check_needs(needs(config), "lbf-nlm" if config.filter == "nlm" else "lbf")


def _apply_frame(params: dict, buffers: Buffers, config: Config) -> jax.Array:
    prep = prepare(buffers, config)
    return postprocess(filter_with(filter_params(params, prep["x"], config), prep, config), config)


def apply(params: dict, buffers: Buffers, config: Config) -> jax.Array:
    """Denoise one frame ``(H, W, 3)``, or a batch ``(B, H, W, 3)`` of independent frames (one at a
    time). Sequences go through `jaxdenoise.sequence` (`window`, `prepare_frame`, `apply_window`)."""
    _check_config(config)
    _check_buffers(buffers, config)
    if np.ndim(buffers.color) < 3:
        raise BuffersError(f"lbf: 'buffers.color' has shape {np.shape(buffers.color)}; expected (..., H, W, 3)")
    return map_frames(lambda b: _apply_frame(params, b, config), buffers)


def prepare_frame(params: dict, buffers: Buffers, config: Config) -> dict:
    """Per-frame work of the spatio-temporal filter (Sec. 5): `prepare` and the frame's own lambdas
    (each frame's parameters come from its own features; the network is not retrained)."""
    _check_config(config)
    _check_buffers(buffers, config)
    prep = prepare(buffers, config)
    return {"guides": prep["guides"], "guide_vars": prep["guide_vars"], "color": prep["color"],
            "color_var": prep["color_var"], "lam": filter_params(params, prep["x"], config)}


def apply_window(params: dict, prepared: tuple, center: int, config: Config) -> jax.Array:
    """Sec. 5: frame ``prepared[center]`` filtered over the frames of its window (t-3..t+3, clipped
    at the ends of the sequence) with its own lambdas, then spike removal."""
    if window(config) == (0, 0):
        prep = prepared[center]
        return postprocess(filter_with(prep["lam"], prep, config), config)
    stack = lambda get: jnp.stack([get(p) for p in prepared])
    feats = [stack(lambda p, f=f: p["guides"][f]) for f in config.features]
    fvars = [stack(lambda p, f=f: p["guide_vars"][f]) for f in config.features]
    lam = prepared[center]["lam"]
    out = spatiotemporal_cross_bilateral(
        stack(lambda p: p["color"]), stack(lambda p: p["color_var"]), feats, fvars, lam[..., 0],
        1.0 / (2.0 * config.beta ** 2), [lam[..., 1 + k] for k in range(len(config.features))],
        radius=config.radius, lam_temporal=config.lam_temporal, center=center)
    return postprocess(out, config)


# -- training ----------------------------------------------------------------------------------

def relmse_loss(out: jax.Array, ref: jax.Array, spp: jax.Array, eps: float) -> jax.Array:
    """Eq. 8 averaged over pixels: ``n/2 sum_q (c_hat - c)^2 / (c^2 + eps)``; ``spp`` per image."""
    n = jnp.reshape(spp, spp.shape + (1,) * (out.ndim - spp.ndim))
    e = 0.5 * n * jnp.square(out - ref) / (jnp.square(ref) + eps)
    return jnp.mean(jnp.sum(e, axis=-1))


def loss(params: dict, batch: dict, config: Config) -> jax.Array:
    """Eq. 8 through the filter for a batch of crops (keys as produced by `batch`)."""

    def one(x, color, color_var, guides, guide_vars):
        prep = {"x": x, "color": color, "color_var": color_var, "guides": guides, "guide_vars": guide_vars}
        return filter_with(filter_params(params, x, config), prep, config)

    out = jax.vmap(one)(batch["x"], batch["color"], batch["color_var"], batch["guides"], batch["guide_vars"])
    return relmse_loss(out, batch["reference"], batch["spp"], config.eps)


@functools.lru_cache(maxsize=8)
def _prepare_jit(config: Config):
    return jax.jit(lambda b: prepare(b, config))


def _scan(data_dir: Path, spps: Sequence[int]) -> list[tuple[Path, dict[int, list[Path]]]]:
    """Shots under ``data_dir`` (`jaxdenoise.data.discover`) with at least one render at every rate
    in ``spps`` (header ``spp``; renders in name order): ``[(shot folder, {spp: [paths]})]``."""
    from ..data import discover, renders_by_spp

    scenes = []
    for shot in discover(data_dir):
        by_spp = renders_by_spp(shot, set(spps))
        if all(by_spp.get(s) for s in spps):
            scenes.append((shot.folder, {s: [r.path for r in by_spp[s]] for s in spps}))
    if not scenes:
        raise FileNotFoundError(f"{data_dir}: no shot (folder with reference.exr) has renders at every spp "
                                f"in {tuple(spps)} (header attribute 'spp')")
    return scenes


def make_dataset(data_dir, config: Config, *, max_instances: int | None = None, progress: bool = True) -> dict:
    """Read every training scene and precompute `prepare` for every noisy render (float32 numpy).

    Returns ``{"scenes": [{"name", "reference", "renders": {spp: [prep, ...]}}], "x_all": sample
    of secondary features for the normalization statistics}``.
    """
    from ..io import read_buffers, read_image

    _check_config(config)
    data_dir = Path(data_dir)
    scenes = _scan(data_dir, config.train_spps)
    prep_jit = _prepare_jit(config)
    keep = needs(config)
    items = [(sd, s, p) for sd, r in scenes for s in config.train_spps for p in r[s][:max_instances]]
    it = items
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(items, desc="lbf features", unit="frame")
    out: dict[str, dict] = {}
    for scene_dir, spp, path in it:
        entry = out.setdefault(str(scene_dir), {"name": scene_dir.name, "renders": {}})
        if "reference" not in entry:
            entry["reference"] = np.asarray(read_image(scene_dir / "reference.exr"), np.float32)[..., :3]
        buf, attrs = read_buffers(path)
        buf.check_needs(keep, "lbf", where=str(path))
        buf = buf.only(keep)
        prep = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), prep_jit(buf))
        prep["spp"] = np.float32(spp)
        entry["renders"].setdefault(spp, []).append(prep)
    return {"scenes": list(out.values())}


def init_from_data(key, config: Config, dataset: dict) -> dict:
    """`init` with the secondary features' mean and std over the training set (Sec. 4.2)."""
    params = init(key, config)
    xs = [p["x"].reshape(-1, p["x"].shape[-1]) for sc in dataset["scenes"] for rs in sc["renders"].values()
          for p in rs]
    allx = np.concatenate(xs, axis=0).astype(np.float64)
    params["norm"] = {"mean": jnp.asarray(allx.mean(0), jnp.float32), "std": jnp.asarray(allx.std(0), jnp.float32)}
    return params


def batch(dataset: dict, step: int, config: Config, rng: np.random.Generator) -> dict:
    """One mini-batch (Sec. 4.2): for ``train_scenes_per_step`` scenes (all when fewer), one crop of
    each sampling rate in ``train_spps``, using noise instance ``step mod n`` (alternating
    instances). Crops are ``train_crop`` pixels square at a random position per scene and spp."""
    scenes = dataset["scenes"]
    n = min(config.train_scenes_per_step, len(scenes))
    chosen = rng.choice(len(scenes), size=n, replace=False)
    cols: dict[str, list] = {"x": [], "color": [], "color_var": [], "reference": [], "spp": []}
    guides = {f: [] for f in config.features}
    gvars = {f: [] for f in config.features}
    for si in chosen:
        sc = scenes[int(si)]
        ref = sc["reference"]
        h, w = ref.shape[:2]
        c = min(config.train_crop, h, w)
        for spp in config.train_spps:
            renders = sc["renders"][spp]
            prep = renders[step % len(renders)]
            y0, x0 = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
            sl = (slice(y0, y0 + c), slice(x0, x0 + c))
            cols["x"].append(prep["x"][sl])
            cols["color"].append(prep["color"][sl])
            cols["color_var"].append(prep["color_var"][sl])
            cols["reference"].append(ref[sl])
            cols["spp"].append(np.float32(spp))
            for f in config.features:
                guides[f].append(prep["guides"][f][sl])
                gvars[f].append(prep["guide_vars"][f][sl])
    out = {k: np.stack(v) for k, v in cols.items()}
    out["guides"] = {f: np.stack(v) for f, v in guides.items()}
    out["guide_vars"] = {f: np.stack(v) for f, v in gvars.items()}
    return out
