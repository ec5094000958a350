"""Same seed, same tree: the hashes of fixed small plans (tests/tree_cases.py), recorded from
the planner before it was split into a loop and strategies (commit e14ddd1).

A change that moves a tree (a different random-number order, another choice of parent, a
rounding) fails here. When the move is intended, say so in the commit and record the new
hash with the reason; a refactor must leave every hash as it is.

Each case also asserts what it exercises (edges by kind, the connections switched on and the
one that reached the goal), so that a case that stops exercising its strategy is noticed
rather than silently hashing a trivial tree.

The LQR connection's Riccati solve is LAPACK's, whose last bits hang on the OpenBLAS kernel
the CPU picks: tests/conftest.py pins the Haswell kernel where the CPU runs it (on an AVX-512
machine OpenBLAS picks SkylakeX, and pendulum_u1, quadrotor and the sparse_rrt cart-pole came
out different there).
"""

from __future__ import annotations

import pytest
from tests.tree_cases import CASES, fit_model, plan_case, summary, tree_hash

# name: (tree hash, what the plan exercised) as the planner at e14ddd1 grew them, except the
# cart-pole, quadrotor and sparse_rrt cart-pole: recorded again when J, U and V came to be
# learned on x1 - x0 along their invariant coordinates (docs/invariance.md), which changes
# their models and so their trees; pendulum_auto, pendulum_u1, quadrotor and the sparse_rrt
# cart-pole recorded again when the Newton steps of shooting and landing stopped going through
# LAPACK and BLAS (pendulum_auto's tree differed with the BLAS kernel the CPU picks);
# pendulum_auto and the cart-pole recorded again when the automatic funnel came to switch on
# with shooting, small and growing (issue 31, docs/derived_settings.md): both now connect
# through it at the iteration the connections switch on (pendulum_auto's shooting connected
# 6 iterations later; the cart-pole's 600 iterations ended unsolved); the three cases with a
# funnel (pendulum, pendulum_auto, cartpole) recorded again when the funnel's extremals came to
# be drawn from a stream of the query's seed of their own, shared by the query's solves
# (`funnel.FunnelStream`, docs/anytime.md "One funnel per query"), instead of from the solve's
# generator at the switch-on: other extremals, and the solve's generator no longer advanced by
# their draws (the pendulum connects at iteration 34 instead of 22, pendulum_auto at the same
# iteration, the cart-pole at 426 instead of 331: one draw of each, no trend); the cart-pole
# recorded again when the funnel connection came to try first the node whose path would cost
# least (cost to come plus its funnel state's cost to go), then the nearest: it connects at
# iteration 331 from a node whose path costs 1 321 (before: at 426, 1 370); the pendulum
# cases' trees are unchanged (pendulum_auto's cheapest node fails to steer, its nearest connects);
# pendulum_auto recorded again when a solve that reached the goal came to shoot at it from the
# nodes cheapest by cost-to-come + J (`plan.goal_parent_tries`, `connections.cheaper_goal_edge`):
# its tree is the one before (c6d61fc847b86080 with the setting at 0) plus one shooting edge
# into the goal, the path 8.02 -> 6.80; the other cases' shots found nothing cheaper; the
# pendulum's funnel count and the cart-pole recorded again when the funnel's extremals came to
# last as long as the data's longest (`plan.funnel_duration` derived: 3.43 s and 19.95 s
# here, before 3 s): the pendulum keeps its tree (26 350 -> 26 726 funnel states), the
# cart-pole connects at the same iteration 331 from another funnel state (path 1 321 -> 1 581:
# one seed; over seeds 0-19 of bench/ablation.py's model the first cost fell, docs/ablation.md);
# the three funnel cases recorded again when the funnel's continuation came to start each
# step from the secant predictor and stopped growing its step after a failure
# (`GoalFunnel.steer`): the same nodes, iterations, connections and path costs (to 1e-3),
# the funnel edge's costate converged from another guess within the solve's tolerance;
# pendulum_u1 and the sparse_rrt cart-pole recorded again when the LQR loop's horizon came to
# be 5 time constants of its closed loop (`GoalLQR.horizon`: 5 s and 9.4 s) instead of 3 s:
# pendulum_u1 connects at the LQR's switch-on (iteration 548, first try; before 1 138, path
# 16.73 -> 12.75), the sparse_rrt cart-pole at its 4th try (iteration 597; before the 11th
# at 1 215, path 119 935 -> 32 819); pendulum_auto recorded again when a funnel continuation
# whose extremal misses the goal as one edge came to be landed by multiple shooting along it
# (`FunnelConnection._chain`): the same iteration 851, now by a chain of two funnel edges
# (path 6.80 -> 5.42; the optimum to the ball is 5.205); the cart-pole recorded again when
# choose-parent for the goal came to try the funnel too (`FunnelConnection.cheaper`): the
# same tree, connected at the same iteration 331, plus a cheaper chain of two funnel edges
# (path 1 581 -> 818); and again when it came to try nodes within twice the funnel's radius
# too (`connections.PARENT_REACH`): one funnel edge from another node (path 1 581 -> 691)
EXPECTED = {
    "pendulum": ("14c14b80f476f1e4", {"connection": "funnel", "funnel_states": 26726}),
    "pendulum_auto": ("547b79e027def467", {"connection": "funnel",
                                           "switched": {"lqr": 851, "shooting": 851,
                                                        "funnel": 851}}),
    "pendulum_u1": ("6160cbf1da1ae409", {"connection": "lqr",
                                         "edges_by": {"learned": 91, "control": 417},
                                         "switched": {"controls": 30, "lqr": 548}}),
    "pendulum_u1_obstacle": ("c314f55558930e9e", {"edges_by": {"learned": 5, "control": 695},
                                                  "lqr": {"tries": 101}}),
    "cartpole": ("609e47022f095142", {"nodes": 274, "connection": "funnel",
                                      "switched": {"lqr": 331, "shooting": 331,
                                                   "funnel": 331}}),
    "acrobot": ("a115ad656a07d5c3", {"nodes": 537}),
    "quadrotor": ("1e659a65b522405d", {"edges_by": {"learned": 26, "control": 190}}),
    "sparse_rrt_cartpole": ("aadc100e4aa08431", {"connection": "lqr", "lqr": {"tries": 4},
                                                 "edges_by": {"learned": 47,
                                                              "control": 353}}),
    "sparse_rrt_acrobot": ("1bcb2e9e569edb9f", {"edges_by": {"learned": 65, "control": 1372},
                                                "lqr": {"tries": 25}}),
}


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Each case's model, fitted once (cases with equal model settings share it)."""
    root = tmp_path_factory.mktemp("tree_models")
    return {c.name: fit_model(c, root / str(i)) for i, c in enumerate(CASES)}


def test_every_case_has_a_recorded_hash():
    assert sorted(EXPECTED) == sorted(c.name for c in CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_the_tree_is_the_recorded_one(models, case):
    plan = plan_case(case, models[case.name])
    got = summary(plan)
    want_hash, exercised = EXPECTED[case.name]
    assert {k: got[k] for k in exercised} == exercised
    assert tree_hash(plan) == want_hash
