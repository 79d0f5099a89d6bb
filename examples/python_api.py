"""A team of 3D double integrators controlled from Python, as in a notebook.

The model comes from a ``ModelSpec`` object (no model file, no flat config keys); each agent
learns its residual with GPyTorch models written here (one exact GP per residual row, a Matern
kernel), wrapped by ``ResidualGP.from_gpytorch``; a ``Controller`` runs 50 closed-loop steps;
then the gradients of a plan cost to rho, the risk split and one lengthscale are taken and
checked against central finite differences.

Run: ``python examples/python_api.py`` (10 s wall, alone on a 2-core machine; the first run after
installing also compiles the solver kernel, 20-30 s).
"""

from __future__ import annotations

import gpytorch
import torch

from torch_gpmpc import Controller, ControllerSettings, ModelSpec, ResidualGP, compute_metrics
from torch_gpmpc.dynamics.systems import NominalModel, TrueSystem, VortexWind


class MaternGP(gpytorch.models.ExactGP):
    """One residual row: constant mean, Matern-5/2 kernel with ARD."""

    def __init__(self, x, y, likelihood):
        super().__init__(x, y, likelihood)
        self.mean_module = gpytorch.means.ConstantMean()
        self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.MaternKernel(nu=2.5,
                                                                                      ard_num_dims=x.shape[-1]))

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def fit(x, y, iters=60):
    """Fit one row's GP by Adam on the exact marginal likelihood; returns (model, likelihood)."""
    likelihood = gpytorch.likelihoods.GaussianLikelihood().double()
    model = MaternGP(x, y, likelihood).double()
    model.train(), likelihood.train()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
    opt = torch.optim.Adam(model.parameters(), lr=0.1)
    for _ in range(iters):
        opt.zero_grad()
        (-mll(model(x), y)).backward()
        opt.step()
    return model.eval(), likelihood.eval()


def learn_residuals(plant: TrueSystem, agents: int, samples: int, generator: torch.Generator) -> list:
    """Per agent: random transitions of the plant, one GP per residual row (the velocity rows,
    read from the position: the model's ``gp_inputs``)."""
    nominal = plant.nominal
    gps = []
    for _ in range(agents):
        p = 4 * torch.rand(samples, 3, generator=generator, dtype=torch.float64) - 2
        v = 0.5 * torch.randn(samples, 3, generator=generator, dtype=torch.float64)
        u = torch.randn(samples, 3, generator=generator, dtype=torch.float64)
        x = torch.cat([p, v], dim=1)
        residual = (plant.step(x, u, generator=generator) - nominal(x, u))[:, nominal.residual]
        inputs = nominal.gp_input(x, u)
        rows = [fit(inputs, residual[:, r]) for r in range(residual.shape[1])]
        gps.append(ResidualGP.from_gpytorch([m for m, _ in rows], [lik for _, lik in rows]))
    return gps


def line_references(model: NominalModel, starts, targets, t: int, horizon: int, duration: int = 40):
    """State references (K, T+1, n): straight lines start -> target over ``duration`` steps, then hold."""
    s = torch.arange(t, t + horizon + 1, dtype=torch.float64).clamp(max=duration) / duration
    path = starts[:, None] + s[None, :, None] * (targets - starts)[:, None]
    return model.reference_states(path)


def plan_cost(step, xref) -> torch.Tensor:
    """A scalar of the plans: their squared tracking error."""
    return ((step.plans - xref) ** 2).sum()


def run(steps: int = 50, gradient_step: int = 14, agents: int = 4, horizon: int = 13, samples: int = 80,
        seed: int = 0) -> dict:
    """The closed loop, then the gradient check at ``gradient_step`` (returns the figures)."""
    gen = torch.Generator().manual_seed(seed)
    model = ModelSpec.double_integrator(dim=3, dt=0.1, u_max=2.0)
    plant = TrueSystem(NominalModel(model), VortexWind(0.1), noise_std=0.01)
    K = agents
    angles = 2 * torch.pi * torch.arange(K, dtype=torch.float64) / K
    starts = torch.stack([2 * torch.cos(angles), 2 * torch.sin(angles), 0.2 * torch.arange(K) - 0.3], dim=1)
    targets = -starts  # antipodal swap through the centre
    gps = learn_residuals(plant, K, samples=samples, generator=gen)
    # consensus on copies, whose penalty rho weighs every consensus term (the default plane coupling's rho
    # only sizes the planes' capped moves: this plan's gradient to it is 6e-12)
    settings = ControllerSettings(horizon=horizon, eps=0.1, rho=20.0, admm_coupling="copies")
    ctrl = Controller(model, gps=gps, settings=settings)
    print(f"message size {ctrl.message_size} numbers, uncertainty {ctrl.uncertainty}")

    x = ctrl.model.states_at(starts)
    saved = None
    states = [x]
    for t in range(steps):
        xref = line_references(ctrl.model, starts, targets, t, settings.horizon)
        if t == gradient_step:
            saved = (x.clone(), xref, ctrl.warm)
        step = ctrl.step(x, xref)
        x = plant.step(x, step.inputs[:, 0], generator=gen)
        states.append(x)
    metrics = compute_metrics(states=torch.stack(states), targets=targets, r_safe=settings.r_safe,
                              goal_tol=0.1, position=model.position)
    min_distance = metrics["min_pair_distance"]
    final_error = max(metrics["final_distance_to_target"])
    print(f"{steps} steps: closest pair {min_distance:.3f} (r_safe {settings.r_safe}, {metrics['violations']} "
          f"violations), farthest agent from its target {final_error:.3f}")

    # gradients of a plan cost at one step, from the same warm start: differentiable_step runs a fixed
    # number of ADMM iterations without the safety fallback and leaves the controller's warm start alone
    x_g, xref_g, warm = saved
    probe = Controller(model, gps=gps, settings=settings)
    kernel = gps[0].models[0].covar_module.base_kernel
    for gp in gps:
        gp.enable_hyperparameter_gradients()
        gp.zero_grad(set_to_none=True)  # training left its last gradients on the parameters

    probe.warm = warm

    def cost(rho, split):
        return plan_cost(probe.differentiable_step(x_g, xref_g, iterations=25, rho=rho, risk_split=split), xref_g)

    rho = torch.tensor(20.0, dtype=torch.float64, requires_grad=True)
    split = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    cost(rho, split).backward()
    grads = {"rho": float(rho.grad), "risk_split": float(split.grad),
             "raw_lengthscale[0]": float(kernel.raw_lengthscale.grad[0, 0])}

    def central(name: str, h: float) -> float:
        def at(delta: float) -> float:
            with torch.no_grad():
                if name == "rho":
                    return float(cost(20.0 + delta, 0.5))
                if name == "risk_split":
                    return float(cost(20.0, 0.5 + delta))
                kernel.raw_lengthscale[0, 0] += delta
                try:
                    return float(cost(20.0, 0.5))
                finally:
                    kernel.raw_lengthscale[0, 0] -= delta
        return (at(h) - at(-h)) / (2 * h)

    steps_h = {"rho": 1e-4, "risk_split": 1e-5, "raw_lengthscale[0]": 1e-5}
    fd = {name: central(name, h) for name, h in steps_h.items()}
    for gp in gps:
        gp.enable_hyperparameter_gradients(False)
    for name in grads:
        print(f"d cost / d {name}: autograd {grads[name]:+.6e}, finite differences {fd[name]:+.6e}")
    return {"min_distance": min_distance, "final_error": final_error, "grads": grads, "fd": fd,
            "message_size": ctrl.message_size, "uncertainty": ctrl.uncertainty}


if __name__ == "__main__":
    run()
