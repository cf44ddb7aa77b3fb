"""Screened Poisson reconstruction for gradient-domain rendering (Guo et al. 2019, Sec. 3, Eq. 1).

    I* = argmin_I  ||D I - g||_p + alpha ||I - I_b||_p ,   p in {1, 2},  per colour channel,

with ``D = (D_x, D_y)`` the forward differences of docs/architecture.md,
``(D_x I)[y, x] = I[y, x+1] - I[y, x]`` and ``(D_y I)[y, x] = I[y+1, x] - I[y, x]``, ``g = (dx, dy)``
the rendered gradients and ``I_b`` the rendered base (primal) image. Conventions (see
``docs/methods/poisson.md``):

- **Boundary.** The last column of ``dx`` and the last row of ``dy`` pair a pixel with one outside
  the image: they are *ignored* (treated as zero in ``D I`` and in ``g``). This is the Neumann
  boundary, under which ``D^T D`` is the Neumann Laplacian, diagonal in the DCT-II basis.
- **L2** means squared norms, ``E_2 = ||D I - g||^2 + alpha ||I - I_b||^2``, whose normal equations
  are ``(alpha 1 + D^T D) I = D^T g + alpha I_b``. (Lehtinen et al. 2013 write the same system as
  ``||[D; a 1] I - [g; a I_b]||^2``, i.e. their ``a`` is ``sqrt(alpha)`` here.)
- **L1** is the anisotropic, element-wise norm, ``E_1 = sum |D I - g| + alpha sum |I - I_b|``,
  summed over pixels and channels (Lehtinen 2013 / Kettunen 2015 use the same per-component form).

Solvers (all pure and jittable, HWC in, HWC out, iteration counts keyword-only and static):

- `poisson_l2_dct`: exact L2 solve in the DCT domain; differentiable (it is linear in the inputs).
- `poisson_l2_cg`: the jaxopt conjugate-gradient baseline for the same system.
- `poisson_l1_irls`: the classical L1 baseline, iteratively reweighted least squares with each
  weighted system solved by jaxopt CG (20 IRLS x 50 CG as the common presets).
- `poisson_l1_admm`: ADMM for the L1 problem whose linear step is the exact DCT solve (fixed penalty,
  started at the L2 solution).
- `poisson_l1_radmm`: the fast L1 solver (the default of ``poisson-l1``): the same exact-DCT ADMM in
  its Douglas-Rachford form, started from a clamped-data warm start, with a decreasing penalty
  schedule (continuation) and over-relaxation.

Helpers: `gradient`, `gradient_adjoint`, `normal_matvec`, `energy`, `residual`.
"""
from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import compute_dtype, edge_views, is_concrete, median9


def solve_cg(*args, **kwargs):
    """jaxopt's conjugate gradient, imported on first use: the training path (`jaxdenoise.train`,
    the optimizers beside this module) must import on machines without jaxopt (a GPU box)."""
    from jaxopt.linear_solve import solve_cg as cg

    return cg(*args, **kwargs)
from .dct import dct_apply, laplacian_eigenvalue
from ..errors import JaxdenoiseError

__all__ = [
    "SolverError", "gradient", "gradient_adjoint", "normal_matvec", "energy", "residual",
    "poisson_l2_dct", "poisson_l2_cg", "poisson_l1_irls", "poisson_l1_admm", "poisson_l1_radmm",
]


class SolverError(JaxdenoiseError):
    """A solver was called with an argument of the wrong shape, dtype or value."""


# -- argument checks --------------------------------------------------------------------------------

def _check_images(fn: str, **images):
    """Validate same-shaped (H, W, C) images; NaN/Inf is refused when the values are concrete."""
    shape0 = name0 = None
    for name, x in images.items():
        if x is None:
            raise SolverError(f"{fn}: argument '{name}' is None; expected an (H, W, C) array")
        shape = tuple(np.shape(x))
        if len(shape) != 3 or 0 in shape:
            raise SolverError(f"{fn}: argument '{name}' has shape {shape}; expected (H, W, C) with every size >= 1")
        if shape0 is None:
            shape0, name0 = shape, name
        elif shape != shape0:
            raise SolverError(f"{fn}: argument '{name}' has shape {shape} but '{name0}' has {shape0}; "
                              "they must match")
        if is_concrete(x):
            bad = int(np.size(x) - np.count_nonzero(np.isfinite(np.asarray(x))))
            if bad:
                raise SolverError(f"{fn}: argument '{name}' has {bad} NaN/Inf value(s); expected finite values")
    dt = compute_dtype(*images.values())  # float32 at least (none is None: refused above)
    return [jnp.asarray(x, dt) for x in images.values()]


def _check_alpha(fn: str, alpha: Any, dtype):
    if np.ndim(alpha) != 0:
        raise SolverError(f"{fn}: argument 'alpha' has shape {np.shape(alpha)}; expected a scalar")
    if is_concrete(alpha):
        a = float(alpha)
        if not (np.isfinite(a) and a > 0):
            raise SolverError(f"{fn}: argument 'alpha' is {a}; expected a finite value > 0 "
                              "(alpha = 0 leaves the image mean undetermined)")
    return jnp.asarray(alpha, dtype)


def _check_iters(fn: str, **counts):
    for name, n in counts.items():
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 0:
            raise SolverError(f"{fn}: argument '{name}' is {n!r}; expected a non-negative Python int "
                              "(static under jit)")


# -- operators ----------------------------------------------------------------------------------------

def gradient(image):
    """Forward differences ``(D_x I, D_y I)`` of an HWC image, with the out-of-image last column of
    ``D_x I`` / last row of ``D_y I`` set to zero (Neumann boundary, module docstring)."""
    gx = jnp.concatenate([image[:, 1:] - image[:, :-1], jnp.zeros_like(image[:, :1])], 1)
    gy = jnp.concatenate([image[1:] - image[:-1], jnp.zeros_like(image[:1])], 0)
    return gx, gy


def _mask(gx, gy):
    """Zero the ignored entries (last column of dx, last row of dy) of user-given gradients."""
    gx, gy = jnp.asarray(gx), jnp.asarray(gy)
    # `where` on an index mask rather than `.at[...].set(0)`: it fuses into the consumer instead of
    # materializing masked copies (2 ms of the 1280x720 L2 solve).
    keep_x = jnp.arange(gx.shape[1])[None, :, None] < gx.shape[1] - 1
    keep_y = jnp.arange(gy.shape[0])[:, None, None] < gy.shape[0] - 1
    return jnp.where(keep_x, gx, 0), jnp.where(keep_y, gy, 0)


def gradient_adjoint(gx, gy):
    """``D^T (gx, gy)`` (a negative divergence); the ignored entries of ``gx``/``gy`` are not read."""
    gx, gy = _mask(gx, gy)
    ax = jnp.concatenate([jnp.zeros_like(gx[:, :1]), gx[:, :-1]], 1) - gx
    ay = jnp.concatenate([jnp.zeros_like(gy[:1]), gy[:-1]], 0) - gy
    return ax + ay


def normal_matvec(image, alpha, wx=None, wy=None, wb=None):
    """``(D^T W D + alpha W_b) I``; unit weights when ``wx``/``wy``/``wb`` are None."""
    gx, gy = gradient(image)
    if wx is not None:
        gx, gy = wx * gx, wy * gy
    base = alpha * image if wb is None else wb * image
    return gradient_adjoint(gx, gy) + base


def energy(image, base, dx, dy, alpha, *, norm: str = "l2"):
    """Eq. 1 energy summed over pixels and channels: ``||D I - g||^2 + alpha ||I - I_b||^2`` (``'l2'``)
    or ``sum |D I - g| + alpha sum |I - I_b|`` (``'l1'``). Ignored boundary entries do not count."""
    image, base, dx, dy = _check_images("energy", image=image, base=base, dx=dx, dy=dy)
    alpha = _check_alpha("energy", alpha, image.dtype)
    if norm not in ("l1", "l2"):
        raise SolverError(f"energy: argument 'norm' is {norm!r}; expected 'l1' or 'l2'")
    return _energy(image, base, dx, dy, alpha, norm=norm)


@functools.partial(jax.jit, static_argnames=("norm",))
def _energy(image, base, dx, dy, alpha, *, norm):
    gx, gy = gradient(image)
    rx, ry = _mask(gx - dx, gy - dy)
    rb = image - base
    if norm == "l2":
        return jnp.sum(rx * rx) + jnp.sum(ry * ry) + alpha * jnp.sum(rb * rb)
    return jnp.sum(jnp.abs(rx)) + jnp.sum(jnp.abs(ry)) + alpha * jnp.sum(jnp.abs(rb))


def residual(image, base, dx, dy, alpha):
    """Relative residual of the L2 normal equations, per channel, shape (C,):
    ``||A I - b|| / ||b||`` with ``A = alpha 1 + D^T D`` and ``b = D^T g + alpha I_b``.

    Computed in the inputs' dtype: to judge a float32 solution to 1e-6, pass float64 arrays (with
    x64 enabled), since float32 evaluation of ``A I - b`` alone carries ~1e-7 * ||A|| ||I|| error.
    When ``b = 0`` (all-zero inputs) the absolute residual is returned (guard against 0 / 0).
    """
    image, base, dx, dy = _check_images("residual", image=image, base=base, dx=dx, dy=dy)
    alpha = _check_alpha("residual", alpha, image.dtype)
    return _residual(image, base, dx, dy, alpha)


@jax.jit
def _residual(image, base, dx, dy, alpha):
    b = gradient_adjoint(dx, dy) + alpha * base
    r = normal_matvec(image, alpha) - b
    nr = jnp.sqrt(jnp.sum(r * r, axis=(0, 1)))
    nb = jnp.sqrt(jnp.sum(b * b, axis=(0, 1)))
    return jnp.where(nb > 0, nr / jnp.where(nb > 0, nb, 1), nr)


# -- L2 ------------------------------------------------------------------------------------------------

def _dct_solve(rhs, alpha):
    """``(alpha 1 + D^T D)^{-1} rhs`` for an HWC ``rhs`` orthogonal to constants.

    The multiplier ``1 / (lambda + alpha)`` is evaluated inside the DCT's fused twiddle pass. The DC
    coefficient is set to exactly zero: analytically ``1^T rhs = 0`` for the right-hand sides used
    here (they are ``D^T(...)``, and ``D 1 = 0``), but float32 rounding leaves ~1e-7 * ||rhs|| in
    it, which division by the DC eigenvalue ``alpha`` (down to 1e-6) would blow up into a large
    constant offset. This is where small alpha is unstable, so the guard sits here.
    """
    h, w = rhs.shape[:2]

    def multiplier(k1, k2):
        lam = laplacian_eigenvalue(k1, k2, h, w, rhs.dtype)
        return jnp.where((k1 == 0) & (k2 == 0), 0, 1 / (lam + alpha))

    return dct_apply(rhs, multiplier)


def _per_channel(fn, *arrays):
    """vmap ``fn`` over the channel axis of HWC arrays (channels are independent problems).

    Inside, each channel is an (H, W, 1) image and the stacked arrays are laid out (C, H, W, 1), so
    the DCT's moves of the channel axis are free reshapes (measured ~1.3x faster at 1280x720 than
    transposing HWC arrays)."""
    moved = [jnp.moveaxis(a, -1, 0)[..., None] for a in arrays]
    out = jax.vmap(fn)(*moved)
    return jnp.moveaxis(out[..., 0], 0, -1)


# Each public solver validates its (concrete) arguments, then calls a jitted implementation: eager
# calls compile once per shape instead of dispatching dozens of small ops, and inside a caller's
# jit the inner jit is simply inlined.

def poisson_l2_dct(base, dx, dy, alpha):
    """Exact L2 screened-Poisson reconstruction (Eq. 1, p = 2) by the DCT (O(N log N), no iteration).

    Solved in correction form ``I = I_b + (alpha 1 + D^T D)^{-1} D^T (g - D I_b)``: the correction's
    right-hand side is orthogonal to constants (its DC mode is exactly known, see `_dct_solve`), and for
    large alpha the correction vanishes smoothly, so ``I -> I_b`` without cancellation at alpha = 1e6.
    Differentiable in every argument (linear in base, dx, dy; smooth in alpha).
    """
    base, dx, dy = _check_images("poisson_l2_dct", base=base, dx=dx, dy=dy)
    alpha = _check_alpha("poisson_l2_dct", alpha, base.dtype)
    return _l2_dct(base, dx, dy, alpha)


@jax.jit
def _l2_dct(base, dx, dy, alpha):
    def one(b_img, gx_t, gy_t):
        gx, gy = gradient(b_img)
        return b_img + _dct_solve(gradient_adjoint(gx_t - gx, gy_t - gy), alpha)

    return _per_channel(one, base, dx, dy)


def poisson_l2_cg(base, dx, dy, alpha, *, maxiter: int = 1000, tol: float = 1e-6):
    """L2 reconstruction by jaxopt conjugate gradient on the normal equations (the baseline).

    Per channel (vmapped), warm-started at ``I_b``; stops when ``||r|| <= tol ||b||`` or after
    ``maxiter`` iterations. Its iteration count grows like ``sqrt(cond) = sqrt(8 / alpha)`` once alpha is
    below the smallest nonzero Laplacian eigenvalue (~(pi/H)^2), which is what makes it slow at small
    alpha (measured in ``experiments/bench_poisson.py``).
    """
    base, dx, dy = _check_images("poisson_l2_cg", base=base, dx=dx, dy=dy)
    alpha = _check_alpha("poisson_l2_cg", alpha, base.dtype)
    _check_iters("poisson_l2_cg", maxiter=maxiter)
    if not (np.ndim(tol) == 0 and 0 < float(tol) < 1):
        # tol = 0 would let CG step past an exactly-zero residual (0 / 0 = NaN).
        raise SolverError(f"poisson_l2_cg: argument 'tol' is {tol!r}; expected 0 < tol < 1")
    return _l2_cg(base, dx, dy, alpha, maxiter=maxiter, tol=float(tol))


@functools.partial(jax.jit, static_argnames=("maxiter", "tol"))
def _l2_cg(base, dx, dy, alpha, *, maxiter, tol):
    def one(b_img, gx, gy):
        rhs = gradient_adjoint(gx, gy) + alpha * b_img
        return solve_cg(lambda v: normal_matvec(v, alpha), rhs, init=b_img, tol=tol, atol=0.0,
                        maxiter=maxiter)

    return _per_channel(one, base, dx, dy)


# -- L1 ------------------------------------------------------------------------------------------------

def poisson_l1_irls(base, dx, dy, alpha, *, irls_iters: int = 20, cg_iters: int = 50, eps: float = 1e-4,
                    init: str = "l2"):
    """L1 reconstruction by iteratively reweighted least squares, the classical baseline
    (Lehtinen et al. 2013; Guo 2019 Sec. 3 "usually relying on IRLS").

    Each iteration reweights ``w = 1 / max(|r|, eps)`` (the ``eps`` floor bounds the weights where a
    residual vanishes, which would otherwise divide by zero; it makes the problem a Huber-like
    smoothing of L1 with threshold ``eps``) and runs ``cg_iters`` jaxopt CG iterations on
    ``(D^T W_g D + alpha W_b) I = D^T W_g g + alpha W_b I_b``, warm-started at the previous iterate.
    ``init`` is ``'l2'`` (start at the exact L2 solution, the default: it halved the energy gap of
    the 20 x 50 preset in our scan) or ``'base'`` (start at ``I_b``).
    """
    base, dx, dy = _check_images("poisson_l1_irls", base=base, dx=dx, dy=dy)
    alpha = _check_alpha("poisson_l1_irls", alpha, base.dtype)
    _check_iters("poisson_l1_irls", irls_iters=irls_iters, cg_iters=cg_iters)
    if init not in ("base", "l2"):
        raise SolverError(f"poisson_l1_irls: argument 'init' is {init!r}; expected 'base' or 'l2'")
    if not (np.ndim(eps) == 0 and np.isfinite(float(eps)) and float(eps) > 0):
        raise SolverError(f"poisson_l1_irls: argument 'eps' is {eps!r}; expected a finite scalar > 0")
    return _l1_irls(base, dx, dy, alpha, irls_iters=irls_iters, cg_iters=cg_iters, eps=float(eps), init=init)


@functools.partial(jax.jit, static_argnames=("irls_iters", "cg_iters", "eps", "init"))
def _l1_irls(base, dx, dy, alpha, *, irls_iters, cg_iters, eps, init):
    dx, dy = _mask(dx, dy)
    x0 = base if init == "base" else _l2_dct(base, dx, dy, alpha)

    def one(b_img, gx_t, gy_t, x):
        def step(x, _):
            gx, gy = gradient(x)
            wx = 1.0 / jnp.maximum(jnp.abs(gx - gx_t), eps)
            wy = 1.0 / jnp.maximum(jnp.abs(gy - gy_t), eps)
            wb = alpha / jnp.maximum(jnp.abs(x - b_img), eps)
            rhs = gradient_adjoint(wx * gx_t, wy * gy_t) + wb * b_img
            # Jacobi preconditioner: the diagonal of D^T W D + W_b. The weights span up to 1/eps over
            # alpha (1e10 at alpha = 1e-6); without it float32 CG loses conjugacy and can diverge.
            wxm, wym = _mask(wx, wy)
            diag = (wxm + jnp.concatenate([jnp.zeros_like(wxm[:, :1]), wxm[:, :-1]], 1)
                    + wym + jnp.concatenate([jnp.zeros_like(wym[:1]), wym[:-1]], 0) + wb)
            # tol = 1e-7 (float32's rounding floor, relative): CG stops once the residual cannot
            # shrink further. A smaller tol lets it step at the floor, where p.Ap rounds to 0 and the
            # next step divides 0 by 0: NaN, seen in the transposed solve of the gradient at alpha
            # 1e-6 and 1e6 (stability suite, 7x5 case).
            x = solve_cg(lambda v: normal_matvec(v, alpha, wx, wy, wb), rhs, init=x, tol=1e-7, atol=0.0,
                         maxiter=cg_iters, M=lambda v: v / diag)
            # Exact correction along the constant image (deflation of the near-null mode): D^T W D
            # annihilates constants, so along 1 the system is sum(W_b) c = sum(W_b (I_b - x)). Its
            # eigenvalue is ~alpha / eps times smaller than the gradient term's (1e-10 relative at
            # alpha = 1e-6); CG in float32 cannot resolve it and lets the image mean drift by 1e3+.
            wbr = alpha / jnp.maximum(jnp.abs(x - b_img), eps)
            x = x + jnp.sum(wbr * (b_img - x)) / jnp.sum(wbr)
            return x, None
        return jax.lax.scan(step, x, None, length=irls_iters)[0]

    return _per_channel(one, base, dx, dy, x0)


def _shrink(v, t):
    """Soft thresholding, the proximal map of ``t |.|``."""
    return jnp.sign(v) * jnp.maximum(jnp.abs(v) - t, 0)


def poisson_l1_admm(base, dx, dy, alpha, *, iters: int = 100, rho: float | None = None, relax: float = 1.6):
    """L1 reconstruction by ADMM (Boyd et al. 2011, Secs. 3.1, 3.4.3, 6.1), the fast solver beside IRLS.

    Splits ``z_g = D I - g`` and ``z_b = I - I_b`` and alternates: the I-step is a screened Poisson
    solve with the same operator ``alpha 1 + D^T D`` (penalties ``rho`` on ``z_g`` and ``alpha rho``
    on ``z_b``, so ``rho`` cancels from the operator), done exactly by the DCT; the z-steps are soft
    thresholding with threshold ``1 / rho``; over-relaxation ``relax`` (Boyd Sec. 3.4.3). Starts from
    the exact L2 solution. ``rho`` defaults to ``1 / mean |D I_2 - g|`` over the L2 solution ``I_2``:
    the L1 problem is 1-homogeneous in the images, so rho must scale like 1 / (residual size) for the
    iteration to be scale-invariant; the factor 1 and ``relax = 1.6`` were the most robust of a scan
    over two synthetic frames (docs/methods/poisson.md). Residual balancing (Boyd Sec. 3.4.1) was
    tried and slowed convergence.
    """
    base, dx, dy = _check_images("poisson_l1_admm", base=base, dx=dx, dy=dy)
    alpha = _check_alpha("poisson_l1_admm", alpha, base.dtype)
    _check_iters("poisson_l1_admm", iters=iters)
    if not 0 < relax < 2:
        raise SolverError(f"poisson_l1_admm: argument 'relax' is {relax}; expected in (0, 2)")
    if rho is not None:
        if not (np.ndim(rho) == 0 and (not is_concrete(rho) or (np.isfinite(float(rho)) and float(rho) > 0))):
            raise SolverError(f"poisson_l1_admm: argument 'rho' is {rho!r}; expected a finite scalar > 0 or None")
        rho = jnp.asarray(rho, base.dtype)
    return _l1_admm(base, dx, dy, alpha, rho, iters=iters, relax=float(relax))


@functools.partial(jax.jit, static_argnames=("iters", "relax"))
def _l1_admm(base, dx, dy, alpha, rho, *, iters, relax):
    dt = base.dtype
    x0 = _l2_dct(base, dx, dy, alpha)
    gx_t, gy_t = _mask(dx, dy)
    gx, gy = gradient(x0)
    zx, zy = _mask(gx - gx_t, gy - gy_t)
    if rho is None:
        scale = (jnp.sum(jnp.abs(zx)) + jnp.sum(jnp.abs(zy))) / (2 * zx.size)
        # Guard: on exact data the L2 residuals are ~0 and 1 / scale would be infinite; any finite
        # rho converges, so floor the scale relative to the image magnitude (and absolutely).
        scale = jnp.maximum(scale, 1e-6 * jnp.mean(jnp.abs(base)) + jnp.finfo(dt).tiny)
        # rho is a step parameter (the converged answer does not depend on it): no gradient flows
        # through it, which would otherwise be -1/scale^2 = -inf on an all-black frame.
        thr = jax.lax.stop_gradient(scale).astype(dt)          # = 1 / rho
    else:
        thr = (1.0 / rho).astype(dt)

    def one(b_img, gx_t, gy_t, x, zx, zy):
        zb = x - b_img
        zeros = jnp.zeros_like(x)

        def body(_, s):
            x, zx, zy, zb, ux, uy, ub = s
            # I-step: argmin ||D I - (g + z_g - u_g)||^2 + alpha ||I - (I_b + z_b - u_b)||^2, exactly.
            tb = b_img + zb - ub
            gxb, gyb = gradient(tb)
            x = tb + _dct_solve(gradient_adjoint(gx_t + zx - ux - gxb, gy_t + zy - uy - gyb), alpha)
            gx, gy = gradient(x)
            ax = relax * (gx - gx_t) + (1 - relax) * zx
            ay = relax * (gy - gy_t) + (1 - relax) * zy
            ab = relax * (x - b_img) + (1 - relax) * zb
            zx_n, zy_n, zb_n = _shrink(ax + ux, thr), _shrink(ay + uy, thr), _shrink(ab + ub, thr)
            return x, zx_n, zy_n, zb_n, ux + ax - zx_n, uy + ay - zy_n, ub + ab - zb_n

        return jax.lax.fori_loop(0, iters, body, (x, zx, zy, zb, zeros, zeros, zeros))[0]

    return _per_channel(one, base, gx_t, gy_t, x0, zx, zy)


# -- L1: ADMM with a clamped-data warm start and penalty continuation ------------------------------

def _abs(x):
    """``|x|`` as a select: XLA's CPU backend (jax 0.10) runs a sum over ``abs(x)`` (or ``minimum``) about
    10x slower than the same sum over a select, measured at 640x360x3 (4.7 vs 0.8 ms)."""
    return jnp.where(x < 0, -x, x)


def _robust_scale(blocks, rounds: int = 5, samples: int = 1 << 15):
    """Winsorized mean absolute value of the valid entries of ``blocks`` (pairs ``(kind, array)`` with kind
    ``'x'`` / ``'y'`` for (H, W, 1) gradient planes, whose last column / row is ignored and zero, or
    ``'b'`` for a pixel plane): ``s <- mean(min(|r|, 3 s))`` from the plain mean, ``rounds`` times. A few
    huge outliers move the plain mean by their sum / count; after the rounds they count at most 3 s each.

    Estimated on every ``stride``-th row and column, ``stride`` the largest keeping >= ``samples``
    pixels (2 at 1280x720 is 3): a scale needs no more, and each round is a pass over the data."""
    h, w = blocks[0][1].shape[:2]
    stride = max(1, int(np.sqrt(h * w / samples)))
    rows, cols = np.arange(0, h, stride), np.arange(0, w, stride)
    valid = {"x": len(rows) * int(np.sum(cols < w - 1)), "y": int(np.sum(rows < h - 1)) * len(cols),
             "b": len(rows) * len(cols)}
    count = max(sum(valid[k] for k, _ in blocks), 1)
    mags = [_abs(a[::stride, ::stride]) for _, a in blocks]
    s = sum(jnp.sum(m) for m in mags) / count
    for _ in range(rounds):
        c = 3 * s
        s = sum(jnp.sum(jnp.where(m < c, m, c)) for m in mags) / count
    return s


# Defaults of `poisson_l1_radmm`, fixed by the scans in docs/methods/poisson.md.
RADMM_ITERS = 40
_RADMM_CONTINUATION = (3.0, 0.05, 8.0)   # thresholds t_k = s (t_end + (t_start - t_end) exp(-k / decay))


def poisson_l1_radmm(base, dx, dy, alpha, *, iters: int = RADMM_ITERS, relax: float = 1.6, clamp: float = 8.0,
                     continuation: tuple[float, float, float] = _RADMM_CONTINUATION):
    """L1 reconstruction (Eq. 1, p = 1; Guo et al. 2019 Sec. 3) by ADMM with the exact DCT step, a
    clamped-data warm start and a decreasing penalty: the fast, converged L1 solver.

    **Iteration.** The split of `poisson_l1_admm` (``z_g = D I - g``, ``z_b = I - I_b``, penalties ``rho``
    and ``alpha rho``, so the I-step is ``(alpha 1 + D^T D)^{-1}`` by the DCT for any rho), written as
    over-relaxed Douglas-Rachford splitting on the single state ``v = z + u`` (the relaxed ADMM of
    Eckstein & Bertsekas 1992, "On the Douglas-Rachford splitting method and the proximal point algorithm";
    Boyd et al. 2011 Sec. 3.4.3): with ``t = 1 / rho`` and ``S_t`` soft thresholding, per iteration::

        z = S_t(v);   I = argmin ||D I - g - (2 z_g - v_g)||^2 + alpha ||I - I_b - (2 z_b - v_b)||^2;
        v <- v + relax (K I - c - z),          K I - c = (D I - g, I - I_b).

    One DCT solve (one ``rfft2`` + one ``irfft2``) and the elementwise work around it per iteration (about
    1.2-1.4 times an L2 solve, measured); the state is three planes per channel (ADMM's (z, u) is six).

    **Penalty continuation** (He, Yang & Wang 2000, "Alternating direction method with self-adaptive
    penalty parameters for monotone variational inequalities": ADMM converges when the relative changes of
    the penalty are summable, as they are for this schedule): ``t_k = s (t_end + (t_start - t_end)
    exp(-k / decay))`` with
    ``continuation = (t_start, t_end, decay) = (3, 0.05, 8)`` and ``s`` a robust scale (`_robust_scale`,
    per channel) of the warm start's gradient residuals against the clamped data, but at least a tenth of
    the L2 solution's (on consistent data with a few outliers the warm start leaves almost no residual,
    and thresholds that small could not undo a clamp that crossed the minimizer): large thresholds move
    the image far per iteration early, small ones converge fast at the end. The scaled dual ``u = v - z``
    is rescaled by ``t_k / t_{k-1}`` when t changes (the unscaled multiplier ``u / t`` carries over).

    **Warm start.** ADMM moves a residual by about ``t`` per iteration, so an L2 start that spreads a
    huge outlier (a firefly in ``I_b``, a wrong gradient) into a bump of size A needs ~A / t iterations
    (measured: no convergence in 200 iterations on heavy-tailed gradients). The warm start removes such
    bumps: a robust predictor of the data, ``P = (D M, M)`` with ``M`` the 3x3 median of ``I_b``, and the
    deviation ``e = c - P`` of each datum from it with robust scale ``s_e`` (per block: gradients, base).
    Where the L2 solution also misfits the datum by more than ``s_e``, the datum is clamped to
    ``P + clip(e, +-clamp s_e)``; the warm start is the exact L2 solve on the clamped data. The iteration
    then runs on the *original* data from ``v = K I_0 - c``: moving a datum towards the L1 minimizer
    without crossing it does not change the minimizer (the optimality conditions only read the residuals'
    signs), and where a clamp did cross, the iteration corrects it. The L2 gate keeps consistent data
    untouched (exact gradients return the base).

    Returns the I-step iterate after ``iters`` iterations (static). Numerical guards: the DC mode of each
    I-step is exact (`_dct_solve`); the scales are floored at ``1e-6`` of the data's mean magnitude (an
    all-black or exactly consistent frame has no residual scale) and carry no gradient. Differentiable
    through the unrolled iterations.
    """
    base, dx, dy = _check_images("poisson_l1_radmm", base=base, dx=dx, dy=dy)
    alpha = _check_alpha("poisson_l1_radmm", alpha, base.dtype)
    _check_iters("poisson_l1_radmm", iters=iters)
    if not 0 < relax < 2:
        raise SolverError(f"poisson_l1_radmm: argument 'relax' is {relax}; expected in (0, 2)")
    if not (np.ndim(clamp) == 0 and np.isfinite(float(clamp)) and float(clamp) > 0):
        raise SolverError(f"poisson_l1_radmm: argument 'clamp' is {clamp!r}; expected a finite scalar > 0")
    cont = tuple(float(c) for c in np.ravel(continuation))
    if len(cont) != 3 or not all(np.isfinite(c) and c > 0 for c in cont):
        raise SolverError(f"poisson_l1_radmm: argument 'continuation' is {continuation!r}; expected "
                          "(t_start, t_end, decay), three finite scalars > 0")
    return _l1_radmm(base, dx, dy, alpha, iters=iters, relax=float(relax), clamp=float(clamp), continuation=cont)


@functools.partial(jax.jit, static_argnames=("iters", "relax", "clamp", "continuation"))
def _l1_radmm(base, dx, dy, alpha, *, iters, relax, clamp, continuation):
    t_start, t_end, decay = continuation
    # thresholds relative to s, one per iteration (constants of the program), and their ratios
    fac = t_end + (t_start - t_end) * np.exp(-np.arange(max(iters, 1)) / decay)
    prev = np.concatenate([fac[:1], fac[:-1]])            # the threshold of the iteration before
    ratio = fac / prev
    dt = base.dtype
    gx_t, gy_t = _mask(dx, dy)
    x_l2 = _l2_dct(base, gx_t, gy_t, alpha)
    h, w = base.shape[:2]
    n_g = h * (w - 1) + (h - 1) * w

    def one(b_img, gx_t, gy_t, x_l2):
        floor = 1e-6 * (jnp.mean(_abs(b_img)) + (jnp.sum(_abs(gx_t)) + jnp.sum(_abs(gy_t))) / max(n_g, 1))
        floor = floor + jnp.finfo(dt).tiny
        # -- warm start: clamp the data that both the median predictor and the L2 fit call outliers
        med = median9(edge_views(b_img, 1))  # 3x3 median, border replicated
        px, py = gradient(med)
        ex, ey, eb = gx_t - px, gy_t - py, b_img - med          # ex, ey: zero on the ignored entries
        s_g = jax.lax.stop_gradient(jnp.maximum(_robust_scale((("x", ex), ("y", ey))), floor))
        s_b = jax.lax.stop_gradient(jnp.maximum(_robust_scale((("b", eb),)), floor))
        gx2, gy2 = gradient(x_l2)
        rx, ry, rb = gx2 - gx_t, gy2 - gy_t, x_l2 - b_img

        def clamped(e, r, s):
            return jnp.where(jnp.abs(r) > s, jnp.clip(e, -clamp * s, clamp * s), e)

        gx_c, gy_c, b_c = px + clamped(ex, rx, s_g), py + clamped(ey, ry, s_g), med + clamped(eb, rb, s_b)
        gcx, gcy = gradient(b_c)
        x = b_c + _dct_solve(gradient_adjoint(gx_c - gcx, gy_c - gcy), alpha)
        gx0, gy0 = gradient(x)
        vx, vy, vb = gx0 - gx_t, gy0 - gy_t, x - b_img        # v = K I_0 - c on the original data
        # threshold scale: the warm start's gradient residuals against the clamped data, but at least a
        # tenth of the L2 solution's (nearly consistent data with a few outliers leave the warm start
        # almost no residual, and thresholds that small cannot undo a clamp that crossed the minimizer)
        s_warm = _robust_scale((("x", gx0 - gx_c), ("y", gy0 - gy_c)))
        s_l2 = _robust_scale((("x", rx), ("y", ry)))
        s = jax.lax.stop_gradient(jnp.maximum(jnp.maximum(s_warm, 0.1 * s_l2), floor))
        prev_j, ratio_j = jnp.asarray(prev, dt), jnp.asarray(ratio, dt)

        def body(k, state):
            # With z = S_t'(v) and u = v - z = clip(v, +-t') at the previous threshold t', the rescaled
            # state is v' = z + q u (q = t / t') and S_t(v') = z: one clip per block does both.
            vx, vy, vb, _ = state
            t_prev, q = s * prev_j[k], ratio_j[k]
            ux, uy, ub = (jnp.clip(v, -t_prev, t_prev) for v in (vx, vy, vb))
            # I-step towards c + 2 S_t(v') - v' = c + z - q u
            y = b_img + vb - (1 + q) * ub
            gyx, gyy = gradient(y)
            x = y + _dct_solve(gradient_adjoint(gx_t + vx - (1 + q) * ux - gyx, gy_t + vy - (1 + q) * uy - gyy),
                               alpha)
            gx, gy = gradient(x)
            # v <- v' + relax (K I - c - z)
            return (vx + (q - 1) * ux + relax * (gx - gx_t - vx + ux),
                    vy + (q - 1) * uy + relax * (gy - gy_t - vy + uy),
                    vb + (q - 1) * ub + relax * (x - b_img - vb + ub), x)

        return jax.lax.fori_loop(0, iters, body, (vx, vy, vb, x))[3]

    return _per_channel(one, base, gx_t, gy_t, x_l2)
