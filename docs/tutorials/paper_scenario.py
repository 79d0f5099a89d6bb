# %% [markdown]
# # The paper's scenario
#
# Three agents on a circle of radius 4 swap places through a vortex wind that their nominal model
# `x' = x + 0.1 u` does not know. Each agent learns the wind as a residual GP from 100 logged
# transitions, plans with the GP linearized along its plan, and keeps a chance margin against each
# neighbour, agreeing on the crossing by consensus ADMM. This page is executed when the docs build:
# every number and figure below comes from running it.

# %%
import matplotlib.pyplot as plt
import torch

from torch_gpmpc import Config, compute_metrics, simulate

cfg = Config(seed=0)  # the paper scenario, the proposed gp-chance method, noise s = 0.1
rollout = simulate(cfg)
m = compute_metrics(rollout)
print(f"every agent within {m['goal_tol']} of its goal by t = {m['arrival_step_max']}; "
      f"closest pair {m['min_pair_distance']:.3f} (r_safe {m['r_safe']}), {m['violations']} violating step-pairs; "
      f"ADMM iterations per step {m['admm_iterations_mean']:.1f}")

# %% [markdown]
# The trajectories (`rollout.states`, shape (S+1, K, n)) and the pair distances over the run:

# %%
states = torch.as_tensor(rollout.states)
fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4.2))
for k in range(states.shape[1]):
    ax.plot(states[:, k, 0], states[:, k, 1], label=f"agent {k}")
    ax.plot(states[0, k, 0], states[0, k, 1], "o", color=f"C{k}")
ax.set_aspect("equal")
ax.set_title("trajectories (circles: starts)")
ax.legend(fontsize=8)
pairs = [(0, 1), (0, 2), (1, 2)]
for i, j in pairs:
    bx.plot((states[:, i] - states[:, j]).norm(dim=-1), label=f"pair {i}-{j}")
bx.axhline(cfg.r_safe, color="k", ls="--", lw=1, label="r_safe")
bx.set_xlabel("step")
bx.set_ylabel("distance")
bx.set_ylim(0, 3)
bx.set_title("pair distances")
bx.legend(fontsize=8)
plt.tight_layout()
plt.show()

# %% [markdown]
# `gpmpc run --out runs/paper` does the same from the command line and also writes the figures,
# `metrics.json`, `rollout.npz` and TensorBoard logs; `gpmpc reproduce` runs the paper's six methods
# over ten seeds (see [Reproducing the paper](../guides/reproduce.md)).
