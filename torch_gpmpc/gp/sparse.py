"""Sparse residual GPs for large logs: inducing points and the SGPR posterior (Titsias, 2009).

An exact GP costs O(N^3) to fit and O(N) per prediction; a real log has thousands of rows.
For large N the package fits the hyperparameters by exact marginal likelihood on a seeded
uniform subset of the rows (GPyTorch's exact GP, as for small data), places M inducing
points by k-means on all standardized inputs, and conditions on **all** rows through the
SGPR posterior with those inducing points (one O(N M^2) factorization)::

    Sigma   = (K_uu + s^-2 K_uf K_fu)^-1
    mean(x) = s^-2 k_xu Sigma K_uf y                      = k_xu alpha
    var(x)  = k_xx - k_xu K_uu^-1 k_ux + k_xu Sigma k_ux   (latent; + s^2 for a measurement)

(the variational posterior of Titsias 2009, which GPyTorch's ``InducingPointKernel`` (SGPR)
also uses; its predictive variance leaves out the Nystrom term ``k_xx - k_xu K_uu^-1 k_ux``,
which we keep: it is what makes the variance grow away from the inducing points.)

Numerically, with ``L_uu L_uu^T = K_uu`` and ``L_B L_B^T = I + A A^T``, ``A = L_uu^-1 K_uf / s``,
the factor of ``Sigma^-1`` is ``L_uu L_B``: prediction then has the form of the exact GP's
(:mod:`~torch_gpmpc.gp.cache`) with the inducing points as support points, so
``ResidualGP.linearize`` serves both at O(M) per point.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.gp.cache import safe_cholesky, squared_distances

#: Training rows above which ``method="auto"`` fits the sparse model (an exact fit of 1000
#: rows and 3 outputs takes about 30 s on a 2-core CPU).
EXACT_MAX_POINTS = 1000
#: Rows of the seeded subset the hyperparameters are fitted on.
HYPERPARAMETER_SUBSET = 600
#: Inducing points.
NUM_INDUCING = 512
#: Lloyd iterations of the k-means placement.
KMEANS_ITERS = 10


@dataclass
class SparsePosterior:
    """The SGPR posterior in standardized units (shapes: D outputs, M inducing points).

    Attributes:
        chol_uu: (D, M, M) lower factor of ``K_uu``.
        chol_sigma: (D, M, M) lower factor of ``Sigma^-1 = K_uu + s^-2 K_uf K_fu``.
        alpha: (D, M) ``s^-2 Sigma K_uf y``.
    """

    chol_uu: Tensor
    chol_sigma: Tensor
    alpha: Tensor


def kmeans_centers(z: Tensor, num: int, seed: int, iters: int = KMEANS_ITERS) -> Tensor:
    """``num`` k-means centres of the rows of ``z`` (N, Din), started at a seeded subset.

    Returns:
        (min(num, N), Din) centres; a centre that loses all its points stays where it was.
    """
    num = min(int(num), z.shape[0])
    gen = torch.Generator().manual_seed(int(seed))
    centres = z[torch.randperm(z.shape[0], generator=gen)[:num]].clone()
    for _ in range(iters):
        label = torch.cdist(z, centres).argmin(dim=1)
        sums = torch.zeros_like(centres).index_add_(0, label, z)
        counts = torch.bincount(label, minlength=num).to(z.dtype)
        moved = counts > 0
        centres[moved] = sums[moved] / counts[moved, None]
    return centres


def sparse_posterior(S_u: Tensor, S_f: Tensor, ys: Tensor, outputscale: Tensor, noise: Tensor) -> SparsePosterior:
    """Factor the SGPR posterior (module docstring).

    Args:
        S_u: (D, M, Din) inducing points over the lengthscales (standardized inputs / l).
        S_f: (D, N, Din) training inputs over the lengthscales.
        ys: (D, N) standardized targets.
        outputscale: (D,) signal variances; noise: (D,) noise variances (standardized).
    """
    os_ = outputscale[:, None, None]
    K_uu = os_ * torch.exp(-0.5 * squared_distances(S_u, S_u))
    K_uf = os_ * torch.exp(-0.5 * squared_distances(S_u, S_f))
    chol_uu = safe_cholesky(K_uu, outputscale)
    A = torch.linalg.solve_triangular(chol_uu, K_uf, upper=False) / noise.sqrt()[:, None, None]
    eye = torch.eye(S_u.shape[1], dtype=S_u.dtype)
    chol_b = safe_cholesky(eye + A @ A.mT, torch.ones_like(outputscale))
    c = torch.linalg.solve_triangular(chol_b, A @ (ys / noise.sqrt()[:, None]).unsqueeze(-1), upper=False)
    alpha = torch.linalg.solve_triangular(chol_uu.mT, torch.linalg.solve_triangular(chol_b.mT, c, upper=True),
                                          upper=True).squeeze(-1)
    return SparsePosterior(chol_uu, chol_uu @ chol_b, alpha)
