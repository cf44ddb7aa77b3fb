"""`poisson-l2` / `poisson-l1`: classical screened-Poisson reconstruction of gradient-domain renders.

Guo et al. 2019, Sec. 3, Eq. 1 (after Lehtinen et al. 2013, Kettunen et al. 2015): the image whose
finite differences best match the rendered gradients ``dx``/``dy`` while staying close to the
rendered base image ``color``, in the L2 or L1 norm, per colour channel. Solvers, conventions
(boundary, norms, alpha) and measurements: `jaxdenoise.solvers.poisson`, ``docs/methods/poisson.md``,
``docs/results/poisson.md``. Not trainable (no ``loss``).
"""
from __future__ import annotations

import dataclasses


from ..buffers import Buffers, map_frames
from ..solvers import poisson as _sp
from ..errors import JaxdenoiseError

_SOLVERS = {"l2": ("dct", "cg"), "l1": ("radmm", "irls", "admm")}  # first = default (docs/methods/poisson.md)


@dataclasses.dataclass(frozen=True)
class Config:
    alpha: float = 0.2        # weight of the base term (Lehtinen 2013 / Kettunen 2015 presets use 0.2)
    norm: str = "l2"          # 'l2' | 'l1' (Guo 2019 Eq. 1, p = 2 or 1)
    solver: str | None = None  # l2: 'dct' (exact, default) | 'cg'; l1: 'radmm' (default) | 'irls' | 'admm'
    cg_iters: int = 1000      # 'cg': max iterations of the L2 CG (tolerance 1e-6 relative)
    irls_iters: int = 20      # 'irls': reweighting rounds (the common 20 x 50 preset)
    irls_cg_iters: int = 50   # 'irls': CG iterations per round
    admm_iters: int = 100     # 'admm': iterations (L1 energy within ~0.1% of its minimum, results doc)
    radmm_iters: int = _sp.RADMM_ITERS  # 'radmm': iterations (40: energy gap 7e-4 at 1280x720, results doc)

    def __post_init__(self) -> None:
        if self.norm not in _SOLVERS:
            raise JaxdenoiseError(f"poisson Config: 'norm' is {self.norm!r}; expected 'l1' or 'l2'")
        if self.solver is not None and self.solver not in _SOLVERS[self.norm]:
            raise JaxdenoiseError(f"poisson Config: 'solver' is {self.solver!r}; expected one of "
                             f"{_SOLVERS[self.norm]} for norm {self.norm!r}")
        if not (self.alpha > 0):
            raise JaxdenoiseError(f"poisson Config: 'alpha' is {self.alpha}; expected > 0")

    @property
    def resolved_solver(self) -> str:
        return self.solver or _SOLVERS[self.norm][0]


def needs(config: Config) -> frozenset[str]:
    return frozenset({"color", "dx", "dy"})


def init(key, config: Config) -> dict:
    return {}


def _solve(base, dx, dy, config: Config):
    s = config.resolved_solver
    if s == "dct":
        return _sp.poisson_l2_dct(base, dx, dy, config.alpha)
    if s == "cg":
        return _sp.poisson_l2_cg(base, dx, dy, config.alpha, maxiter=config.cg_iters)
    if s == "irls":
        return _sp.poisson_l1_irls(base, dx, dy, config.alpha, irls_iters=config.irls_iters,
                                   cg_iters=config.irls_cg_iters)
    if s == "radmm":
        return _sp.poisson_l1_radmm(base, dx, dy, config.alpha, iters=config.radmm_iters)
    return _sp.poisson_l1_admm(base, dx, dy, config.alpha, iters=config.admm_iters)


def _frame(b: Buffers, config: Config):
    # Where dx, dy leave the directly seen emission out (Kettunen et al. 2015's tracer), the solve is
    # for ``color - emission`` and the emission is added back.
    if b.emission is None:
        return _solve(b.color, b.dx, b.dy, config)
    return _solve(b.color - b.emission, b.dx, b.dy, config) + b.emission


def apply(params: dict, buffers: Buffers, config: Config):
    """Reconstruct from ``color`` (the base image) and ``dx``/``dy``; a batch (leading axes) of
    independent frames is solved frame by frame. A frame with an ``emission`` layer (its gradients
    leave the directly seen emission out) is solved for ``color - emission``, which is added back."""
    buffers.check_needs(needs(config), "poisson-" + config.norm)
    return map_frames(lambda b: _frame(b, config), buffers)
