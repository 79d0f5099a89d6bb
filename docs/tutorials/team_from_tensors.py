# %% [markdown]
# # A team from tensors, with your own GPyTorch models and cost
#
# Four double integrators from your own `A`, `B` tensors, residual GPs you train yourself in GPyTorch,
# your own quadratic cost, your own closed loop, and the metrics of `metrics.json` for it.

# %%
import gpytorch
import torch

from torch_gpmpc import (Controller, ControllerSettings, ModelSpec, QuadraticCost, ResidualGP,
                         compute_metrics)

torch.manual_seed(0)
dt = 0.1
A = torch.tensor([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float64)
B = torch.tensor([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]], dtype=torch.float64)
model = ModelSpec.from_table({"name": "double integrator", "dt": dt, "A": A, "B": B, "position": [0, 1],
                              "residual": [2, 3], "gp_inputs": ["x0", "x1"], "input_bound": {"norm": 2.0}})


def wind(p):
    """What the model does not know: a velocity kick that depends on the position."""
    return 0.05 * torch.stack([torch.sin(p[..., 1]), torch.cos(p[..., 0])], -1)


# %% [markdown]
# One exact GP per residual row (any mean and kernel), trained by you; `ResidualGP.from_gpytorch`
# wraps them for the controller.

# %%
class RowGP(gpytorch.models.ExactGP):
    def __init__(self, x, y, likelihood):
        super().__init__(x, y, likelihood)
        self.mean_module = gpytorch.means.ZeroMean()
        self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.MaternKernel(nu=2.5, ard_num_dims=2))

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def train_agent_gp(samples=80):
    p = 6 * torch.rand(samples, 2, dtype=torch.float64) - 3
    y = wind(p) + 0.01 * torch.randn(samples, 2, dtype=torch.float64)
    models, likelihoods = [], []
    for r in range(2):
        lik = gpytorch.likelihoods.GaussianLikelihood().double()
        gp = RowGP(p, y[:, r], lik).double()
        gp.train(), lik.train()
        opt = torch.optim.Adam(gp.parameters(), lr=0.1)
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, gp)
        for _ in range(40):
            opt.zero_grad()
            (-mll(gp(p), y[:, r])).backward()
            opt.step()
        models.append(gp.eval()), likelihoods.append(lik.eval())
    return ResidualGP.from_gpytorch(models, likelihoods)


gps = [train_agent_gp() for _ in range(4)]

# %% [markdown]
# Your cost: position errors weigh 1, velocity errors 0.1, inputs 0.01; the terminal weight is the LQR
# cost-to-go of the model for these Q and R (give `P=` to choose it).

# %%
cost = QuadraticCost(Q=torch.tensor([1.0, 1.0, 0.1, 0.1], dtype=torch.float64), R=0.01)
ctrl = Controller(model, gps=gps, settings=ControllerSettings(horizon=10), cost=cost)
print("terminal weight P (diagonal):", ctrl.agent_step.cost_weights[2][0].diagonal())

angles = torch.arange(4, dtype=torch.float64) * torch.pi / 2
starts = torch.stack([2.5 * torch.cos(angles), 2.5 * torch.sin(angles)], 1)
targets = -starts
x = ctrl.model.states_at(starts)
states = [x]
for t in range(100):
    s = torch.clamp((t + torch.arange(11, dtype=torch.float64)) / 50.0, max=1.0)
    path = starts[:, None] + s[None, :, None] * (targets - starts)[:, None]
    step = ctrl.step(x, ctrl.model.reference_states(path))
    x = x @ A.T + step.inputs[:, 0] @ B.T              # your plant
    x[:, 2:] += wind(x[:, :2]) + 0.01 * torch.randn(4, 2, dtype=torch.float64)
    states.append(x)

m = compute_metrics(states=torch.stack(states), targets=targets, r_safe=0.5, goal_tol=0.1, position=[0, 1])
print({k: m[k] for k in ("violations", "min_pair_distance", "arrival_step_max", "time_to_target")})
