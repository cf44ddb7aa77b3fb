"""Orthonormal 2-D DCT-II over the pixel axes of HWC images, in pure JAX.

The screened-Poisson operator ``alpha I + D^T D`` with the forward differences of DESIGN.md and a
Neumann boundary (the last column of ``dx`` / last row of ``dy`` ignored) is diagonal in the DCT-II
basis (see `laplacian_eigenvalues`), which makes the L2 solve exact and O(N log N).

The transforms follow Makhoul, "A fast cosine transform in one and two dimensions" (IEEE TASSP
1980): reorder the samples (even ones forward, odd ones backward), take a *real* FFT of the same
length, rotate by a quarter-sample twiddle. `jax.scipy.fft.dctn` implements the same algorithm
with a complex FFT of the whole array; using `jnp.fft.rfft` and working on the contiguous last axis
is several times faster on CPU (peer timing in `docs/results/poisson.md`), and the orthonormality
and agreement with SciPy are tested in ``tests/test_solvers.py``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["dct2", "idct2", "dct2_cwh", "idct2_cwh", "laplacian_eigenvalues"]


def _ortho_scale(n: int, dtype, inverse: bool):
    """Per-frequency scale of the orthonormal DCT-II (sqrt(1/4n) at k=0, sqrt(1/2n) elsewhere)."""
    s = np.full((n,), np.sqrt(1.0 / (2 * n)))
    s[0] = np.sqrt(1.0 / (4 * n))
    if inverse:
        s = 1.0 / s
    return jnp.asarray(s, dtype)


def _dct_last(x):
    """Orthonormal DCT-II along the last axis (Makhoul 1980, Eqs. 20-21, real-FFT form)."""
    n = x.shape[-1]
    if n == 1:
        return x
    v = jnp.concatenate([x[..., ::2], jnp.flip(x[..., 1::2], -1)], -1)
    V = jnp.fft.rfft(v, axis=-1)                              # k = 0 .. n//2
    k = np.arange(n // 2 + 1)
    w = np.exp(-0.5j * np.pi * k / n)
    Z = V * jnp.asarray(w, V.dtype)
    # Z_k gives C_k = 2 Re Z_k for k <= n/2 and C_{n-k} = -2 Im Z_k (Hermitian symmetry of V).
    out = jnp.concatenate([Z.real, -jnp.flip(Z[..., 1:(n + 1) // 2].imag, -1)], -1)
    return out * (2 * _ortho_scale(n, x.dtype, False))


def _idct_last(X):
    """Inverse of `_dct_last` (orthonormal DCT-III) along the last axis."""
    n = X.shape[-1]
    if n == 1:
        return X
    C = X * (0.5 * _ortho_scale(n, X.dtype, True))           # = C_k / 2
    m = n // 2 + 1
    # C_{n-k} for k = 0 .. n//2, with C_n := 0.
    Crev = jnp.concatenate([jnp.zeros_like(C[..., :1]), jnp.flip(C[..., n - m + 1:], -1)], -1)
    k = np.arange(m)
    w = np.exp(0.5j * np.pi * k / n)
    V = (C[..., :m] - 1j * Crev) * jnp.asarray(w, jnp.result_type(X.dtype, jnp.complex64))
    v = jnp.fft.irfft(V, n=n, axis=-1)
    h = (n + 1) // 2
    even, odd = v[..., :h], jnp.flip(v[..., h:], -1)          # x[2j] = v[j], x[2j+1] = v[n-1-j]
    if n % 2:
        odd = jnp.concatenate([odd, jnp.zeros_like(odd[..., :1])], -1)
    return jnp.stack([even, odd], -1).reshape(*v.shape[:-1], 2 * h)[..., :n]


def _check_hwc(x, name):
    if x.ndim != 3:
        raise ValueError(f"{name}: expected an HWC array (height, width, channels), got shape {x.shape}")


def dct2_cwh(x):
    """`dct2` of an HWC array, coefficients left in (C, W, H) order (saves two transposes when the
    caller works in the DCT domain and transforms back with `idct2_cwh`)."""
    _check_hwc(x, "dct2(x)")
    y = _dct_last(jnp.transpose(x, (2, 0, 1)))                # C H W, transform over W
    return _dct_last(jnp.swapaxes(y, 1, 2))                   # C W H, transform over H


def idct2_cwh(X):
    """Inverse of `dct2_cwh`: (C, W, H) coefficients back to an HWC image."""
    if X.ndim != 3:
        raise ValueError(f"idct2_cwh(X): expected (channels, width, height), got shape {X.shape}")
    y = _idct_last(X)                                         # C W H, inverse over H
    y = _idct_last(jnp.swapaxes(y, 1, 2))                     # C H W, inverse over W
    return jnp.transpose(y, (1, 2, 0))


@jax.jit
def dct2(x):
    """Orthonormal 2-D DCT-II over axes (0, 1) of an HWC array; equals
    ``scipy.fft.dctn(x, axes=(0, 1), norm='ortho')``. Returns HWC."""
    return jnp.transpose(dct2_cwh(x), (2, 1, 0))


@jax.jit
def idct2(X):
    """Inverse of `dct2` (orthonormal, so also its transpose). HWC in, HWC out."""
    _check_hwc(X, "idct2(X)")
    return idct2_cwh(jnp.transpose(X, (2, 1, 0)))


def laplacian_eigenvalues(height: int, width: int, dtype=jnp.float32):
    """Eigenvalues of ``D^T D`` (Neumann boundary) in the `dct2` basis, shape (H, W, 1).

    ``lambda[k, l] = 4 sin^2(pi k / 2H) + 4 sin^2(pi l / 2W)``. The sine form (not ``2 - 2 cos``)
    keeps full relative precision at the lowest frequencies, where ``2 - 2 cos`` cancels
    catastrophically (e.g. 1 - cos(pi/1440) ~ 2.4e-6 is below float32 resolution of 1).
    """
    ky = 4.0 * np.sin(np.pi * np.arange(height) / (2 * height)) ** 2
    kx = 4.0 * np.sin(np.pi * np.arange(width) / (2 * width)) ** 2
    return jnp.asarray((ky[:, None] + kx[None, :])[..., None], dtype)
