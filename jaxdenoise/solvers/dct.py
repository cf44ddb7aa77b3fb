"""Orthonormal 2-D DCT-II in pure JAX, and the DCT-diagonal solve the L2 Poisson solver needs.

The screened-Poisson operator ``alpha I + D^T D`` with the forward differences of docs/architecture.md and a
Neumann boundary (the last column of ``dx`` / last row of ``dy`` ignored) is diagonal in the DCT-II
basis (see `laplacian_eigenvalues`), which makes the L2 solve exact and O(N log N):
``x = idct2(m * dct2(r))`` with ``m = 1 / (lambda + alpha)``. `dct_apply` computes exactly that.

Algorithm: the two-dimensional form of Makhoul, "A fast cosine transform in one and two dimensions"
(IEEE TASSP 1980, Sec. III). Reorder the samples along both axes (even ones forward, odd ones
backward), take *one* real 2-D FFT of the same size, and combine each stored coefficient
``V(k1, k2)`` with its reflection ``V(N1 - k1, k2)`` through the quarter-sample twiddles
``a_i(k) = exp(-i pi k / 2 N_i)``. With ``P = a2 V`` and ``Q(k1, k2) = conj(P(-k1, k2))``, for
``k2 = 0 .. N2 // 2``::

    C(k1, k2)      =  2 Re[a1 (P + Q)]        C(k1, N2 - k2) = -2 Im[a1 (P - Q)]

(unnormalized DCT-II, ``C(k, N) := 0``), and back::

    V(k1, k2) = conj(a1 a2) / 4 [C(k1, k2) - C(N1-k1, N2-k2) - i (C(N1-k1, k2) + C(k1, N2-k2))]

`dct_apply` never forms ``C`` in natural order: the forward twiddles at rows ``k1`` and
``N1 - k1``, the multiplier on the two half-size blocks ("lo", the ``C(k1, k2)``, and "hi", the
``C(k1, N2 - k2)``) and the inverse twiddles are one elementwise pass over ``V`` and its row
reflection, between one ``rfft2`` and one ``irfft2``. Unnormalized forward and exact inverse give
the orthonormal result, since the normalizing diagonal commutes with ``m``. Measured at
1280x720x3 (choices in docs/methods/poisson.md): the whole L2 solve went from 40 ms (a real FFT per
axis, a transpose between, four reorder / twiddle passes) to about 21 ms.
Orthonormality and agreement with SciPy are tested in ``tests/test_solvers.py``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from ..errors import JaxdenoiseError

__all__ = ["dct2", "idct2", "dct_apply", "laplacian_eigenvalue", "laplacian_eigenvalues"]


def _order(n: int) -> np.ndarray:
    """Makhoul's reordering: ``v[j] = x[order[j]]``, even samples forward then odd ones backward."""
    return np.concatenate([np.arange(0, n, 2), np.arange(1, n, 2)[::-1]])


def _reorder(x):
    n1, n2 = x.shape[-2:]
    return x[..., _order(n1), :][..., _order(n2)]


def _unorder(v):
    n1, n2 = v.shape[-2:]
    return v[..., np.argsort(_order(n1)), :][..., np.argsort(_order(n2))]


def _twiddles(n1: int, n2: int, dtype):
    """Real and imaginary parts of ``a1`` as (n1, 1) and of ``a2`` as (1, n2 // 2 + 1)."""
    a1 = np.exp(-0.5j * np.pi * np.arange(n1) / n1)[:, None]
    a2 = np.exp(-0.5j * np.pi * np.arange(n2 // 2 + 1) / n2)[None, :]
    return tuple(jnp.asarray(p, dtype) for p in (a1.real, a1.imag, a2.real, a2.imag))


def _reflect_rows(x, *, wrap: bool):
    """``x`` at row ``N1 - k1``; row 0 maps to row 0 (``wrap``, the FFT's periodicity) or to 0
    (the DCT's ``C(N1, .) := 0``)."""
    first = x[..., :1, :] if wrap else jnp.zeros_like(x[..., :1, :])
    return jnp.concatenate([first, jnp.flip(x[..., 1:, :], -2)], -2)


# The twiddle arithmetic is written on real and imaginary planes: XLA's CPU backend runs complex
# elementwise fusions several times slower than the same arithmetic on float planes.

def _spectrum(x):
    """``P = a2 V`` with ``V = rfft2`` of the reordered ``x``, as (real, imaginary) planes."""
    n1, n2 = x.shape[-2:]
    _, _, c2, s2 = _twiddles(n1, n2, x.dtype)
    v = jnp.fft.rfft2(_reorder(x))
    vr, vi = v.real, v.imag
    return c2 * vr - s2 * vi, c2 * vi + s2 * vr


def _lo_hi(pr, pi, qr, qi, c1, s1):
    """``lo = 2 Re[a1 (P + Q)]`` and ``hi = -2 Im[a1 (P - Q)]`` from planes of ``P``, ``Q``, ``a1``."""
    return 2 * (c1 * (pr + qr) - s1 * (pi + qi)), -2 * (c1 * (pi - qi) + s1 * (pr - qr))


def _back(zr, zi, n2: int):
    """``x`` from ``Z = C(k1, k2) - C(N1-k1, N2-k2) - i (C(N1-k1, k2) + C(k1, N2-k2))``: the inverse
    twiddle ``conj(a1 a2) / 4``, one ``irfft2``, and the inverse reordering."""
    n1 = zr.shape[-2]
    c1, s1, c2, s2 = _twiddles(n1, n2, zr.dtype)
    wr, wi = (c1 * c2 - s1 * s2) / 4, -(c1 * s2 + s1 * c2) / 4
    v = jax.lax.complex(wr * zr - wi * zi, wr * zi + wi * zr)
    return _unorder(jnp.fft.irfft2(v, s=(n1, n2))).astype(zr.dtype)


def _forward_halves(x):
    """Unnormalized 2-D DCT-II of the last two axes as the halves ``(lo, hi)``, each (..., N1, N2//2+1):
    ``lo[k1, k2] = C(k1, k2)``, ``hi[k1, k2] = C(k1, N2 - k2)`` (``hi[:, 0] = 0``)."""
    n1, n2 = x.shape[-2:]
    c1, s1, _, _ = _twiddles(n1, n2, x.dtype)
    pr, pi = _spectrum(x)
    qr, qi = _reflect_rows(pr, wrap=True), -_reflect_rows(pi, wrap=True)   # Q = conj P(-k1)
    return _lo_hi(pr, pi, qr, qi, c1, s1)


def _inverse_halves(lo, hi, n2: int):
    """Inverse of `_forward_halves` (``n2``: the last axis's length, which the halves do not fix)."""
    return _back(lo - _reflect_rows(hi, wrap=False), -(_reflect_rows(lo, wrap=False) + hi), n2)


def _halves(c):
    """Split a natural-order (..., N1, N2) coefficient array into ``(lo, hi)`` as above."""
    n2 = c.shape[-1]
    m2 = n2 // 2 + 1
    hi = jnp.concatenate([jnp.zeros_like(c[..., :1]), jnp.flip(c, -1)[..., :m2 - 1]], -1)
    return c[..., :m2], hi


def _join(lo, hi, n2: int):
    """Inverse of `_halves`: natural-order (..., N1, N2)."""
    return jnp.concatenate([lo, jnp.flip(hi[..., 1:(n2 + 1) // 2], -1)], -1)


def _ortho(n1: int, n2: int, dtype):
    """(N1, N2) factor turning the unnormalized DCT-II into the orthonormal one."""
    s1 = np.full(n1, np.sqrt(1.0 / (2 * n1)))
    s1[0] = np.sqrt(1.0 / (4 * n1))
    s2 = np.full(n2, np.sqrt(1.0 / (2 * n2)))
    s2[0] = np.sqrt(1.0 / (4 * n2))
    return jnp.asarray(s1[:, None] * s2[None, :], dtype)


def _check_hwc(x, name):
    if x.ndim != 3:
        raise JaxdenoiseError(f"{name}: expected an HWC array (height, width, channels), got shape {x.shape}")


@jax.jit
def dct2(x):
    """Orthonormal 2-D DCT-II over axes (0, 1) of an HWC array; equals
    ``scipy.fft.dctn(x, axes=(0, 1), norm='ortho')``. Returns HWC."""
    _check_hwc(x, "dct2(x)")
    h, w = x.shape[:2]
    lo, hi = _forward_halves(jnp.moveaxis(x, -1, 0))
    return jnp.moveaxis(_join(lo, hi, w) * _ortho(h, w, x.dtype), 0, -1)


@jax.jit
def idct2(X):
    """Inverse of `dct2` (orthonormal, so also its transpose). HWC in, HWC out."""
    _check_hwc(X, "idct2(X)")
    h, w = X.shape[:2]
    lo, hi = _halves(jnp.moveaxis(X, -1, 0) / _ortho(h, w, X.dtype))
    return jnp.moveaxis(_inverse_halves(lo, hi, w), 0, -1)


def dct_apply(x, multiplier):
    """``idct2(m * dct2(x))`` of an HWC array without forming the coefficients in natural order
    (module docstring). HWC in, HWC out.

    ``multiplier(k1, k2)`` returns ``m`` at integer frequency indices (NumPy arrays, ``k1`` of shape
    (H, 1), ``k2`` of shape (1, K), both in the natural order of `dct2`: ``m[k1, k2]`` scales the cosine of
    frequencies ``(k1, k2)``); it is evaluated on the two half-size blocks and their row
    reflections inside the fused twiddle pass (reading a precomputed (H, W) multiplier instead
    measured 1.4x slower in total), so build it from constants and scalars.
    """
    h, w = x.shape[:2]
    k1 = np.arange(h)[:, None]
    k2 = np.arange(w // 2 + 1)[None, :]
    k1r = (h - k1) % h                                    # the reflected row N1 - k1 (row 0: itself)
    k2r = np.where(k2 == 0, 0, w - k2)                    # hi's column index N2 - k2 (column 0 unused)
    c1, s1, _, _ = _twiddles(h, w, x.dtype)
    c1r, s1r = c1[k1r[:, 0]], s1[k1r[:, 0]]
    # Everything between the rfft2 and the irfft2 is one elementwise pass over P and its row
    # reflection P(-k1): the forward twiddles at rows k1 (Q = conj P(-k1)) and N1 - k1 (Q = conj P(k1)),
    # the multiplier, and the inverse twiddle's input Z.
    pr, pi = _spectrum(jnp.moveaxis(x, -1, 0))            # the transpose fuses into the reordering
    pbr, pbi = _reflect_rows(pr, wrap=True), _reflect_rows(pi, wrap=True)
    lo, hi = _lo_hi(pr, pi, pbr, -pbi, c1, s1)
    lo_r, hi_r = _lo_hi(pbr, pbi, pr, -pi, c1r, s1r)
    top = k1 > 0                                           # C(N1, .) := 0 for the reflection of row 0
    m_lo, m_hi = multiplier(k1, k2), jnp.where(k2 == 0, 0, multiplier(k1, k2r))
    m_lo_r = jnp.where(top, multiplier(k1r, k2), 0)
    m_hi_r = jnp.where(top & (k2 > 0), multiplier(k1r, k2r), 0)
    out = _back(m_lo * lo - m_hi_r * hi_r, -(m_lo_r * lo_r + m_hi * hi), w)
    return jnp.moveaxis(out.astype(x.dtype), 0, -1)


def laplacian_eigenvalues(height: int, width: int, dtype=jnp.float32):
    """Eigenvalues of ``D^T D`` (Neumann boundary) in the `dct2` basis, shape (H, W, 1)."""
    return laplacian_eigenvalue(np.arange(height)[:, None], np.arange(width)[None, :], height, width,
                                dtype)[..., None]


def laplacian_eigenvalue(k1: np.ndarray, k2: np.ndarray, height: int, width: int, dtype=jnp.float32):
    """The eigenvalue of ``D^T D`` at DCT frequency indices ``(k1, k2)`` (NumPy integer arrays that
    broadcast, such as the ones `dct_apply` passes to its multiplier).

    ``lambda[k, l] = 4 sin^2(pi k / 2H) + 4 sin^2(pi l / 2W)``, each axis's term computed in float64
    (a constant of the compiled program), summed in ``dtype``. The sine form (not ``2 - 2 cos``)
    keeps full relative precision at the lowest frequencies, where ``2 - 2 cos`` cancels
    catastrophically (e.g. 1 - cos(pi/1440) ~ 2.4e-6 is below float32 resolution of 1).
    """
    ly = 4 * np.sin(np.pi * np.asarray(k1) / (2 * height)) ** 2
    lx = 4 * np.sin(np.pi * np.asarray(k2) / (2 * width)) ** 2
    return jnp.asarray(ly, dtype) + jnp.asarray(lx, dtype)
