"""Who re-plans in the safety fallback: the closure of the short rows over the cell exits."""

import torch

from torch_gpmpc.coordination.fallback import (
    cell_exits, cell_slots, fallback_agents, own_rows_unsafe, pair_safety, replanning_closure, replanning_from_seeds,
)
from torch_gpmpc.coordination.graph import communication_graph

POS = [0, 1]


def _team(positions: list[list[float]], steps: list[list[float]]) -> tuple:
    """``(plans (K, 2, 2), graph)``: plans from the positions (tau = 0) one step on (tau = 1)."""
    x0 = torch.tensor(positions, dtype=torch.float64)
    plans = torch.stack([x0, x0 + torch.tensor(steps, dtype=torch.float64)], dim=1)
    return plans, communication_graph(x0, None)


def test_a_chain_of_cell_exits_joins_the_re_plan_and_nothing_else():
    """Five agents on a line 1 m apart, bound 0.5: agents 1 and 2 step 0.3 towards each other
    (their rows ask 0.5, they keep 0.4: both seeds); agent 3 steps 0.3 left, out of its cell towards
    agent 2 (it joins), agent 4 then steps out of its cell towards agent 3 (it joins too); agent 0
    stays inside its cell and keeps its plan."""
    plans, graph = _team([[0.0, 0], [1.0, 0], [2.0, 0], [3.0, 0], [4.0, 0]],
                         [[0.0, 0], [0.3, 0], [-0.3, 0], [-0.8, 0], [-1.3, 0]])
    bounds = torch.where(graph.active, 0.5, float("-inf")).to(torch.float64)
    seeds = own_rows_unsafe(plans, graph, bounds, 1e-3, POS)
    assert seeds.tolist() == [False, True, True, False, False]
    exits = cell_exits(plans, graph, bounds, 1e-3, POS)
    assert replanning_closure(seeds, exits, graph).tolist() == [False, True, True, True, True]
    replan, cells = fallback_agents(plans, graph, bounds, 1e-3, POS, torch.zeros(5, dtype=torch.bool), "cells")
    assert replan.tolist() == [False, True, True, True, True] and torch.equal(cells, graph.active)
    # the world's form (the distributed backend's messages, by agent id) gives the same set
    by_id = torch.zeros(5, 5, dtype=torch.bool)
    k, m = torch.nonzero(exits, as_tuple=True)
    by_id[k, graph.slot_nbr[k, m]] = True
    assert torch.equal(replanning_from_seeds(seeds, by_id, graph), replan)


def test_every_pair_is_safe_after_the_re_plan_on_random_teams():
    """On random teams with random steps, unequal row bounds and (in half the teams) some agents
    with momentum: every agent whose own row of a cell pair is short re-plans, and both agents of an
    unsafe pair with momentum; no agent that keeps its plan leaves its cell towards a cell
    neighbour that re-plans; and every cell pair that keeps both plans is as far apart as the larger
    of its two bounds asks (less tol). So after the re-plans (each inside its cells) every cell pair
    keeps (b_k + b_j) / 2 or more at tau = 1, as long as no re-plan needs slack (not solved here)."""
    gen = torch.Generator().manual_seed(0)
    tol = 1e-3
    checked = joined = mixed = 0
    for team in range(400):
        K = 12
        x0 = torch.rand(K, 2, generator=gen, dtype=torch.float64) * 4.0
        step = (torch.rand(K, 2, generator=gen, dtype=torch.float64) - 0.5) * 0.6
        plans = torch.stack([x0, x0 + step], dim=1)
        graph = communication_graph(x0, 2.5)
        momentum = (torch.rand(K, generator=gen) < 0.3) & torch.tensor(team % 2 == 1)
        if not graph.num_edges:
            continue
        bounds = torch.where(graph.active, 0.4 + 0.2 * torch.rand(graph.active.shape, generator=gen,
                                                                    dtype=torch.float64), float("-inf"))
        unsafe, sep, req = pair_safety(plans, graph, bounds, tol, POS)
        replan, cells = fallback_agents(plans, graph, bounds, tol, POS, momentum, "cells")
        assert torch.equal(cells, cell_slots(momentum, graph))
        seeds = own_rows_unsafe(plans, graph, torch.where(cells, bounds, float("-inf")), tol, POS)
        assert bool((replan | ~seeds).all())
        k, m = torch.nonzero(graph.active & ~cells, as_tuple=True)  # pairs with momentum
        j = graph.slot_nbr[k, m]
        assert bool(replan[k[sep[k, j] < req[k, j] - tol]].all())
        # without cells, exactly the agents of unsafe pairs re-plan: a pair closer at tau = 1 than
        # the larger of its two bounds, less tol, counted pair by pair
        by_pair = {(int(a), int(graph.slot_nbr[a, s])): float(bounds[a, s]) for a, s in graph.active.nonzero()}
        expected = torch.zeros(K, dtype=torch.bool)
        for (a, b), bound in by_pair.items():
            gap = float(torch.linalg.vector_norm(plans[a, 1] - plans[b, 1]))
            expected[a] |= gap < max(bound, by_pair[(b, a)]) - tol
        assert torch.equal(unsafe, expected)
        assert torch.equal(fallback_agents(plans, graph, bounds, tol, POS, momentum, "obstacles")[0], expected)
        joined += int((replan & ~seeds & ~unsafe).sum())
        exits = cell_exits(plans, graph, bounds, tol, POS)
        towards_member = exits & replan[graph.slot_nbr] & cells
        assert not bool((towards_member & ~replan[:, None]).any())
        k, m = torch.nonzero(cells & ~replan[:, None] & ~replan[graph.slot_nbr], as_tuple=True)
        j = graph.slot_nbr[k, m]
        gap = torch.linalg.vector_norm(plans[k, 1] - plans[j, 1], dim=-1)
        assert bool((gap >= bounds[k, m] - tol).all())
        checked += int(k.numel())
        mixed += int((momentum.any() & ~momentum & (cells.any(dim=1)) & (graph.active & ~cells).any(dim=1)).sum())
    assert checked > 500 and joined > 50 and mixed > 100  # the closure reached past the seeds; mixed agents met


def test_a_cell_pair_is_kept_when_one_of_its_agents_has_a_neighbour_with_momentum():
    """Four agents on a line, bound 0.5, each talking to the next (comm radius 1.3); agent 3 has
    momentum. Agents 0 and 1 step towards each other (their rows are short: seeds); agent 1 may
    re-plan up to its cell's face towards agent 2 at 1.35. Agent 2's plan leaves its cell towards
    agent 1 (bisector 1.6, its cell x >= 1.85; it plans 1.7), 0.35 from that face, while the pair
    keeps 1.0 apart at tau = 1 (not unsafe). Agent 2 has a neighbour with momentum, yet the pair
    (1, 2) is a cell pair: agent 2 re-plans. (Decided per agent, agent 2 would give up its cells
    and keep its plan, since none of its pairs is unsafe, while agent 1 kept to its cells.)"""
    x0 = torch.tensor([[0.0, 0], [1.0, 0], [2.2, 0], [3.4, 0]], dtype=torch.float64)
    step = torch.tensor([[0.3, 0], [-0.3, 0], [-0.5, 0], [0.0, 0]], dtype=torch.float64)
    plans, graph = torch.stack([x0, x0 + step], dim=1), communication_graph(x0, 1.3)
    bounds = torch.where(graph.active, 0.5, float("-inf")).to(torch.float64)
    momentum = torch.tensor([False, False, False, True])
    slots = cell_slots(momentum, graph)
    pairs = {(int(k), int(graph.slot_nbr[k, m])) for k, m in zip(*torch.nonzero(slots, as_tuple=True))}
    assert pairs == {(0, 1), (1, 0), (1, 2), (2, 1)}  # the pair (2, 3) has momentum
    unsafe, _, _ = pair_safety(plans, graph, bounds, 1e-3, POS)
    assert unsafe.tolist() == [True, True, False, False]
    replan, cells = fallback_agents(plans, graph, bounds, 1e-3, POS, momentum, "cells")
    assert replan.tolist() == [True, True, True, False] and torch.equal(cells, slots)
