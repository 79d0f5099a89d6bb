# %% [markdown]
# # Gradients through a control step
#
# The local problems are solved by a differentiable interior point, and ADMM's iterations are torch
# operations, so a plan's cost has gradients with respect to the ADMM penalty rho, the risk split and
# the weights of your cost. `Controller.differentiable_step` sets what gradients need: a fixed number of
# ADMM iterations (a stopping test would make the map jump), no safety fallback, cold local solves.
#
# This page runs the paper's coupling, consensus on trajectory copies, where rho weighs every consensus
# term. Under the default plane coupling rho only sizes the planes' moves, which are capped at a quarter
# of the pair's distance: where every move is at its cap the plans do not depend on rho at all.

# %%
import torch

from torch_gpmpc import Controller, ControllerSettings, ModelSpec, QuadraticCost

model = ModelSpec.double_integrator(dim=2, dt=0.1, u_max=2.0)
q = torch.tensor([1.0, 1.0, 0.1, 0.1], dtype=torch.float64, requires_grad=True)
settings = ControllerSettings(method="nominal", horizon=10, admm_coupling="copies")
ctrl = Controller(model, settings=settings, cost=QuadraticCost(Q=q, R=0.01))
x0 = ctrl.model.states_at(torch.tensor([[-1.0, 0.05], [1.0, -0.05]], dtype=torch.float64))
xref = x0.flip(0)[:, None].expand(2, 11, 4)  # swap places


def plan_cost(rho):
    step = ctrl.differentiable_step(x0, xref, iterations=15, rho=rho)
    return ((step.plans[:, :, :2] - xref[:, :, :2]) ** 2).sum()


rho = torch.tensor(20.0, dtype=torch.float64, requires_grad=True)
value = plan_cost(rho)
value.backward()
print(f"plan cost {value.item():.4f}, d/drho {rho.grad.item():+.6f}, d/dQ {q.grad.tolist()}")

# %% [markdown]
# Against central differences:

# %%
h = 1e-4
with torch.no_grad():
    fd = (plan_cost(torch.tensor(20.0 + h, dtype=torch.float64)) -
          plan_cost(torch.tensor(20.0 - h, dtype=torch.float64))) / (2 * h)
print(f"autograd {rho.grad.item():+.6f}, finite differences {fd.item():+.6f}")

# %% [markdown]
# A few gradient steps on log rho: what `gpmpc tune` does over many instances and closed-loop steps,
# together with the risk split.

# %%
log_rho = torch.tensor(20.0, dtype=torch.float64).log().requires_grad_(True)
opt = torch.optim.Adam([log_rho], lr=0.15)
for i in range(5):
    opt.zero_grad()
    rho_i = log_rho.exp()
    loss = plan_cost(rho_i)
    loss.backward()
    print(f"iteration {i}: rho {rho_i.item():7.3f}, plan cost {loss.item():.4f}")
    opt.step()
