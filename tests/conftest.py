"""Test-wide settings: one torch thread (the problems are tiny; more threads only add
overhead and make timings on a shared 2-core machine erratic)."""

import torch

torch.set_num_threads(1)

