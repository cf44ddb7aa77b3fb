"""Convolution layers and their initializers (stax style, NHWC activations, HWIO kernels).

- `Conv`: 2-D cross-correlation with stride, dilation, ``"SAME"`` / ``"VALID"`` (or explicit)
  padding and an optional bias: ``y[o] = sum_{i, j, c} x[s*o + d*(i, j) - pad, c] w[i, j, c, :] + b``.
- `ConvTranspose`: the transposed convolution (the adjoint of a strided `Conv`), with PyTorch's
  ``padding`` convention: ``out = (in - 1) * stride - 2 * padding + kernel``; the default padding
  ``(kernel - stride) // 2`` makes it an exact ``stride``-fold up-sampler in size (GradNet's 4x4
  stride-2 deconvolution, Guo 2019 Sec. 4.4: ``H -> 2H``). In scatter form:
  ``y[stride * p + i - padding, :] += x[p, c] w[i, j, c, :]``. Computed by output phase (one
  small correlation per phase, interleaved), not by dilating the input with zeros.
- Initializers for HWIO kernels: `he_normal_init` (Kaiming: N(0, 2 / fan_in), Chaitanya 2017 and
  Guo 2019), `glorot_uniform_init` (Xavier, in `jaxdenoise.nn`, receptive-field aware),
  `bilinear_init` (a ConvTranspose that is exact bilinear up-sampling with half-pixel centres:
  DEMC's decoder, Yang 2019 Sec. 3.2), `identity_init` (a 1x1 kernel made of identity / zero blocks:
  DEMC's skip fusion, Yang 2019 Eq. 3).
- `pad_to_multiple` / `crop_to`: any input size through a network of total stride ``m``: pad the
  spatial axes up to a multiple of ``m`` and crop the output back (the one helper for it).

Reverse mode computes a spatial convolution's kernel gradient through the layer's own derivative
rule on CPU (`WEIGHT_GRADIENT`, `_kernel_tangent`): row-block im2col matrix products on large
images (`conv_by_rows`, public so that experiments can time it as a forward convolution), XLA's
transposed convolution on small ones; the forward pass is XLA's convolution unchanged. On an
accelerator, XLA's own kernel gradient is kept (the rule was measured on CPU).

Inputs may carry any number of leading axes (``(H, W, C)``, ``(N, H, W, C)``, ``(T, N, H, W, C)``);
they are flattened into one batch axis around the XLA convolution and restored.
"""
from __future__ import annotations

import functools
import math
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

__all__ = ["Conv", "ConvTranspose", "he_normal_init", "bilinear_init", "identity_init", "pad_to_multiple",
           "crop_to", "conv_by_rows"]

_DN = ("NHWC", "HWIO", "NHWC")


def _pair(v: Any, name: str, layer: str, minimum: int = 1) -> tuple[int, int]:
    t = (v, v) if isinstance(v, (int, np.integer)) else tuple(v)
    if len(t) != 2 or not all(isinstance(a, (int, np.integer)) and a >= minimum for a in t):
        raise ValueError(f"{layer}: '{name}' must be an int >= {minimum} or a pair of them, got {v!r}")
    return int(t[0]), int(t[1])


def _fans(shape: Sequence[int]) -> tuple[int, int]:
    """(fan_in, fan_out) of a kernel whose last two axes are (in, out): receptive field x channels."""
    rf = int(np.prod(shape[:-2])) if len(shape) > 2 else 1
    return rf * int(shape[-2]), rf * int(shape[-1])


def he_normal_init(gain: float = 2.0):
    """Kaiming He et al. 2015: N(0, gain / fan_in), fan_in = kh * kw * c_in (``gain`` 2 for ReLU; for
    a leaky ReLU of slope a the exact gain is 2 / (1 + a^2))."""

    def init(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
        fan_in, _ = _fans(shape)
        return jax.random.normal(key, shape, jnp.float32) * math.sqrt(gain / fan_in)

    return init


def bilinear_init(stride: int = 2):
    """Kernel of a `ConvTranspose` (kernel k, ``stride``, default padding) that up-samples each
    channel bilinearly with half-pixel centres: ``w[i, j, c, o] = b[i] b[j] [c == o]`` with
    ``b[i] = 1 - |i - centre| / stride``, ``centre = (k - 1) / 2`` (the FCN kernel; for k = 4,
    stride 2: b = (1/4, 3/4, 3/4, 1/4)). With c_in != c_out the channel map is the rectangular
    identity (output channel o up-samples input channel o for o < min(c_in, c_out); other outputs
    start at zero): DEMC's decoder narrows the channels at each level (docs/methods/demc.md). Away
    from the border (one input pixel) the result is exactly the bilinear interpolation; at the border
    the missing neighbour counts as 0."""

    def init(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
        kh, kw, cin, cout = shape

        def taps(k):
            centre = (k - 1) / 2.0
            return np.maximum(0.0, 1.0 - np.abs(np.arange(k) - centre) / stride)

        w = np.einsum("i,j,co->ijco", taps(kh), taps(kw), np.eye(cin, cout))
        return jnp.asarray(w, jnp.float32)

    return init


def identity_init(blocks: Sequence[float]):
    """A 1x1 kernel ``(1, 1, len(blocks) * C, C)`` whose input-channel blocks are ``blocks[k] * I``:
    ``identity_init((1, 0, 0))`` passes the first of three concatenated C-channel tensors through
    unchanged (DEMC's skip fusion, Yang 2019 Eq. 3)."""
    blocks = tuple(float(b) for b in blocks)

    def init(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
        kh, kw, cin, cout = shape
        if (kh, kw) != (1, 1) or cin != len(blocks) * cout:
            raise ValueError(f"identity_init{blocks}: needs a 1x1 kernel with {len(blocks)} x c_out input "
                             f"channels, got HWIO {shape}")
        w = np.concatenate([b * np.eye(cout) for b in blocks], axis=0)
        return jnp.asarray(w.reshape(1, 1, cin, cout), jnp.float32)

    return init


def _flatten(x: jax.Array, layer: str) -> tuple[jax.Array, tuple[int, ...]]:
    if x.ndim < 3:
        raise ValueError(f"{layer}: input has shape {tuple(x.shape)}; expected (..., H, W, C)")
    lead = tuple(x.shape[:-3])
    return x.reshape((-1,) + tuple(x.shape[-3:])), lead


def _padding(padding: Any, layer: str):
    if isinstance(padding, str):
        p = padding.upper()
        if p not in ("SAME", "VALID"):
            raise ValueError(f"{layer}: padding must be 'SAME', 'VALID' or ((top, bottom), (left, right)), got {padding!r}")
        return p
    try:
        (a, b), (c, d) = padding
        return ((int(a), int(b)), (int(c), int(d)))
    except (TypeError, ValueError):
        raise ValueError(f"{layer}: padding must be 'SAME', 'VALID' or ((top, bottom), (left, right)), "
                         f"got {padding!r}") from None


def _check_in(layer: str, in_shape: Sequence[int]) -> tuple[int, ...]:
    in_shape = tuple(int(s) for s in in_shape)
    if len(in_shape) < 3 or in_shape[-1] <= 0:
        raise ValueError(f"{layer}: in_shape must be (..., H, W, C) with C > 0, got {in_shape}")
    return in_shape


def _conv_size(n: int, k: int, s: int, d: int, pad: Any, axis: int) -> int:
    if n < 0:
        return -1
    ke = d * (k - 1) + 1
    if pad == "SAME":
        return -(-n // s)
    if pad == "VALID":
        return max(0, (n - ke) // s + 1)
    lo, hi = pad[axis]
    return max(0, (n + lo + hi - ke) // s + 1)


def _kernel_params(key: jax.Array, shape: tuple[int, ...], w_init, b_init, bias: bool) -> dict:
    """``{"w": HWIO kernel, "b": bias}`` (no ``"b"`` without bias; zero bias unless ``b_init``)."""
    k1, k2 = jax.random.split(key)
    params = {"w": w_init(k1, shape)}
    if bias:
        params["b"] = b_init(k2, (shape[-1],)) if b_init else jnp.zeros((shape[-1],), jnp.float32)
    return params


def Conv(out_channels: int, kernel: int | tuple[int, int] = 3, *, stride: int | tuple[int, int] = 1,
         dilation: int | tuple[int, int] = 1, padding: Any = "SAME", bias: bool = True, w_init=None,
         b_init=None):
    """2-D convolution layer (module docstring). Params ``{"w": (kh, kw, c_in, out), "b": (out,)}``
    (no ``"b"`` when ``bias=False``). Default init: He normal weights, zero bias."""
    if int(out_channels) <= 0:
        raise ValueError(f"Conv: out_channels must be a positive integer, got {out_channels}")
    out_channels = int(out_channels)
    kh, kw = _pair(kernel, "kernel", "Conv")
    sh, sw = _pair(stride, "stride", "Conv")
    dh, dw = _pair(dilation, "dilation", "Conv")
    pad = _padding(padding, "Conv")
    w_init = w_init or he_normal_init()

    def init(key: jax.Array, in_shape: Sequence[int]):
        in_shape = _check_in("Conv", in_shape)
        params = _kernel_params(key, (kh, kw, in_shape[-1], out_channels), w_init, b_init, bias)
        h = _conv_size(in_shape[-3], kh, sh, dh, pad, 0)
        w = _conv_size(in_shape[-2], kw, sw, dw, pad, 1)
        return in_shape[:-3] + (h, w, out_channels), params

    def apply(params: dict, x: jax.Array) -> jax.Array:
        w = params["w"]
        if x.shape[-1] != w.shape[2]:
            raise ValueError(f"Conv: input has {x.shape[-1]} channels, the layer expects {w.shape[2]}")
        xf, lead = _flatten(x, "Conv")
        y = _correlate(xf, w.astype(x.dtype), (sh, sw), pad, (dh, dw))
        if "b" in params:
            y = y + params["b"].astype(y.dtype)
        return y.reshape(lead + tuple(y.shape[1:]))

    return init, apply


def ConvTranspose(out_channels: int, kernel: int | tuple[int, int] = 4, *, stride: int | tuple[int, int] = 2,
                  padding: int | tuple[int, int] | None = None, bias: bool = True, w_init=None, b_init=None):
    """Transposed convolution (module docstring); ``padding`` per side, default ``(k - s) // 2``.
    Params as `Conv`'s (HWIO, ``I`` = input channels). Default init: He normal, zero bias;
    ``w_init=bilinear_init(stride)`` makes it bilinear up-sampling."""
    if int(out_channels) <= 0:
        raise ValueError(f"ConvTranspose: out_channels must be a positive integer, got {out_channels}")
    out_channels = int(out_channels)
    kh, kw = _pair(kernel, "kernel", "ConvTranspose")
    sh, sw = _pair(stride, "stride", "ConvTranspose")
    if padding is None:
        ph, pw = max(0, (kh - sh) // 2), max(0, (kw - sw) // 2)
    else:
        ph, pw = _pair(padding, "padding", "ConvTranspose", minimum=0)
    if ph > kh - 1 or pw > kw - 1:
        raise ValueError(f"ConvTranspose: padding {(ph, pw)} must be at most kernel - 1 = {(kh - 1, kw - 1)}")
    w_init = w_init or he_normal_init()

    def init(key: jax.Array, in_shape: Sequence[int]):
        in_shape = _check_in("ConvTranspose", in_shape)
        params = _kernel_params(key, (kh, kw, in_shape[-1], out_channels), w_init, b_init, bias)
        size = lambda n, k, s, p: -1 if n < 0 else (n - 1) * s - 2 * p + k
        return in_shape[:-3] + (size(in_shape[-3], kh, sh, ph), size(in_shape[-2], kw, sw, pw), out_channels), params

    def apply(params: dict, x: jax.Array) -> jax.Array:
        w = params["w"]
        if x.shape[-1] != w.shape[2]:
            raise ValueError(f"ConvTranspose: input has {x.shape[-1]} channels, the layer expects {w.shape[2]}")
        xf, lead = _flatten(x, "ConvTranspose")
        y = _transpose_by_phases(xf, w.astype(x.dtype), (sh, sw), (ph, pw))
        if "b" in params:
            y = y + params["b"].astype(y.dtype)
        return y.reshape(lead + tuple(y.shape[1:]))

    return init, apply


# Input channels are zero-padded to a multiple of this before a spatial convolution: exact, and
# measured 1.4-3.5x faster on this CPU (jax 0.10, 1280x736: 3x3 conv 3->24 in 248 ms, 8->24 in
# 71 ms; 12->24 in 93 ms, 16->24 in 66 ms; docs/results/demc.md).
CHANNEL_MULTIPLE = 8


def _correlate(x: jax.Array, w: jax.Array, stride: tuple[int, int], pad: Any, dilation: tuple[int, int]) -> jax.Array:
    """``lax.conv_general_dilated`` in NHWC/HWIO with two exact rewrites that XLA's CPU back end
    does not make itself: a 1x1, stride-1 convolution is a matrix product over channels (4x faster
    at 1280x736, 72 -> 24 channels: 54 vs 203 ms), and input channels are padded with zeros to a
    multiple of `CHANNEL_MULTIPLE`."""
    kh, kw, cin, _ = w.shape
    if (kh, kw) == (1, 1) and stride == (1, 1) and (isinstance(pad, str) or pad == ((0, 0), (0, 0))):
        return jnp.dot(x, w[0, 0])
    extra = (-cin) % CHANNEL_MULTIPLE
    if extra:
        x = jnp.pad(x, ((0, 0), (0, 0), (0, 0), (0, extra)))
        w = jnp.pad(w, ((0, 0), (0, 0), (0, extra), (0, 0)))
    if WEIGHT_GRADIENT not in ("fast", "xla"):
        raise ValueError(f"nn.conv.WEIGHT_GRADIENT must be 'fast' or 'xla', got {WEIGHT_GRADIENT!r}")
    # The fast rule was measured on XLA:CPU only; on an accelerator XLA's own kernel gradient (cuDNN's)
    # is kept.
    if WEIGHT_GRADIENT == "xla" or jax.default_backend() != "cpu":
        return _xla_conv(x, w, stride, pad, dilation)
    return _conv(x, w, stride, pad, dilation)


# How reverse mode computes a spatial convolution's kernel gradient: ``"fast"`` (the default) by
# `_kernel_tangent`'s measured choice, ``"xla"`` as XLA's own transposed convolution everywhere (the
# path before; no custom derivative). Read at trace time; experiments/bench_xla_flags.py and
# bench_conv.py switch it to measure both in one run. On this CPU (jax 0.10.2, 2 cores) XLA's
# kernel gradient takes 3-25x the forward pass on large images (1280x736, 48 -> 48 channels:
# 1228 ms against a 59 ms forward; row blocks: 109 ms) but is as fast or faster than row blocks on
# training crops of 64x64 and below (docs/results/conv.md).
WEIGHT_GRADIENT = "fast"
# Output pixels per row block of `conv_by_rows`: the block's im2col matrix stays in cache. 2048
# was the fastest of 2048-65536 on every large-image shape measured.
BLOCK_PIXELS = 2048
# Output images (H_out x W_out) above this many pixels take row blocks; at or below, XLA's kernel
# gradient (measured: a 96x96 first layer, 8 -> 24 channels, 32 crops: 2.4x faster by row blocks;
# 64x64, 32 -> 32, 28 crops: 1.6x slower; 48x48 and below: within 20 %).
ROW_BLOCK_MIN_PIXELS = 4 * BLOCK_PIXELS


def _xla_conv(x, w, stride, pad, dilation):
    return jax.lax.conv_general_dilated(x, w, stride, pad, rhs_dilation=dilation, dimension_numbers=_DN)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3, 4))
def _conv(x, w, stride, pad, dilation):
    """XLA's convolution, differentiated as ``dy = conv(dx, w) + conv(x, dw)`` with the kernel term
    in `_kernel_tangent`'s form, so that its transpose (reverse mode's kernel gradient) is the
    fastest measured for the layer's size rather than always XLA's transposed convolution. Forward
    and reverse mode both work; the primal is XLA's convolution, bit for bit."""
    return _xla_conv(x, w, stride, pad, dilation)


@functools.partial(_conv.defjvp, symbolic_zeros=True)
def _conv_jvp(stride, pad, dilation, primals, tangents):
    x, w = primals
    tx, tw = tangents
    y = _xla_conv(x, w, stride, pad, dilation)
    parts = []
    if not isinstance(tx, SymbolicZero):
        parts.append(_xla_conv(tx, w, stride, pad, dilation))
    if not isinstance(tw, SymbolicZero):
        parts.append(_kernel_tangent(x, tw, stride, pad, dilation).astype(y.dtype))
    return y, (sum(parts[1:], parts[0]) if parts else jnp.zeros_like(y))


def _kernel_tangent(x: jax.Array, tw: jax.Array, stride: tuple[int, int], pad: Any,
                    dilation: tuple[int, int]) -> jax.Array:
    """``conv(x, tw)``, the kernel term of the convolution's tangent, in the form whose transpose
    (reverse mode's kernel gradient) was fastest on this CPU for its size (docs/results/conv.md):
    row blocks (`conv_by_rows`) for output images above `ROW_BLOCK_MIN_PIXELS` pixels; below, XLA's
    transposed convolution, with the output channels zero-padded to a multiple of
    `CHANNEL_MULTIPLE` (exact; 1.3-1.5x faster on RAE's 43 / 57 / 76 channels)."""
    kh, kw, _, cout = tw.shape
    ho = _conv_size(x.shape[1], kh, stride[0], dilation[0], pad, 0)
    wo = _conv_size(x.shape[2], kw, stride[1], dilation[1], pad, 1)
    if ho * wo > ROW_BLOCK_MIN_PIXELS:
        return conv_by_rows(x, tw, stride, pad, dilation)
    extra = (-cout) % CHANNEL_MULTIPLE
    if extra:
        return _xla_conv(x, jnp.pad(tw, ((0, 0), (0, 0), (0, 0), (0, extra))), stride, pad, dilation)[..., :cout]
    return _xla_conv(x, tw, stride, pad, dilation)


def conv_by_rows(x: jax.Array, w: jax.Array, stride: tuple[int, int], pad: Any,
                 dilation: tuple[int, int], preferred_element_type: Any = None) -> jax.Array:
    """The same correlation as XLA's convolution (NHWC input, HWIO kernel, ``pad`` a padding string or
    explicit pairs), as a scan over blocks of output rows across the batch: each block's im2col matrix
    (``n * rows * W_out`` pixels, about `BLOCK_PIXELS`, x ``kh * kw * c_in``) times the kernel as a
    ``(kh kw c_in, c_out)`` matrix (``preferred_element_type``: the product's accumulation type, as
    `jnp.dot` takes it). Linear in ``w``; its transpose, which reverse mode derives, is the sum over
    blocks of ``cols^T @ g``. The body is rematerialised (`jax.checkpoint`), so reverse mode keeps ``x``
    and not the 9x larger im2col matrix. The kernel gradient's fast rule uses it;
    experiments/bench_im2col.py measures it as a forward convolution."""
    kh, kw, cin, cout = w.shape
    n, h, wd, _ = x.shape
    (sh, sw), (dh, dw) = stride, dilation
    (plo, phi), (qlo, qhi) = (jax.lax.padtype_to_pads((h, wd), (dh * (kh - 1) + 1, dw * (kw - 1) + 1), stride, pad)
                              if isinstance(pad, str) else pad)
    ho, wo = _conv_size(h, kh, sh, dh, pad, 0), _conv_size(wd, kw, sw, dw, pad, 1)
    if ho == 0 or wo == 0 or n == 0:
        return jnp.zeros((n, ho, wo, cout), preferred_element_type or jnp.result_type(x, w))
    rows = max(1, min(ho, BLOCK_PIXELS // (n * wo)))
    blocks = -(-ho // rows)
    span = sh * (rows - 1) + dh * (kh - 1) + 1  # padded input rows one block reads
    need = sh * (blocks * rows - 1) + dh * (kh - 1) + 1  # ... and all blocks (the last one padded)
    xp = jax.lax.pad(x, jnp.zeros((), x.dtype), ((0, 0, 0), (plo, need - h - plo, 0), (qlo, qhi, 0), (0, 0, 0)))
    wm = w.reshape(kh * kw * cin, cout)

    @jax.checkpoint
    def body(carry, b):
        xs = jax.lax.dynamic_slice_in_dim(xp, b * rows * sh, span, axis=1)
        cols = jnp.concatenate([jax.lax.slice(xs, (0, dh * i, dw * j, 0),
                                              (n, dh * i + sh * (rows - 1) + 1, dw * j + sw * (wo - 1) + 1, cin),
                                              (1, sh, sw, 1))
                                for i in range(kh) for j in range(kw)], axis=-1)
        return carry, jnp.dot(cols, wm, preferred_element_type=preferred_element_type)

    _, ys = jax.lax.scan(body, None, jnp.arange(blocks))  # (blocks, n, rows, W_out, c_out)
    return ys.transpose(1, 0, 2, 3, 4).reshape(n, blocks * rows, wo, cout)[:, :ho]


def _phase_taps(n_in: int, k: int, s: int, p: int, r: int) -> tuple[int, list[tuple[int, int]], int, int]:
    """Output phase ``r`` (outputs ``o = s m + r``) of a 1-D transposed convolution as a correlation:
    ``y_r[m] = sum_t x[m + d_t] w[t]`` over the taps ``t = r + p (mod s)``, ``d_t = (r + p - t) / s``.
    Returns ``(M_r, [(d_t, t)], pad_lo, pad_hi)`` (negative pads are crops)."""
    n_out = (n_in - 1) * s - 2 * p + k
    m_r = max(0, -(-(n_out - r) // s))
    taps = [((r + p - t) // s, t) for t in range(k) if (t - r - p) % s == 0]
    if not taps:
        return m_r, [], 0, 0
    d_min, d_max = min(d for d, _ in taps), max(d for d, _ in taps)
    lo = -d_min
    hi = m_r - n_in + (d_max - d_min) - lo
    return m_r, taps, lo, hi


def _transpose_by_phases(x: jax.Array, w: jax.Array, stride: tuple[int, int], pad: tuple[int, int]) -> jax.Array:
    """The transposed convolution (scatter form in the module docstring) as ``s_h * s_w`` small
    stride-1 correlations, one per output phase, interleaved (the sub-pixel form). Exact, and
    ``s_h s_w`` times fewer multiply-adds than correlating an input dilated by the stride with zeros,
    which is what XLA's ``lhs_dilation`` costs on a CPU (a 4x4 stride-2 layer: 4 taps per output
    pixel instead of 16)."""
    (sh, sw), (ph, pw) = stride, pad
    n, h, wd, _ = x.shape
    kh, kw, _, cout = w.shape
    rows = []
    for ry in range(sh):
        my, ty, loy, hiy = _phase_taps(h, kh, sh, ph, ry)
        cols = []
        for rx in range(sw):
            mx, tx, lox, hix = _phase_taps(wd, kw, sw, pw, rx)
            if not ty or not tx:
                cols.append(jnp.zeros((n, my, mx, cout), x.dtype))
                continue
            dy0, dx0 = min(d for d, _ in ty), min(d for d, _ in tx)
            sub = jnp.zeros((max(d for d, _ in ty) - dy0 + 1, max(d for d, _ in tx) - dx0 + 1) + w.shape[2:], w.dtype)
            for dy, t_y in ty:
                for dx, t_x in tx:
                    sub = sub.at[dy - dy0, dx - dx0].set(w[t_y, t_x])
            xp = jax.lax.pad(x, jnp.zeros((), x.dtype), ((0, 0, 0), (loy, hiy, 0), (lox, hix, 0), (0, 0, 0)))
            cols.append(_correlate(xp, sub, (1, 1), "VALID", (1, 1)))
        rows.append(cols)
    n_out_h = (h - 1) * sh - 2 * ph + kh
    n_out_w = (wd - 1) * sw - 2 * pw + kw
    my_max = max(r[0].shape[1] for r in rows)
    mx_max = max(c.shape[2] for c in rows[0])
    grid = [[jnp.pad(c, ((0, 0), (0, my_max - c.shape[1]), (0, mx_max - c.shape[2]), (0, 0))) for c in r] for r in rows]
    # (n, my, sh, mx, sw, c) -> (n, my * sh, mx * sw, c): output row s*m + r takes phase r's row m
    y = jnp.stack([jnp.stack(r, axis=3) for r in grid], axis=2)
    y = y.reshape(n, my_max * sh, mx_max * sw, cout)
    return y[:, :n_out_h, :n_out_w]


def pad_to_multiple(x: jax.Array, multiple: int, *, mode: str = "edge") -> tuple[jax.Array, tuple[int, int]]:
    """Pad the spatial axes (-3, -2) of ``x`` at the bottom and right up to the next multiple of
    ``multiple`` (a network's total stride, e.g. 32 for five 2x2 poolings); returns the padded array
    and the original ``(H, W)`` for `crop_to`. ``mode`` is `jnp.pad`'s (``"edge"`` repeats the last
    row and column, so no artificial black border reaches the convolutions)."""
    if int(multiple) < 1:
        raise ValueError(f"pad_to_multiple: multiple must be >= 1, got {multiple}")
    h, w = int(x.shape[-3]), int(x.shape[-2])
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph or pw:
        widths = [(0, 0)] * (x.ndim - 3) + [(0, ph), (0, pw), (0, 0)]
        x = jnp.pad(x, widths, mode=mode)
    return x, (h, w)


def crop_to(y: jax.Array, size: tuple[int, int]) -> jax.Array:
    """Undo `pad_to_multiple`: keep the top-left ``size = (H, W)`` of the spatial axes."""
    return y[..., : size[0], : size[1], :]
