"""Residual Gaussian process: one independent GP per state dimension (paper §2.1).

For each output dimension d the residual ``y_d = [x' - f(x, u)]_d`` is modelled by a
zero-mean GP with a squared-exponential ARD kernel (paper eq. 3-4)::

    kappa_d(a, b) = sigma_d^2 exp(-1/2 (a - b)^T L_d^{-1} (a - b)),   L_d = diag(l_{d,1}^2, ...)
    mu_d(x)       = k_d(x)^T (K_d + s_d^2 I)^{-1} Y_d                               (eq. 3)
    var_d(x)      = kappa_d(x, x) - k_d(x)^T (K_d + s_d^2 I)^{-1} k_d(x)            (eq. 4)
    d mu_d / dx   = sum_n kappa_d(x, xi_n) L_d^{-1} (xi_n - x) alpha_{d,n}          (eq. 13)

Internally inputs are standardized per input dimension and outputs per output
dimension (the standardized GP is fitted by GPyTorch: ``ExactGP`` with
``batch_shape=[D]``, ``ZeroMean``, ``ScaleKernel(RBFKernel(ard))``,
``GaussianLikelihood`` with learned noise). This is exactly a GP in raw units whose
prior mean is the empirical mean of ``y`` and whose hyperparameters are the raw-unit
values reported by :attr:`ResidualGP.lengthscales`, :attr:`ResidualGP.outputscales`
and :attr:`ResidualGP.noise`. Users pass raw units and get raw units back.

The model caches (:mod:`~torch_gpmpc.gp.cache`) the Cholesky factor of ``K_d + s_d^2 I``
and ``alpha_d = (K_d + s_d^2 I)^{-1} Y_d``, rebuilt whenever a hyperparameter changes (every
prediction compares them with the cached ones, as GPyTorch clears its prediction strategy);
:meth:`ResidualGP.linearize` then evaluates mean, Jacobian and variance for a batch of points
with a few batched torch ops (no GPyTorch predictive machinery), because the controller calls
it every control step. Gradients to the hyperparameters are opt-in
(:meth:`ResidualGP.enable_hyperparameter_gradients`). With ``inducing_points`` the same model is the sparse (SGPR) posterior of
:mod:`~torch_gpmpc.gp.sparse`, served by the same code with the inducing points as the
support points.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any, Sequence

import gpytorch
import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.cache import (
    PredictionCache, cross_covariances, explained_variance, latent_variance, mean_and_jacobian, parameter_values,
    posterior_mean, raw_mean, safe_cholesky, squared_distances,
)
from torch_gpmpc.gp.gpytorch_models import GPyTorchResidual
from torch_gpmpc.gp.io import FORMAT, VERSION, read_payload, verify_checksum, write_payload
from torch_gpmpc.gp.normalization import Standardization
from torch_gpmpc.gp.protocol import PlanningGP, evaluates_as
from torch_gpmpc.gp.sparse import sparse_posterior

log = logging.getLogger(__name__)

#: What a GP's inputs are: the state (the paper) or the state and the input.
GP_INPUTS = ("state", "state_input")
#: GPyTorch switches to iterative solvers above this size; we always want Cholesky.
MAX_CHOLESKY_SIZE = 1_000_000
#: Standardized initial hyperparameters (inputs and outputs have unit variance).
_INIT = {"lengthscale": 1.0, "outputscale": 1.0, "noise": 0.1}


class _BatchExactGP(gpytorch.models.ExactGP):
    """D independent exact GPs on standardized data (GPyTorch batch mode).

    Args:
        train_x: standardized inputs, shape (D, N, Din) (the same points for every d).
        train_y: standardized targets, shape (D, N).
        likelihood: ``GaussianLikelihood(batch_shape=[D])``.
    """

    def __init__(self, train_x: Tensor, train_y: Tensor, likelihood: gpytorch.likelihoods.GaussianLikelihood):
        super().__init__(train_x, train_y, likelihood)
        batch = torch.Size([train_y.shape[0]])
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=batch)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            gpytorch.kernels.RBFKernel(ard_num_dims=train_x.shape[-1], batch_shape=batch),
            batch_shape=batch,
        )

    def forward(self, x: Tensor) -> gpytorch.distributions.MultivariateNormal:
        """Prior at standardized inputs ``x`` of shape (D, n, Din); batch MVN (D, n)."""
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


class ResidualGP(torch.nn.Module):
    """Residual GP ``x -> y`` with D independent outputs (one GP per state dimension).

    Build it with :func:`fit_residual_gp`; evaluate with :meth:`predict`,
    :meth:`mean_jacobian` or (fastest, all at once) :meth:`linearize`. Each agent of
    the multi-agent controller owns one instance (the
    :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol). Bring your own GPyTorch
    models with :meth:`from_gpytorch`.

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ResidualGP
        >>> x = torch.linspace(-3, 3, 30, dtype=torch.float64)[:, None]
        >>> gp = ResidualGP(x, torch.sin(x))          # hyperparameters at their initial values
        >>> mean, jac, var = gp.linearize(torch.zeros(1, 1, dtype=torch.float64))
        >>> round(float(mean), 3), round(float(jac), 3), round(float(var), 4)
        (0.0, 0.99, 0.0063)
        >>> gp.model.covar_module.base_kernel.lengthscale = 0.2   # the cache follows
        >>> round(float(gp.linearize(torch.zeros(1, 1, dtype=torch.float64))[2]), 4)
        0.0251

    Args:
        inputs: raw training inputs, shape (N, Din).
        y: raw training targets (residuals), shape (N, D).
        gp_inputs: what the inputs are: ``"state"`` (Din = D, the paper) or
            ``"state_input"`` (Din = D + Du). Stored in the model file.
        normalization: the :class:`~torch_gpmpc.gp.normalization.Standardization` to use;
            computed from the data when ``None``.
        inducing_points: raw inducing inputs, shape (M, Din): the sparse (SGPR) posterior on
            all N rows (:mod:`~torch_gpmpc.gp.sparse`); ``None``: the exact GP.

    Attributes:
        model: the GPyTorch ``ExactGP`` on standardized data (batch_shape [D]).
        likelihood: its ``GaussianLikelihood`` (batch_shape [D]).
    """

    def __init__(self, inputs: Tensor, y: Tensor, gp_inputs: str = "state",
                 normalization: Standardization | None = None, inducing_points: Tensor | None = None):
        super().__init__()
        inputs, y = check_training_data(inputs, y)
        self.inducing_points = _check_inducing(inducing_points, inputs.shape[1])
        if gp_inputs not in GP_INPUTS and not _is_column_list(gp_inputs):
            raise GpmpcError(f"gp_inputs must be one of {GP_INPUTS} or model columns such as 'x3,x4,u0', "
                             f"got {gp_inputs!r}")
        self.gp_inputs = gp_inputs
        self.train_inputs_raw = inputs
        self.train_y_raw = y
        s = self.standardization = normalization or Standardization.from_data(inputs, y)
        self.x_mean, self.x_std, self.y_mean, self.y_std = s.x_mean, s.x_std, s.y_mean, s.y_std
        D, (N, Din) = y.shape[1], inputs.shape
        z = s.inputs(inputs).expand(D, N, Din)
        ys = s.outputs(y).T.contiguous()
        self.likelihood = gpytorch.likelihoods.GaussianLikelihood(batch_shape=torch.Size([D]))
        self.model = _BatchExactGP(z, ys, self.likelihood)
        self.model.covar_module.base_kernel.lengthscale = _INIT["lengthscale"]
        self.model.covar_module.outputscale = _INIT["outputscale"]
        self.likelihood.noise = _INIT["noise"]
        self._cache: PredictionCache | None = None
        self._cache_key: Tensor | None = None
        #: whether predictions carry gradients to the hyperparameters (opt in with
        #: :meth:`enable_hyperparameter_gradients`)
        self.hyperparameter_gradients = False
        #: the model state rows the GP's outputs are the residuals of (``"x2,x3"``: a double
        #: integrator's velocities), set by the fits that know the model; stored in the model file and
        #: checked when a run loads it (:func:`~torch_gpmpc.gp.fit.load_model_gp`). ``None``: unknown.
        self.residual_rows: str | None = None

    @classmethod
    def from_gpytorch(cls, models: Sequence[Any], likelihoods: Sequence[Any]) -> GPyTorchResidual:
        """Wrap a user's own GPyTorch exact GPs, one model and one ``GaussianLikelihood`` per
        residual row (any mean and kernel), as an agent's residual model for the controller.

        Returns a :class:`~torch_gpmpc.gp.gpytorch_models.GPyTorchResidual` (the
        :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol; see its example).
        """
        return GPyTorchResidual(models, likelihoods)

    # ------------------------------------------------------------------ sizes
    @property
    def input_dim(self) -> int:
        """Din."""
        return int(self.train_inputs_raw.shape[1])

    @property
    def output_dim(self) -> int:
        """D."""
        return int(self.train_y_raw.shape[1])

    @property
    def num_data(self) -> int:
        """N."""
        return int(self.train_inputs_raw.shape[0])

    @property
    def method(self) -> str:
        """``exact`` or ``sgpr`` (the sparse posterior on inducing points)."""
        return "exact" if self.inducing_points is None else "sgpr"

    # ------------------------------------------------------------------ hyperparameters
    @property
    def lengthscales(self) -> Tensor:
        """ARD length-scales l_{d,i} in raw input units, shape (D, Din)."""
        ls = self.model.covar_module.base_kernel.lengthscale.detach()
        return ls.reshape(self.output_dim, self.input_dim) * self.x_std

    @property
    def outputscales(self) -> Tensor:
        """Signal variances sigma_d^2 in raw output units squared, shape (D,)."""
        return self.model.covar_module.outputscale.detach() * self.y_std ** 2

    @property
    def noise(self) -> Tensor:
        """Observation-noise variances s_d^2 in raw output units squared, shape (D,) (with
        gradients to the noise hyperparameter when they are opted in)."""
        noise = self.likelihood.noise.reshape(self.output_dim)
        if not self.hyperparameter_gradients:
            noise = noise.detach()
        return noise * self.y_std ** 2

    def hyperparameters(self) -> dict[str, Any]:
        """Raw-unit hyperparameters as plain floats/lists (for logging and summaries)."""
        return {
            "lengthscale": self.lengthscales.tolist(),
            "outputscale": self.outputscales.tolist(),
            "noise": self.noise.tolist(),
            "input_dim": self.input_dim,
            "output_dim": self.output_dim,
            "num_data": self.num_data,
            "gp_inputs": self.gp_inputs,
            "method": self.method,
            "num_inducing": 0 if self.inducing_points is None else int(self.inducing_points.shape[0]),
        }

    # ------------------------------------------------------------------ cache
    def refresh(self) -> "ResidualGP":
        """Recompute the prediction cache from the current hyperparameters.

        Not needed after changing hyperparameters: every prediction checks them and rebuilds
        the cache when they changed. Also resets GPyTorch's own caches.

        Raises:
            GpmpcError: if ``K + s^2 I`` is not positive definite even with jitter.
        """
        self.model.eval()
        self.likelihood.eval()
        self.model.prediction_strategy = None
        with torch.no_grad():
            self._cache = self._build_cache()
        self._cache_key = parameter_values(self.model)
        return self

    def prediction_cache(self) -> PredictionCache:
        """The prediction cache of the current rows and hyperparameters (built if needed)."""
        return self._get_cache()

    def set_rows(self, inputs: Tensor, y: Tensor, cache: PredictionCache | None = None) -> "ResidualGP":
        """Replace the training rows (raw units, (N, Din) and (N, D)); the standardization, the
        hyperparameters and the inducing points stay.

        Args:
            cache: the factorization of exactly these rows at the current hyperparameters (an online
                update, :mod:`~torch_gpmpc.gp.online`); ``None``: rebuilt on the next prediction.
        """
        inputs, y = check_training_data(inputs, y)
        self.train_inputs_raw, self.train_y_raw = inputs, y
        s = self.standardization
        z = s.inputs(inputs).expand(self.output_dim, *inputs.shape)
        self.model.set_train_data(z, s.outputs(y).T.contiguous(), strict=False)
        self.model.prediction_strategy = None
        self._cache = cache
        self._cache_key = None if cache is None else parameter_values(self.model)
        return self

    def enable_hyperparameter_gradients(self, enabled: bool = True) -> "ResidualGP":
        """Opt in (or out) of gradients from :meth:`predict` / :meth:`linearize` to the
        hyperparameters (lengthscales, outputscales, noise). While enabled and autograd is on,
        each call rebuilds the factorization inside the graph (an O(N^3) Cholesky per call)."""
        self.hyperparameter_gradients = bool(enabled)
        return self

    def _build_cache(self) -> PredictionCache:
        """The cache at the current hyperparameters (inside the autograd graph when enabled)."""
        D, Din = self.output_dim, self.input_dim
        ls = self.model.covar_module.base_kernel.lengthscale.reshape(D, 1, Din)
        outputscale = self.model.covar_module.outputscale.reshape(D)
        noise = self.likelihood.noise.reshape(D)
        S_f = ((self.train_inputs_raw - self.x_mean) / self.x_std) / ls
        ys = ((self.train_y_raw - self.y_mean) / self.y_std).T
        chol_add = None
        if self.inducing_points is None:
            S = S_f
            K = outputscale[:, None, None] * torch.exp(-0.5 * squared_distances(S, S))
            K = K + noise[:, None, None] * torch.eye(self.num_data, dtype=K.dtype)
            chol = safe_cholesky(K, outputscale.detach())
            alpha = torch.cholesky_solve(ys.unsqueeze(-1), chol).squeeze(-1)
        else:
            S = ((self.inducing_points - self.x_mean) / self.x_std) / ls
            post = sparse_posterior(S, S_f, ys, outputscale, noise)
            chol, chol_add, alpha = post.chol_uu, post.chol_sigma, post.alpha
        S_cols = tuple(S[:, None, :, i].contiguous() for i in range(Din))
        return PredictionCache(self.x_mean, self.x_std, ls, self.x_std * ls, S, S_cols, outputscale, chol, alpha,
                               self.y_mean, self.y_std, noise * self.y_std ** 2, chol_add)

    def _get_cache(self) -> PredictionCache:
        """The prediction cache, rebuilt when a hyperparameter changed since it was built (the
        check compares a few numbers); built in the autograd graph with gradients opted in."""
        if getattr(self, "hyperparameter_gradients", False) and torch.is_grad_enabled():
            return self._build_cache()
        if self._cache is None or not torch.equal(self._cache_key, parameter_values(self.model)):
            self.refresh()
        return self._cache

    def _cross(self, x: Tensor) -> tuple[PredictionCache, Tensor, Tensor]:
        """Scaled query points s (D, n, Din) and cross-covariances k (D, n, N)."""
        c = self._get_cache()
        s, k = cross_covariances(c, self.check_query(x))
        return c, s, k

    def check_query(self, x: Tensor) -> Tensor:
        """Query points x (n, Din) as float64.

        Raises:
            GpmpcError: naming the expected shape, for anything else.
        """
        if not isinstance(x, Tensor) or x.ndim != 2 or x.shape[1] != self.input_dim:
            shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise GpmpcError(f"GP query points must have shape (n, {self.input_dim}) "
                             f"({self.gp_inputs} inputs), got {shape}")
        return x.to(torch.float64)

    # ------------------------------------------------------------------ predictions
    def predict(self, x: Tensor, include_noise: bool = False) -> tuple[Tensor, Tensor]:
        """Posterior mean and marginal variance (paper eq. 3-6).

        Args:
            x: query inputs, shape (n, Din), raw units.
            include_noise: add the observation noise s_d^2 (predictive variance of a
                new measurement) instead of the latent variance of eq. 4.

        Returns:
            ``(mean (n, D), var (n, D))`` in raw units.
        """
        c, _, k = self._cross(x)
        mean = raw_mean(c, posterior_mean(c, k))  # the same operations as linearize's mean
        var = latent_variance(c, *explained_variance(c, k))
        if include_noise:
            var = var + c.noise_raw
        return mean, var

    def mean_jacobian(self, x: Tensor) -> Tensor:
        """Closed-form Jacobian of the posterior mean (paper eq. 13, with standardization).

        Args:
            x: query inputs, shape (n, Din), raw units.

        Returns:
            ``J`` of shape (n, D, Din) with ``J[j, d, i] = d mu_d / d x_i`` at ``x[j]``.
        """
        c, s, k = self._cross(x)
        return mean_and_jacobian(c, s, k)[1]

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Mean, mean Jacobian and latent variance at ``x`` in one call.

        Equals ``predict(x)`` and ``mean_jacobian(x)``; differentiable w.r.t. ``x``. A team's models
        at once: :func:`~torch_gpmpc.gp.batch.linearize_models` (the same bits).

        Args:
            x: linearization points, shape (n, Din), raw units.

        Returns:
            ``(mean (n, D), jac (n, D, Din), var (n, D))`` in raw units.
        """
        c, s, k = self._cross(x)
        mean, jac = mean_and_jacobian(c, s, k)
        return mean, jac, latent_variance(c, *explained_variance(c, k))

    def planning_gp(self) -> PlanningGP | None:
        """This model for a team's batched evaluation (:mod:`~torch_gpmpc.gp.batch`); ``None`` while
        its predictions carry gradients to the hyperparameters (each call builds its own graph), and for
        a subclass that predicts otherwise."""
        if (self.hyperparameter_gradients and torch.is_grad_enabled()) or not evaluates_as(self, ResidualGP):
            return None
        return PlanningGP(self)

    def gpytorch_predict(self, x: Tensor, include_noise: bool = False) -> tuple[Tensor, Tensor]:
        """The same prediction through GPyTorch's own predictive path (reference/baseline).

        Args:
            x: query inputs, shape (n, Din), raw units.
            include_noise: pass the posterior through the likelihood.

        Returns:
            ``(mean (n, D), var (n, D))`` in raw units (differentiable w.r.t. ``x``).
        """
        x = self.check_query(x)
        if self.inducing_points is not None:
            raise GpmpcError("gpytorch_predict is the exact GP's reference path; this model is sparse "
                             "(tests/gp/test_sparse.py compares it with GPyTorch's SGPR)")
        self.model.eval()
        self.likelihood.eval()
        z = ((x - self.x_mean) / self.x_std).expand(self.output_dim, *x.shape)
        with gpytorch.settings.max_cholesky_size(MAX_CHOLESKY_SIZE):
            post = self.model(z)
            if include_noise:
                post = self.likelihood(post)
            mean, var = post.mean, post.variance
        return self.y_mean + self.y_std * mean.T, self.y_std ** 2 * var.T

    def negative_log_marginal_likelihood(self) -> float:
        """Exact ``-log p(Y)`` of the training data in raw units, summed over the D outputs
        (``nan`` for a sparse model, whose factorization does not give it)."""
        if self.inducing_points is not None:
            return float("nan")
        c = self._get_cache()
        ys = ((self.train_y_raw - self.y_mean) / self.y_std).T
        n = self.num_data
        per_dim = (0.5 * (ys * c.alpha).sum(-1) + torch.diagonal(c.chol, dim1=-2, dim2=-1).log().sum(-1)
                   + 0.5 * n * math.log(2 * math.pi) + n * torch.log(self.y_std))
        return float(per_dim.sum())

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> None:
        """Write the model to ONE ``.pt`` file, atomically.

        The file is ``torch.save`` of a dict holding only strings, ints and tensors:
        the GPyTorch state dict (raw hyperparameters and constraint bounds), the
        normalization constants and the raw training data.
        """
        payload = {
            "format": FORMAT,
            "version": VERSION,
            "input_kind": self.gp_inputs,
            "train_inputs": self.train_inputs_raw.detach().clone(),
            "train_y": self.train_y_raw.detach().clone(),
            "x_mean": self.x_mean.clone(), "x_std": self.x_std.clone(),
            "y_mean": self.y_mean.clone(), "y_std": self.y_std.clone(),
            "state_dict": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
        }
        if self.inducing_points is not None:
            payload["inducing_points"] = self.inducing_points.detach().clone()
        if self.residual_rows is not None:  # files without it (older ones) still load
            payload["residual_rows"] = self.residual_rows
        write_payload(path, payload)

    @classmethod
    def load(cls, path: str | Path, expected_dim: int | None = None,
             expected_input_dim: int | None = None) -> "ResidualGP":
        """Read a model written by :meth:`save` (``torch.load(weights_only=True)``: never runs code).

        Args:
            path: the ``.pt`` file.
            expected_dim: if given, the required output (state) dimension D.
            expected_input_dim: if given, the required input dimension Din.

        Raises:
            GpmpcError: missing, corrupt or truncated file, wrong format, unsafe
                pickle content, invalid content, or dimension mismatch.
        """
        src = f"GP model file {str(path)!r}"
        gp = cls.from_payload(read_payload(Path(path), src), src)
        if expected_dim is not None and gp.output_dim != int(expected_dim):
            raise GpmpcError(f"{src}: the model predicts D={gp.output_dim} residual dimensions but "
                             f"D={expected_dim} is required; fit a model on data of dimension {expected_dim}")
        if expected_input_dim is not None and gp.input_dim != int(expected_input_dim):
            raise GpmpcError(f"{src}: the model takes Din={gp.input_dim} inputs ({gp.gp_inputs}) but "
                             f"Din={expected_input_dim} is required; refit with the matching --gp-inputs "
                             "(state: Din = D, state_input: Din = D + Du)")
        return gp

    @classmethod
    def from_payload(cls, payload: Any, src: str) -> "ResidualGP":
        """Validate a dict read from a model file and rebuild the model.

        Raises:
            GpmpcError: naming ``src`` and the first invalid entry.
        """
        if not isinstance(payload, dict) or payload.get("format") != FORMAT:
            raise GpmpcError(f"{src}: not a torch_gpmpc ResidualGP file (missing format tag {FORMAT!r})")
        if payload.get("version") != VERSION:
            raise GpmpcError(f"{src}: unsupported version {payload.get('version')!r}; expected {VERSION}")
        tensors = {}
        for key in ("train_inputs", "train_y", "x_mean", "x_std", "y_mean", "y_std"):
            value = payload.get(key)
            if not isinstance(value, Tensor) or not value.is_floating_point():
                raise GpmpcError(f"{src}: entry {key!r} is missing or not a float tensor (corrupt file)")
            if not bool(torch.isfinite(value).all()):
                raise GpmpcError(f"{src}: entry {key!r} has NaN/inf values (corrupt file)")
            tensors[key] = value.to(torch.float64)
        X, Y = tensors["train_inputs"], tensors["train_y"]
        if X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0] or X.shape[0] < 2:
            raise GpmpcError(f"{src}: training data shapes {tuple(X.shape)} / {tuple(Y.shape)} are "
                             "inconsistent (corrupt file)")
        expect = {"x_mean": X.shape[1], "x_std": X.shape[1], "y_mean": Y.shape[1], "y_std": Y.shape[1]}
        for key, size in expect.items():
            if tuple(tensors[key].shape) != (size,) or (key.endswith("std") and bool((tensors[key] <= 0).any())):
                raise GpmpcError(f"{src}: entry {key!r} has shape {tuple(tensors[key].shape)} or values "
                                 f"inconsistent with the training data (expected ({size},), std > 0)")
        kind = payload.get("input_kind")  # the file's name for gp_inputs
        if kind not in GP_INPUTS and not _is_column_list(kind):
            raise GpmpcError(f"{src}: entry 'input_kind' must be one of {GP_INPUTS} or model columns "
                             f"such as 'x3,u0', got {kind!r}")
        inducing = payload.get("inducing_points")
        if inducing is not None and not (isinstance(inducing, Tensor) and inducing.is_floating_point()
                                         and inducing.ndim == 2 and inducing.shape[1] == X.shape[1]
                                         and inducing.shape[0] >= 1 and bool(torch.isfinite(inducing).all())):
            raise GpmpcError(f"{src}: entry 'inducing_points' must be a finite (M, {X.shape[1]}) float tensor "
                             "(corrupt file)")
        gp = cls(X, Y, gp_inputs=kind, normalization=Standardization(
            tensors["x_mean"], tensors["x_std"], tensors["y_mean"], tensors["y_std"]), inducing_points=inducing)
        gp._load_state(payload.get("state_dict"), src)
        rows = payload.get("residual_rows")
        if rows is not None and not (_is_column_list(rows) and "u" not in rows and len(rows.split(",")) == Y.shape[1]):
            raise GpmpcError(f"{src}: entry 'residual_rows' must name {Y.shape[1]} state rows such as 'x2,x3', "
                             f"got {rows!r} (corrupt file)")
        gp.residual_rows = rows
        # last: the checks above give more specific messages; this catches what they cannot see
        verify_checksum(payload, src)
        return gp.refresh()



    def _load_state(self, state: Any, src: str) -> None:
        reference = self.model.state_dict()
        if not isinstance(state, dict) or set(state) != set(reference):
            got = sorted(state) if isinstance(state, dict) else type(state).__name__
            raise GpmpcError(f"{src}: entry 'state_dict' does not hold the expected hyperparameters "
                             f"{sorted(reference)} (got {got})")
        for key, ref in reference.items():
            value = state[key]
            if not isinstance(value, Tensor) or value.shape != ref.shape:
                raise GpmpcError(f"{src}: hyperparameter {key!r} has the wrong shape "
                                 f"(expected {tuple(ref.shape)})")
            if value.is_floating_point() and not bool(torch.isfinite(value).all()) and "bound" not in key:
                raise GpmpcError(f"{src}: hyperparameter {key!r} has NaN/inf values (corrupt file)")
        self.model.load_state_dict({k: v.to(reference[k].dtype) for k, v in state.items()})


def _is_column_list(label: Any) -> bool:
    """Whether ``label`` names GP input columns of a model, e.g. ``"x3,x4,u0"``."""
    return isinstance(label, str) and bool(re.fullmatch(r"[xu]\d+(,[xu]\d+)*", label))


def _check_inducing(points: Tensor | None, input_dim: int) -> Tensor | None:
    if points is None:
        return None
    points = torch.as_tensor(points, dtype=torch.float64)
    if points.ndim != 2 or points.shape[1] != input_dim or points.shape[0] < 1:
        raise GpmpcError(f"inducing points must have shape (M, {input_dim}), got {tuple(points.shape)}")
    if not bool(torch.isfinite(points).all()):
        raise GpmpcError("inducing points contain NaN or inf")
    return points.detach().clone()


def check_training_data(inputs: Tensor, y: Tensor, min_rows: int = 2) -> tuple[Tensor, Tensor]:
    """Float64 copies of GP rows ``inputs`` (N, Din) and ``y`` (N, D) with N >= ``min_rows`` (a fit
    needs 2; an online update adds 1), non-empty dimensions and finite values.

    Raises:
        GpmpcError: naming the shapes or the non-finite values.
    """
    inputs = torch.as_tensor(inputs, dtype=torch.float64)
    y = torch.as_tensor(y, dtype=torch.float64)
    if inputs.ndim != 2 or y.ndim != 2 or inputs.shape[0] != y.shape[0]:
        raise GpmpcError(f"GP training data: inputs must be (N, Din) and y (N, D) with the same N, "
                         f"got {tuple(inputs.shape)} and {tuple(y.shape)}")
    if inputs.shape[0] < min_rows or inputs.shape[1] < 1 or y.shape[1] < 1:
        raise GpmpcError(f"GP training data: need N >= {min_rows} points and non-empty dimensions, "
                         f"got inputs {tuple(inputs.shape)}, y {tuple(y.shape)}")
    if not (torch.isfinite(inputs).all() and torch.isfinite(y).all()):
        raise GpmpcError("GP training data contains NaN or inf; clean the transitions first")
    return inputs.detach().clone(), y.detach().clone()
