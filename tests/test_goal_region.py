"""Goal regions beyond a state ball: per-coordinate weights, a user goal function and
sampler (OMPL's GoalSampleableRegion), used by the goal bias, the connections and the test."""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import rk4_numpy

from rrtcolearn import pipeline
from rrtcolearn.config import paper_config
from rrtcolearn.planning.problem import PlanningProblem, ProblemError


def _check_path(plan, in_goal) -> None:
    """Every edge re-simulates onto the next node; the last node lies in the goal region."""
    d = plan.to_dict()
    for e in d["path"]:
        z = rk4_numpy(np.r_[e["from"], e["costate"], 0.0], d["time_weight"], d["dt"],
                      round(e["duration"] / d["dt"]))
        np.testing.assert_allclose(z[-1, :2], e["to"], atol=1e-9)
    assert in_goal(np.array(d["path"][-1]["to"]))


def test_free_velocity_goal(paper_model):
    cfg = paper_config(plan={"goal_weights": [1.0, 0.0]})
    ends = []
    for seed in range(3):
        p = pipeline.plan(paper_model, [-np.pi, 0], [0, 0], 0.05, seed=seed, config=cfg,
                          time_limit=None, max_iterations=5000)
        assert p.solved
        _check_path(p, lambda x: abs(x[0]) <= 0.05)
        end = p.tree.states[p.path_nodes[-1]]
        assert p.final_goal_distance == pytest.approx(abs(end[0]))
        ends.append(end[1])
    assert max(abs(v) for v in ends) > 0.05  # the velocity was left free, and used


def test_user_goal_function_and_sampler(paper_model):
    # upright within 0.1 rad either way round, at any speed below 2 rad/s
    def goal_fn(x):
        theta = np.mod(x[:, 0] + np.pi, 2 * np.pi) - np.pi
        return np.maximum(np.abs(theta), 0.05 * np.maximum(np.abs(x[:, 1]) - 2.0, 0.0))

    def sampler(rng):
        return np.array([rng.uniform(-0.05, 0.05), rng.uniform(-2.0, 2.0)])

    for seed in range(3):
        p = pipeline.plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=seed,
                          config=paper_config(), time_limit=None, max_iterations=5000,
                          goal_fn=goal_fn, goal_sampler=sampler)
        assert p.solved
        _check_path(p, lambda x: goal_fn(x[None])[0] <= 0.1)
        assert p.final_goal_distance <= 0.1


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"goal_weights": [1.0]}, "goal_weights"),
    ({"goal_weights": [-1.0, 1.0]}, "non-negative"),
    ({"goal_weights": [0.0, 0.0]}, "not all zero"),
    ({"goal_sampler": lambda rng: np.zeros(2)}, "needs its goal function"),
    ({"goal_fn": lambda x: np.zeros(3)}, "N finite distances"),
    ({"goal_fn": lambda x: np.full(len(x), 5.0)}, "not in the goal region"),
    ({"goal_fn": lambda x: np.zeros(len(x)), "goal_sampler": lambda rng: np.ones(3)},
     "one finite state"),
    ({"goal_fn": lambda x: np.abs(x[:, 0]), "goal_sampler": lambda rng: np.array([1.0, 0])},
     "outside the goal region"),
])
def test_bad_goal_regions_are_refused(pendulum, kwargs, match):
    with pytest.raises(ProblemError, match=match):
        PlanningProblem.create(pendulum, [-np.pi, 0], [0, 0], 0.1, **kwargs)


def test_default_goal_draws_nothing(pendulum):
    # the paper's goal (no weights, no region): goal-biased targets are the goal itself and
    # consume no random numbers, so seeded trees are the paper planner's
    prob = PlanningProblem.create(pendulum, [-np.pi, 0], [0, 0], 0.1, goal_weights=[1, 1])
    assert prob.goal_weights is None
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert prob.sample_goal(rng) is prob.goal and rng.bit_generator.state == state


def test_funnel_of_a_goal_region_keeps_states_near_the_goal(paper_model):
    # a region's tolerance is in its own units: the funnel must not drop the states within
    # that plain distance of the goal state (here all of them would go)
    from rrtcolearn.planning.connections import FunnelConnection
    from rrtcolearn.planning.rrt import RRTCoLearn

    def goal_fn(x):
        return 10.0 * np.abs(np.mod(x[:, 0] + np.pi, 2 * np.pi) - np.pi)

    prob = PlanningProblem.create(paper_model.system, [-np.pi, 0], [0, 0], 5.0, goal_fn=goal_fn)
    planner = RRTCoLearn(prob, paper_model.functions, paper_model.planner_settings())
    search = FunnelConnection.build(planner.propagator, np.random.default_rng(0), np.ones(2),
                                     300)
    near = np.linalg.norm(search.funnel.offsets, axis=1) < 5.0
    assert near.any()


def test_a_goal_function_or_sampler_that_goes_wrong_later_is_an_error(pendulum):
    """Answers are checked on every call, not only the first: a NaN or a wrong shape later
    in a plan is a ProblemError naming it, never a path ending at a NaN node."""
    from rrtcolearn.planning.problem import PlanningProblem, ProblemError

    def nan_far(x):  # fine at the goal and the start, NaN elsewhere
        d = np.abs(np.atleast_2d(x)[:, 0])
        return np.where((d < 1e-9) | (np.abs(d - np.pi) < 1e-9), d, np.nan)

    p = PlanningProblem.create(pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1, goal_fn=nan_far)
    with pytest.raises(ProblemError, match="not finite at"):
        p.goal_distance(np.array([[1.0, 0.0]]))
    short = PlanningProblem.create(pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1,
                                   goal_fn=lambda x: np.abs(np.atleast_2d(x)[:2, 0]))
    with pytest.raises(ProblemError, match=r"got shape \(2,\) for 3 states"):
        short.goal_distance(np.zeros((3, 2)))
    draws = iter([[0.0, 0.0], [np.nan, 0.0]])
    sampled = PlanningProblem.create(pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1,
                                     goal_fn=lambda x: np.abs(np.atleast_2d(x)[:, 0]),
                                     goal_sampler=lambda rng: next(draws))
    with pytest.raises(ProblemError, match="the goal sampler must return one finite state"):
        sampled.sample_goal(np.random.default_rng(0))
