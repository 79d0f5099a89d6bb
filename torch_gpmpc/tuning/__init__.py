r"""Gradient tuning of the ADMM penalty rho and the per-pair risk split (``gpmpc tune``).

Parameters (:class:`TuningParameters`):

* ``log_rho`` (scalar): ``rho = exp(log_rho)``, one global penalty;
* ``theta`` (K, K): for each edge ``(lo, hi)``, ``lo < hi``, the split
  ``s_lo,hi = sigmoid(theta[lo, hi])``, so that ``eps_lo = eps s`` and
  ``eps_hi = eps (1 - s)`` (paper eq. 21: the pair's total ``eps`` stays fixed).
  Entries below the diagonal are unused. The split is handed to
  :meth:`ADMM.solve_step <torch_gpmpc.coordination.admm.ADMM.solve_step>` as the (K, K) tensor
  ``sigmoid(theta)`` (entry ``[lo, hi]``).

Objective (:class:`TuningObjective`), averaged over a batch of training instances
(:class:`TuneInstance`: a start state, a reference, a fixed noise sequence) and over
``mpc_steps`` closed-loop MPC steps per instance. At every step ADMM runs a **fixed**
number ``admm_iters`` of iterations (no early stop, so the objective is one smooth
function of the parameters) with gradients through every local solve (cvxpylayers)::

    L = w_primal   * r_p                                 (final primal residual)
      + w_dual     * r_d                                 (final dual residual)
      + w_cost     * mean_k J_k                          (planned cost)
      + w_distance * sum_{tau,k<j} beta softplus((r_safe - d_kj^tau) / beta) / #pairs

with, at the last iteration (``E`` edges, ``a`` the two ends of an edge),

* ``r_p = sqrt(mean_{e,a} ||y_{e,a} - z_e||^2)`` (root mean square of the per-edge primal
  residuals of the paper's stopping rule; smooth, unlike their max);
* ``r_d = rho sqrt(mean_e ||z_e - z_e^prev||^2)`` (the dual residual; the primal
  residual alone rewards ever larger rho, the dual one penalizes it);
* ``J_k = ||X_k - Xref_k||_F^2 + alpha ||U_k||_F^2`` (+ the input-rate term with ``input_rate_weight``) of agent k's final local plan;
* ``d_kj^tau = ||X_k^tau - X_j^tau||`` for ``tau = 1..T`` between the agents' *own*
  plans (not the copies): a consensus that is not reached shows up here.

Between MPC steps the true system is stepped with the plans' first inputs and the
instance's fixed noise; the next ADMM is warm-started from the shifted iterate (as in
:func:`~torch_gpmpc.sim.closed_loop.simulate`), and gradients flow through the closed loop.
Optionally ``warmup_iters`` gradient-free iterations run first at the current
parameters (truncated back-propagation: a near-converged start, then the unrolled
iterations), which makes the planned cost that of a (nearly) converged consensus.

Implementation note (:mod:`.unroll`): the unroll calls the public ``ADMM.solve_step`` once per
iteration (``max_iter=1``, ``tol=0``) warm-started from the previous iterate, which is
exactly one iteration of the multi-iteration loop (for ``relinearize=False`` the
linearization points are held at the start plans, as ``solve_step`` does). The
tensor residuals need each end's copy of each edge, taken with the ADMM helper
``edge_copies`` (``solve_step`` reports residuals only as floats).

Seeds: instance seed ``s`` draws the start perturbation and the closed-loop noise from
``torch.Generator().manual_seed(s)``; nothing else is random, so an objective value is
reproducible and tuning resumes exactly.
"""

from torch_gpmpc.config.tune_settings import TuneSettings
from torch_gpmpc.tuning.baselines import equalizing_split, grid_search_rho
from torch_gpmpc.tuning.instances import TuneInstance, crossing_index, head_on_instance, make_instances, with_warm_starts
from torch_gpmpc.tuning.objective import PARTS, ObjectiveValue, TuningObjective
from torch_gpmpc.tuning.parameters import ObjectiveWeights, TuningParameters
from torch_gpmpc.tuning.results import load_risk_split, tuned_payload
from torch_gpmpc.tuning.tuner import Tuner, TuneRecord
from torch_gpmpc.tuning.unroll import UnrolledStep, distance_penalty, unroll_admm

__all__ = ["PARTS", "ObjectiveValue", "ObjectiveWeights", "TuneInstance", "TuneRecord", "TuneSettings", "Tuner",
           "TuningObjective", "TuningParameters", "UnrolledStep", "crossing_index", "distance_penalty",
           "equalizing_split", "grid_search_rho", "head_on_instance", "load_risk_split", "make_instances",
           "tuned_payload", "unroll_admm", "with_warm_starts"]
