"""jaxdenoise.nn conv / pool layers: predicted shapes, brute-force NumPy references, adjointness,
the bilinear and identity initializers, gradients against finite differences, jit agreement, any
size through pad_to_multiple, and the max-pool gradient kept off reduce_window (structural)."""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import fit, registered
from jax.test_util import check_grads

from jaxdenoise import nn

RNG = np.random.default_rng(0)


def _x(*shape):
    return RNG.normal(size=shape).astype(np.float32)


# -- NumPy references ---------------------------------------------------------------------------
def _np_conv(x, w, b, stride, dilation, pad):
    """Brute-force correlation of one (H, W, C) image; pad = ((t, b), (l, r)) explicit zeros."""
    (pt, pb), (pl, pr) = pad
    xp = np.pad(x, ((pt, pb), (pl, pr), (0, 0)))
    kh, kw, _, co = w.shape
    (sh, sw), (dh, dw) = stride, dilation
    ho = (xp.shape[0] - (dh * (kh - 1) + 1)) // sh + 1
    wo = (xp.shape[1] - (dw * (kw - 1) + 1)) // sw + 1
    out = np.zeros((ho, wo, co))
    for y, xx, i, j in itertools.product(range(ho), range(wo), range(kh), range(kw)):
        out[y, xx] += xp[y * sh + i * dh, xx * sw + j * dw] @ w[i, j]
    return out + (0 if b is None else b)


def _same_pad(n, k, s, d):
    ke = d * (k - 1) + 1
    out = -(-n // s)
    total = max((out - 1) * s + ke - n, 0)
    return (total // 2, total - total // 2)


def _np_conv_transpose(x, w, b, stride, pad):
    """Scatter form: y[s p + i - pad] += x[p] w[i]."""
    h, wd, _ = x.shape
    kh, kw, _, co = w.shape
    (sh, sw), (ph, pw) = stride, pad
    ho, wo = (h - 1) * sh - 2 * ph + kh, (wd - 1) * sw - 2 * pw + kw
    out = np.zeros((ho, wo, co))
    for y, xx, i, j in itertools.product(range(h), range(wd), range(kh), range(kw)):
        oy, ox = y * sh + i - ph, xx * sw + j - pw
        if 0 <= oy < ho and 0 <= ox < wo:
            out[oy, ox] += x[y, xx] @ w[i, j]
    return out + (0 if b is None else b)


def _np_bilinear_up(x, k):
    """Half-pixel-centre bilinear up-sampling with clamped (edge) sampling."""
    h, w, _ = x.shape
    def coords(n):
        c = (np.arange(n * k) + 0.5) / k - 0.5
        c = np.clip(c, 0, n - 1)
        lo = np.floor(c).astype(int)
        hi = np.minimum(lo + 1, n - 1)
        return lo, hi, c - lo
    y0, y1, fy = coords(h)
    x0, x1, fx = coords(w)
    top = x[y0][:, x0] * (1 - fx)[None, :, None] + x[y0][:, x1] * fx[None, :, None]
    bot = x[y1][:, x0] * (1 - fx)[None, :, None] + x[y1][:, x1] * fx[None, :, None]
    return top * (1 - fy)[:, None, None] + bot * fy[:, None, None]


# -- Conv ---------------------------------------------------------------------------------------
CONV_CASES = [  # (H, W, kernel, stride, dilation, padding)
    (7, 5, 3, 1, 1, "SAME"), (7, 5, 3, 2, 1, "SAME"), (8, 6, 3, 2, 1, "VALID"), (9, 9, 3, 1, 2, "SAME"),
    (6, 7, (1, 3), (2, 1), 1, "VALID"), (1, 1, 3, 1, 1, "SAME"), (5, 4, 2, 2, 1, ((1, 0), (0, 1))),
]


@pytest.mark.parametrize("h,w,k,s,d,pad", CONV_CASES)
def test_conv_matches_numpy_and_predicts_its_shape(h, w, k, s, d, pad):
    init, apply = nn.Conv(4, k, stride=s, dilation=d, padding=pad, b_init=nn.uniform_init(0.5))
    out_shape, params = init(jax.random.PRNGKey(0), (2, h, w, 3))
    x = _x(2, h, w, 3)
    y = np.asarray(apply(params, x))
    assert y.shape == out_shape  # exact
    kk = (k, k) if isinstance(k, int) else k
    ss = (s, s) if isinstance(s, int) else s
    dd = (d, d) if isinstance(d, int) else d
    if pad == "SAME":
        p = (_same_pad(h, kk[0], ss[0], dd[0]), _same_pad(w, kk[1], ss[1], dd[1]))
    elif pad == "VALID":
        p = ((0, 0), (0, 0))
    else:
        p = pad
    for n in range(2):
        want = _np_conv(x[n], np.asarray(params["w"]), np.asarray(params["b"]), ss, dd, p)
        np.testing.assert_allclose(y[n], want, rtol=1e-5, atol=1e-5)  # float32 sums of <= 27 terms


@pytest.mark.parametrize("branch", ["row blocks", "padded channels"])
@pytest.mark.parametrize("h,w,k,s,d,pad", CONV_CASES + [(37, 29, 3, 1, 1, "SAME"), (23, 41, 3, 2, 2, "SAME")])
def test_fast_kernel_gradient_equals_xlas(h, w, k, s, d, pad, branch, monkeypatch):
    """The default kernel gradient (`nn.conv.WEIGHT_GRADIENT = "fast"`) equals XLA's transposed
    convolution in value, reverse and forward mode, on odd sizes, strides, dilations and explicit
    padding, in both of its branches (the size threshold moved so that every layer takes one): row
    blocks (a scan of im2col matrix products; the last two cases span several blocks, the block
    shrunk to 64 pixels) and XLA's with 5 output channels padded to 8. Relative tolerance 1e-5:
    float32 sums in another order."""
    monkeypatch.setattr(nn.conv, "BLOCK_PIXELS", 64)
    monkeypatch.setattr(nn.conv, "ROW_BLOCK_MIN_PIXELS", 0 if branch == "row blocks" else 10 ** 9)
    init, apply = nn.Conv(5, k, stride=s, dilation=d, padding=pad)
    _, params = init(jax.random.PRNGKey(0), (2, h, w, 3))
    x = jnp.asarray(_x(2, h, w, 3))
    g = jnp.asarray(_x(*apply(params, x).shape))

    def run(kind):
        monkeypatch.setattr(nn.conv, "WEIGHT_GRADIENT", kind)
        f = lambda p, v: jnp.vdot(apply(p, v), g)
        val, grads = jax.jit(jax.value_and_grad(f, argnums=(0, 1)))(params, x)
        _, tangent = jax.jvp(lambda p: apply(p, x), (params,), (jax.tree_util.tree_map(jnp.ones_like, params),))
        return val, grads, tangent

    fast, xla = run("fast"), run("xla")
    np.testing.assert_array_equal(np.asarray(fast[0]), np.asarray(xla[0]))  # the primal is XLA's, bit for bit
    for a, b in zip(jax.tree_util.tree_leaves(fast[1:]), jax.tree_util.tree_leaves(xla[1:])):
        scale = float(np.max(np.abs(np.asarray(b)))) or 1.0
        np.testing.assert_allclose(np.asarray(a) / scale, np.asarray(b) / scale, rtol=0, atol=1e-5)


def test_conv_by_rows_is_the_correlation_and_takes_an_accumulation_type(monkeypatch):
    """`nn.conv.conv_by_rows` (public since 0.9.15) as a forward convolution: XLA's correlation on odd
    sizes, a stride and a dilation across several blocks (block shrunk to 64 pixels), relative 1e-5;
    bfloat16 inputs accumulating in float32 come back float32 within bfloat16's rounding."""
    monkeypatch.setattr(nn.conv, "BLOCK_PIXELS", 64)
    for h, w, k, s, d in ((37, 29, 3, 1, 1), (23, 41, 3, 2, 2)):
        x, wt = jnp.asarray(_x(2, h, w, 3)), jnp.asarray(_x(k, k, 3, 5))
        want = jax.lax.conv_general_dilated(x, wt, (s, s), "SAME", rhs_dilation=(d, d),
                                            dimension_numbers=("NHWC", "HWIO", "NHWC"))
        got = nn.conv.conv_by_rows(x, wt, (s, s), "SAME", (d, d))
        scale = float(np.max(np.abs(np.asarray(want))))
        np.testing.assert_allclose(np.asarray(got) / scale, np.asarray(want) / scale, rtol=0, atol=1e-5)
    low = nn.conv.conv_by_rows(x.astype(jnp.bfloat16), wt.astype(jnp.bfloat16), (s, s), "SAME", (d, d),
                               preferred_element_type=jnp.float32)
    assert low.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(low) / scale, np.asarray(want) / scale, rtol=0, atol=2e-2)


def test_conv_leading_axes_and_no_bias():
    init, apply = nn.Conv(2, 3, bias=False)
    shape, params = init(jax.random.PRNGKey(1), (3, 2, 6, 5, 4))
    assert set(params) == {"w"}
    x = _x(3, 2, 6, 5, 4)
    y = apply(params, x)
    assert y.shape == shape == (3, 2, 6, 5, 2)
    np.testing.assert_allclose(np.asarray(y[1, 0]), np.asarray(apply(params, x[1, 0])), atol=1e-6)
    with pytest.raises(ValueError, match="Conv: input has 3 channels, the layer expects 4"):
        apply(params, _x(6, 5, 3))
    with pytest.raises(ValueError, match="padding must be 'SAME', 'VALID'"):
        nn.Conv(2, padding="FULL")


# -- ConvTranspose ------------------------------------------------------------------------------
@pytest.mark.parametrize("h,w,k,s,p", [(3, 4, 4, 2, None), (5, 5, 2, 2, None), (1, 1, 4, 2, None),
                                       (3, 2, 3, 2, 0), (4, 3, 3, 1, 1), (5, 4, 5, 3, 1), (2, 3, 4, 2, 3),
                                       (4, 4, 2, 3, 0)])
def test_conv_transpose_matches_numpy_scatter(h, w, k, s, p):
    init, apply = nn.ConvTranspose(3, k, stride=s, padding=p, b_init=nn.uniform_init(0.5))
    out_shape, params = init(jax.random.PRNGKey(2), (-1, h, w, 2))
    x = _x(2, h, w, 2)
    y = np.asarray(apply(params, x))
    assert y.shape[1:] == out_shape[1:]  # exact
    pp = (k - s) // 2 if p is None else p
    for n in range(2):
        want = _np_conv_transpose(x[n], np.asarray(params["w"]), np.asarray(params["b"]), (s, s), (pp, pp))
        np.testing.assert_allclose(y[n], want, rtol=1e-5, atol=1e-5)


def test_gradnet_deconvolution_doubles_the_size_and_is_the_adjoint_of_the_strided_conv():
    """4x4 stride-2 ConvTranspose: H -> 2H, and <Conv(x), y> = <x, ConvT(y)> for the conv with the
    same kernel (channels swapped), stride 2 and padding 1 (tolerance 1e-4 relative: float32 sums)."""
    ct_init, ct = nn.ConvTranspose(3, 4, stride=2, bias=False)
    shape, params = ct_init(jax.random.PRNGKey(3), (5, 6, 2))
    assert shape == (10, 12, 3)
    _, conv = nn.Conv(2, 4, stride=2, padding=((1, 1), (1, 1)), bias=False)
    w_conv = jnp.transpose(params["w"], (0, 1, 3, 2))
    y, x = _x(5, 6, 2), _x(10, 12, 3)
    lhs = float(jnp.sum(conv({"w": w_conv}, x) * y))
    rhs = float(jnp.sum(x * ct(params, y)))
    assert lhs == pytest.approx(rhs, rel=1e-4)


def test_bilinear_init_upsamples_a_ramp_exactly():
    """Away from the one-pixel border, the bilinear ConvTranspose reproduces a linear ramp sampled at
    half-pixel centres exactly (1e-5) and equals Upsample('bilinear')."""
    init, apply = nn.ConvTranspose(2, 4, stride=2, bias=False, w_init=nn.bilinear_init(2))
    _, params = init(jax.random.PRNGKey(0), (6, 7, 2))
    yy, xx = np.meshgrid(np.arange(6), np.arange(7), indexing="ij")
    ramp = np.stack([2.0 * yy + 3.0 * xx, -yy + 0.5 * xx], -1).astype(np.float32)
    up = np.asarray(apply(params, ramp))
    oy, ox = np.meshgrid((np.arange(12) + 0.5) / 2 - 0.5, (np.arange(14) + 0.5) / 2 - 0.5, indexing="ij")
    want = np.stack([2.0 * oy + 3.0 * ox, -oy + 0.5 * ox], -1)
    inner = (slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(up[inner], want[inner], atol=1e-5)
    _, ups = nn.Upsample(2, "bilinear")
    np.testing.assert_allclose(np.asarray(ups({}, ramp))[inner], up[inner], atol=1e-5)
    # narrowing (3 -> 2 channels, DEMC's decoder): the first two channels up-sample as above
    init3, apply3 = nn.ConvTranspose(2, 4, stride=2, bias=False, w_init=nn.bilinear_init(2))
    _, p3 = init3(jax.random.PRNGKey(0), (6, 7, 3))
    ramp3 = np.concatenate([ramp, np.full((6, 7, 1), 9.0, np.float32)], -1)
    np.testing.assert_allclose(np.asarray(apply3(p3, ramp3))[inner], want[inner], atol=1e-5)
    # widening (2 -> 3): the extra output channel starts at zero
    init4, apply4 = nn.ConvTranspose(3, 4, stride=2, bias=False, w_init=nn.bilinear_init(2))
    _, p4 = init4(jax.random.PRNGKey(0), (6, 7, 2))
    up4 = np.asarray(apply4(p4, ramp))
    np.testing.assert_allclose(up4[inner][..., :2], want[inner], atol=1e-5)
    assert np.all(up4[..., 2] == 0)


def test_identity_init_passes_the_first_block_through():
    init, apply = nn.Conv(4, 1, w_init=nn.identity_init((1, 0, 0)))
    _, params = init(jax.random.PRNGKey(0), (5, 5, 12))
    x = _x(5, 5, 12)
    np.testing.assert_array_equal(np.asarray(apply(params, x)), x[..., :4])  # exact: 1 * x + 0 * rest + 0
    with pytest.raises(ValueError, match="needs a 1x1 kernel with 3 x c_out input channels"):
        nn.Conv(4, 1, w_init=nn.identity_init((1, 0, 0)))[0](jax.random.PRNGKey(0), (5, 5, 10))


def test_initializer_scales():
    """He: std sqrt(2 / fan_in); Glorot on a conv kernel uses the receptive field (tolerance 5 %
    on 150k samples)."""
    w = np.asarray(nn.he_normal_init()(jax.random.PRNGKey(0), (3, 3, 64, 256)))
    assert w.std() == pytest.approx(np.sqrt(2 / (9 * 64)), rel=0.05)
    g = np.asarray(nn.glorot_uniform_init()(jax.random.PRNGKey(0), (3, 3, 64, 256)))
    assert np.abs(g).max() <= np.sqrt(6 / (9 * 64 + 9 * 256)) and np.abs(g).max() > 0.95 * np.sqrt(6 / (9 * 320))


# -- pooling and up-sampling ----------------------------------------------------------------------
@pytest.mark.parametrize("h,w", [(4, 6), (5, 7), (2, 2)])
def test_pools_match_numpy(h, w):
    x = _x(2, h, w, 3)
    for layer, red in ((nn.MaxPool(2), np.max), (nn.AvgPool(2), np.mean)):
        init, apply = layer
        shape, _ = init(None, (2, h, w, 3))
        y = np.asarray(apply({}, x))
        assert y.shape == shape == (2, h // 2, w // 2, 3)
        want = np.zeros(shape)
        for i, j in itertools.product(range(h // 2), range(w // 2)):
            want[:, i, j] = red(x[:, 2 * i:2 * i + 2, 2 * j:2 * j + 2], axis=(1, 2))
        np.testing.assert_allclose(y, want, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="smaller than the 2x2 window"):
        nn.MaxPool(2)[1]({}, _x(1, 1, 3))


@pytest.mark.parametrize("h,w", [(3, 4), (1, 1), (5, 2)])
def test_upsample_matches_numpy(h, w):
    x = _x(h, w, 2)
    init, apply = nn.Upsample(2, "nearest")
    assert init(None, (h, w, 2))[0] == (2 * h, 2 * w, 2)
    np.testing.assert_array_equal(np.asarray(apply({}, x)), x.repeat(2, 0).repeat(2, 1))
    _, bil = nn.Upsample(2, "bilinear")
    np.testing.assert_allclose(np.asarray(bil({}, x)), _np_bilinear_up(x, 2), atol=1e-5)


def test_maxpool_gradient_avoids_reduce_window():
    """Structural: the training-time gradient of MaxPool uses the reshape-and-max form, not
    reduce_window / select_and_scatter (4.5x slower on this CPU; module docstring of nn.pool)."""
    _, apply = nn.MaxPool(2)
    jaxpr = str(jax.make_jaxpr(jax.grad(lambda x: jnp.sum(apply({}, x) ** 2)))(jnp.ones((2, 8, 8, 4))))
    assert "reduce_window" not in jaxpr and "select_and_scatter" not in jaxpr


# -- gradients, jit, any size ---------------------------------------------------------------------
def test_gradients_against_finite_differences():
    """check_grads (order 1, modes fwd and rev) with its float32 default tolerances."""
    ci, ca = nn.Conv(2, 3, stride=2)
    ti, ta = nn.ConvTranspose(2, 4, stride=2)
    _, cp = ci(jax.random.PRNGKey(0), (5, 6, 3))
    _, tp = ti(jax.random.PRNGKey(1), (3, 3, 2))
    x = jnp.asarray(_x(5, 6, 3))
    check_grads(lambda p, v: ca(p, v), (cp, x), order=1, modes=("fwd", "rev"), atol=1e-2, rtol=1e-2)
    check_grads(lambda p, v: ta(p, v), (tp, jnp.asarray(_x(3, 3, 2))), order=1, modes=("fwd", "rev"),
                atol=1e-2, rtol=1e-2)
    xm = jnp.asarray(np.arange(4 * 6 * 2, dtype=np.float32).reshape(4, 6, 2) * 0.1)  # no ties
    check_grads(lambda v: nn.MaxPool(2)[1]({}, v), (xm,), order=1, modes=("rev",), atol=1e-2, rtol=1e-2)
    check_grads(lambda v: nn.Upsample(2, "bilinear")[1]({}, v), (x,), order=1, modes=("rev",),
                atol=1e-2, rtol=1e-2)


def test_jit_agrees_and_any_size_round_trips():
    init, apply = nn.serial(nn.Conv(4, 3), nn.LeakyRelu(0.1), nn.MaxPool(2), nn.Conv(4, 3),
                            nn.Upsample(2), nn.Conv(3, 3))
    _, params = init(jax.random.PRNGKey(0), (-1, 8, 8, 3))
    for h, w in ((7, 5), (1, 1), (9, 16)):
        x = jnp.asarray(_x(h, w, 3))
        xp, size = nn.pad_to_multiple(x, 2)
        assert xp.shape[0] % 2 == 0 and xp.shape[1] % 2 == 0 and size == (h, w)
        y = nn.crop_to(apply(params, xp), size)
        assert y.shape == (h, w, 3)
        yj = nn.crop_to(jax.jit(apply)(params, xp), size)
        np.testing.assert_allclose(np.asarray(y), np.asarray(yj), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(nn.pad_to_multiple(jnp.ones((4, 4, 1)), 4)[0]), np.ones((4, 4, 1)))
    with pytest.raises(ValueError, match="LeakyRelu: slope must be in"):
        nn.LeakyRelu(1.5)


# -- combinators -------------------------------------------------------------------------------------
def test_fanout_parallel_concat_and_residual():
    init, apply = nn.serial(nn.fanout(2), nn.parallel(nn.Conv(3, 3), nn.Conv(5, 1)), nn.Concat())
    shape, params = init(jax.random.PRNGKey(0), (6, 7, 2))
    x = _x(6, 7, 2)
    y = np.asarray(apply(params, x))
    assert y.shape == shape == (6, 7, 8)
    _, a = nn.Conv(3, 3)
    _, b = nn.Conv(5, 1)
    want = np.concatenate([a(params["1"]["0"], x), b(params["1"]["1"], x)], -1)
    np.testing.assert_allclose(y, want, atol=1e-6)  # the same convolutions, composed by hand
    r_init, r_apply = nn.residual(nn.Conv(2, 3))
    _, rp = r_init(jax.random.PRNGKey(1), (6, 7, 2))
    np.testing.assert_allclose(np.asarray(r_apply(rp, x)), x + np.asarray(nn.Conv(2, 3)[1](rp, x)), atol=1e-6)
    with pytest.raises(ValueError, match="it must keep the shape"):
        nn.residual(nn.Conv(3, 3))[0](jax.random.PRNGKey(0), (6, 7, 2))


def _unet(levels=2):
    stage = lambda c: nn.serial(nn.Conv(c, 3), nn.LeakyRelu(0.1))
    return nn.UNet([stage(4 * (i + 1)) for i in range(levels)], nn.MaxPool(2), stage(8), nn.Upsample(2),
                   [stage(4) for _ in range(levels)])


def test_unet_shapes_skips_and_any_size():
    init, apply = _unet(2)
    shape, params = init(jax.random.PRNGKey(0), (-1, 8, 8, 3))
    assert shape == (-1, 8, 8, 4)
    assert set(params) == {"down", "bottleneck", "decode"} and set(params["down"]) == {"0", "1"}
    for h, w in ((13, 9), (1, 1), (8, 8)):
        x = jnp.asarray(_x(2, h, w, 3))
        xp, size = nn.pad_to_multiple(x, 4)
        y = nn.crop_to(apply(params, xp), size)
        assert y.shape == (2, h, w, 4) and bool(jnp.all(jnp.isfinite(y)))
    # the skips carry information: changing the level-0 encoder weights changes the output even
    # with the bottleneck zeroed (only the skip path is left)
    x = jnp.asarray(_x(1, 8, 8, 3))
    zero_b = jax.tree_util.tree_map(jnp.zeros_like, params["bottleneck"])
    p0 = {**params, "bottleneck": zero_b}
    p1 = {**p0, "down": {**params["down"], "0": jax.tree_util.tree_map(lambda a: a * 2, params["down"]["0"])}}
    assert not np.allclose(np.asarray(apply(p0, x)), np.asarray(apply(p1, x)))


def test_recurrent_block_carries_its_state():
    init, apply, init_state = nn.RecurrentBlock(4)
    shape, params = init(jax.random.PRNGKey(0), (6, 5, 3))
    assert shape == (6, 5, 4) and init_state((6, 5, 3)).shape == (6, 5, 4)
    x = jnp.asarray(_x(6, 5, 3))
    h0 = init_state((6, 5, 3))
    h1 = apply(params, x, h0)
    h2 = apply(params, x, h1)
    assert h1.shape == (6, 5, 4) and not np.allclose(np.asarray(h1), np.asarray(h2))  # the state matters
    # zero the recurrent half of the first hidden conv: the state no longer matters
    w = params["h1"]["w"].at[:, :, 4:, :].set(0.0)
    p = {**params, "h1": {**params["h1"], "w": w}}
    np.testing.assert_allclose(np.asarray(apply(p, x, h0)), np.asarray(apply(p, x, h1)), atol=1e-6)
    # Difference quotients near a leaky-ReLU kink miss by percents; which input lands near one
    # depended on the test order (the module's generator), so the check uses its own input and
    # direction, in float64.
    x = jnp.asarray(np.random.default_rng(7).normal(size=(6, 5, 3)).astype(np.float32))
    h1 = apply(params, x, h0)
    np.random.seed(0)  # check_grads draws its directions from NumPy's global generator
    with jax.enable_x64():
        f64 = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), t)
        check_grads(lambda q, h: apply(q, f64(x), h), (f64(params), f64(h1)), order=1, modes=("rev",),
                    atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="hidden state has shape"):
        apply(params, x, jnp.zeros((6, 5, 3)))


# -- BatchNorm and stateful combinators ----------------------------------------------------------------
def test_batchnorm_train_and_eval():
    init, apply = nn.BatchNorm(momentum=0.9)
    _, p = init(None, (-1, 5, 5, 2))
    x = _x(4, 5, 5, 2) * 3 + 1
    y, upd = apply(p, x, train=True)
    y = np.asarray(y)
    # training mode: zero mean, unit (biased) variance per channel (tolerance: float32 sums of 100 values)
    np.testing.assert_allclose(y.mean(axis=(0, 1, 2)), 0, atol=1e-5)
    np.testing.assert_allclose(y.var(axis=(0, 1, 2)), 1, rtol=1e-3)
    n = 4 * 5 * 5
    np.testing.assert_allclose(upd["mean"], 0.1 * x.mean(axis=(0, 1, 2)), rtol=1e-5)
    np.testing.assert_allclose(upd["var"], 0.9 + 0.1 * x.var(axis=(0, 1, 2)) * n / (n - 1), rtol=1e-5)
    # inference mode: the stored statistics, nothing returned
    q = {**p, "mean": np.array([1.0, -2.0], np.float32), "var": np.array([4.0, 0.25], np.float32)}
    np.testing.assert_allclose(np.asarray(apply(q, x)), (x - q["mean"]) / np.sqrt(q["var"] + 1e-5), rtol=1e-5,
                               atol=1e-5)
    # a constant channel stays finite (eps)
    yc, _ = apply(p, np.ones((2, 3, 3, 2), np.float32), train=True)
    assert np.all(np.isfinite(np.asarray(yc)))


def test_stateful_combinators_gather_updates():
    init, apply = nn.serial(nn.Conv(2, 3), nn.BatchNorm(), nn.LeakyRelu(0.1), nn.residual(
        nn.serial(nn.Conv(2, 3), nn.BatchNorm())))
    assert nn.is_stateful(apply)
    _, params = init(jax.random.PRNGKey(0), (-1, 6, 6, 3))
    x = jnp.asarray(_x(2, 6, 6, 3))
    y_eval = apply(params, x)
    y, updates = apply(params, x, train=True)
    assert set(updates) == {"1", "3"} and set(updates["3"]) == {"1"}  # keyed like the params
    merged = nn.merge_updates(params, updates)
    assert not np.allclose(np.asarray(merged["1"]["mean"]), np.asarray(params["1"]["mean"]))
    np.testing.assert_array_equal(np.asarray(merged["0"]["w"]), np.asarray(params["0"]["w"]))  # untouched
    assert y.shape == y_eval.shape
    with pytest.raises(ValueError, match="updates for unknown entries"):
        nn.merge_updates(params, {"9": {}})


def test_trainer_merges_batchnorm_statistics(tmp_path):
    """The loss returns the running statistics as aux updates; after 20 steps the running mean is the
    exponential average (momentum 0.9) of the 20 batches' means, recomputed here by hand."""
    from jaxdenoise import checkpoint
    with registered("fakebn", "fake_bn_method"):
        fit("fakebn", tmp_path, tmp_path / "run", steps=20, progress=False, optimizer="adam",
            learning_rate=1e-9, checkpoint_every=20)
    p, _ = checkpoint.load(tmp_path / "run" / "weights")
    import fake_bn_method as fake

    p0 = fake.init(jax.random.PRNGKey(0), fake.Config())  # the trainer's initial params (seed 0)
    conv = nn.Conv(3, 1)[1]
    want = np.zeros(3)
    for step in range(20):  # the trainer's batches: rng seeded from (seed, step)
        b = fake.batch(None, step, fake.Config(), np.random.default_rng([0, step]))
        want = 0.9 * want + 0.1 * np.asarray(conv(p0["net"]["0"], b["x"])).mean(axis=(0, 1, 2))
    # tolerance 1e-4 relative: Adam at lr 1e-9 moves the conv weights by ~2e-8 over the 20 steps
    np.testing.assert_allclose(np.asarray(p["net"]["1"]["mean"]), want, rtol=1e-4)
