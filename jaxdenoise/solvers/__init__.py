"""Screened-Poisson solvers and pure optimizers (docs/architecture.md "Layout": solvers/).

This package is the only place in jaxdenoise that imports jaxopt.
"""
from .dct import dct2, idct2, laplacian_eigenvalues
from .optim import adam, rprop
from .poisson import (
    SolverError,
    energy,
    gradient,
    gradient_adjoint,
    normal_matvec,
    poisson_l1_admm,
    poisson_l1_irls,
    poisson_l1_radmm,
    poisson_l2_cg,
    poisson_l2_dct,
    residual,
)

__all__ = [
    "SolverError", "adam", "dct2", "energy", "gradient", "gradient_adjoint", "idct2",
    "laplacian_eigenvalues", "normal_matvec", "poisson_l1_admm", "poisson_l1_irls", "poisson_l1_radmm",
    "poisson_l2_cg", "poisson_l2_dct", "residual", "rprop",
]
