"""Tracking a plan (time-varying LQR, rollouts), the exported trajectory replayed as a robot's
follower would, and the track / animate commands."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from tests.test_cli import TINY, assert_one_line_error, invoke

from rrtcolearn import pipeline
from rrtcolearn.errors import ConfigError
from rrtcolearn.evaluate import sample_path
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.settings import PlannerSettings
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make
from rrtcolearn.tracking import TrackingController, check_truth, riccati_gains, rollouts


@pytest.fixture(scope="module")
def limited_run(tmp_path_factory):
    """A pendulum run at |u| <= 1 (saturated extremals) on tiny settings: its plan, solved or
    not, has a path of several edges whose inputs jump where they meet."""
    out = tmp_path_factory.mktemp("track") / "u1"
    result = invoke("run", "--seed", "3", "--u-max", "1", "--out", str(out), *TINY)
    assert result.exit_code == 0, result.output
    d = json.loads((out / "plan.json").read_text())
    assert len(d["path"]) >= 3
    return out


# --- an independent replay: numpy.interp of the CSV's inputs and a fine RK4 ---------------

def _pendulum(x, u):
    return np.array([x[1], math.sin(x[0]) + u[0]])


def _cartpole(x, u):
    """Tedrake's cart-pole (m_c 10, m_p 1, l 0.5, g 9.81, theta = 0 down), written here."""
    mc, mp, ell, g = 10.0, 1.0, 0.5, 9.81
    _, th, dp, dth = x
    s, c = math.sin(th), math.cos(th)
    d = mc + mp * s * s
    ddp = (u[0] + mp * s * (ell * dth * dth + g * c)) / d
    ddth = (-u[0] * c - mp * ell * dth * dth * c * s - (mc + mp) * g * s) / (ell * d)
    return np.array([dp, dth, ddp, ddth])


def _replay(f, t, x0, inputs, substeps=20):
    """RK4 at 1/``substeps`` of the rows' spacing, the input at every stage linearly
    interpolated in the rows by time (numpy.interp), as a trajectory follower does."""
    def u_at(tau):
        return np.array([np.interp(tau, t, col) for col in inputs.T])

    x = np.array(x0, dtype=float)
    grid = np.unique(t)
    for a, b in itertools.pairwise(grid):
        h = (b - a) / substeps
        for i in range(substeps):
            tau = a + i * h
            # a stage exactly on a row time takes the value on the side it integrates into
            k1 = f(x, u_at(min(tau + 1e-12, b)))
            k2 = f(x + 0.5 * h * k1, u_at(tau + 0.5 * h))
            k3 = f(x + 0.5 * h * k2, u_at(tau + 0.5 * h))
            k4 = f(x + h * k3, u_at(max(tau + h - 1e-12, a)))
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def _read_csv(path):
    lines = path.read_text().splitlines()
    header = [line for line in lines if line.startswith("#")]
    names = lines[len(header)].split(",")
    rows = np.array([[float(v) for v in line.split(",")] for line in lines[len(header) + 1:]])
    return header, names, rows


def test_exported_csv_replays_to_the_plans_end_pendulum(limited_run):
    plan_file = limited_run / "plan.json"
    result = invoke("export", str(plan_file))
    assert result.exit_code == 0, result.output
    header, names, rows = _read_csv(limited_run / "plan.csv")
    assert names == ["t", "theta", "omega", "torque", "lambda_theta", "lambda_omega", "edge"]
    assert any("seconds" in h for h in header) and any("two rows" in h for h in header)
    d = json.loads(plan_file.read_text())
    t, edge = rows[:, 0], rows[:, -1]
    # every join of two edges is two rows at one time, the later one the next edge's
    joins = np.flatnonzero(np.diff(t) == 0)
    assert len(joins) == len(d["path"]) - 1
    assert np.all(edge[joins + 1] == edge[joins] + 1)
    assert np.all(np.abs(rows[:, 3]) <= 1.0 + 1e-12)
    end = _replay(_pendulum, t, d["start"], rows[:, 3:4])
    assert np.linalg.norm(end - d["path"][-1]["to"]) < 1e-3
    # the samples of one row per time (the old export) blend the edges' inputs: far worse
    keep = np.r_[np.diff(t) > 0, True]
    blended = _replay(_pendulum, t[keep], d["start"], rows[keep, 3:4])
    assert np.linalg.norm(blended - d["path"][-1]["to"]) > 10 * np.linalg.norm(
        end - d["path"][-1]["to"])


def test_exported_samples_replay_on_the_shipped_cartpole():
    """A cart-pole path of extremal edges and a held-input edge, the costate drawn afresh at
    each join (as the planner draws them), exported and replayed. (A planned swing-up ends
    on the unstable upright, where an open-loop replay's small errors grow: docs/formats.md
    gives its figures.)"""
    system = make("cartpole")
    rng = np.random.default_rng(0)
    dt, w, x = 0.01, 1.0, np.zeros(4)
    path = []
    for i in range(6):
        if i == 3:
            e = {"from": x.tolist(), "control": [40.0], "costate": None, "duration": 0.2}
        else:
            while True:
                p = rng.uniform(system.param_low, system.param_high)[None]
                lam, ok = system.costate_from_params(x[None], p, w)
                if ok[0]:
                    break
            e = {"from": x.tolist(), "control": None, "costate": lam[0].tolist(),
                 "duration": 0.3}
        path.append(e)
        x = sample_path(system, {"path": [e], "time_weight": w, "dt": dt})["state"][-1]
    s = sample_path(system, {"path": path, "time_weight": w, "dt": dt})
    assert np.count_nonzero(np.diff(s["t"]) == 0) == len(path) - 1
    jumps = np.abs(np.diff(s["input"][:, 0]))[np.diff(s["t"]) == 0]
    assert jumps.max() > 1.0  # the inputs do jump at the joins
    end = _replay(_cartpole, s["t"], np.zeros(4), s["input"], substeps=10)
    assert np.linalg.norm(end - x) < 1e-3


def test_a_planned_cartpole_swing_up_replays_to_its_end(tmp_path):
    """The shipped cart-pole swung up to the unstable upright under |f| <= 219.9 N (50% of its
    unbounded need), planned with random controls and the goal LQR at a 2.5 ms step, written,
    exported by the CLI and replayed open-loop: it ends on the plan's end. An open-loop
    replay meets the plan's own integration error grown through the upright's instability
    (docs/formats.md measures it: at the 10 ms default step this plan family lands 7e-5 to
    1.2e-3 away), so the step is the plan's, not the replay's, to choose."""
    system = make("cartpole")
    d = system.defaults
    problem = PlanningProblem.create(system, d["start"], d["goal"], 0.3, u_max=219.9,
                                     wrap_goal=True)
    plan = RRTCoLearn(problem, None, PlannerSettings(dt=0.0025, control_edges=True,
                                                     max_duration=0.5, goal_lqr=True)).solve(
        TerminationCondition(None, 20000), 0)
    assert plan.solved and plan.extra["connection"] == "lqr"
    pipeline.write_plan(plan, tmp_path / "plan.json")
    result = invoke("export", str(tmp_path / "plan.json"), "--system", "cartpole")
    assert result.exit_code == 0, result.output
    _, names, rows = _read_csv(tmp_path / "plan.csv")
    assert names[:6] == ["t", "p", "theta", "p_dot", "theta_dot", "force"]
    saved = json.loads((tmp_path / "plan.json").read_text())
    end = np.array(saved["path"][-1]["to"])
    assert abs(np.angle(np.exp(1j * (end[1] - np.pi)))) < 0.3  # upright, either way
    assert np.all(np.abs(rows[:, 5]) <= 219.9 + 1e-9)
    replayed = _replay(_cartpole, rows[:, 0], saved["start"], rows[:, 5:6], substeps=2)
    assert np.linalg.norm(replayed - end) < 1e-3


# --- the controller ------------------------------------------------------------------------

def test_riccati_recursion_converges_to_the_dare():
    from scipy.linalg import solve_discrete_are

    pendulum = make("pendulum")
    from rrtcolearn.planning.lqr import step_jacobians

    a, b = step_jacobians(pendulum, np.zeros(2), np.zeros(1), 0.01)  # upright: unstable
    assert np.abs(np.linalg.eigvals(a)).max() > 1
    Q, R = np.diag([0.3, 0.1]), np.array([[0.02]])
    N = 4000
    K, P = riccati_gains(np.repeat(a[None], N, 0), np.repeat(b[None], N, 0), Q, R, np.eye(2))
    P_inf = solve_discrete_are(a, b, Q, R)
    K_inf = np.linalg.solve(R + b.T @ P_inf @ b, b.T @ P_inf @ a)
    np.testing.assert_allclose(P[0], P_inf, rtol=1e-8)
    np.testing.assert_allclose(K[0], K_inf, rtol=1e-8)
    assert not np.allclose(P[-2], P_inf, rtol=1e-3)  # the end feels the terminal cost
    K_steps, _ = riccati_gains(np.repeat(a[None], N, 0), np.repeat(b[None], N, 0), Q,
                               np.repeat(R[None], N, 0), np.eye(2))  # R given per step
    np.testing.assert_array_equal(K_steps, K)


@pytest.fixture(scope="module")
def controller(limited_run):
    d = pipeline.read_plan(limited_run / "plan.json")
    return TrackingController.build(pipeline.plan_system(d), d), d


def test_tracking_on_the_exact_model_reproduces_the_plan(controller):
    c, d = controller
    open_loop, tracked = rollouts(c, 2)
    steps = np.cumsum([round(e["duration"] / d["dt"]) for e in d["path"]])
    for runs in (open_loop, tracked):
        for k, e in zip(steps, d["path"], strict=True):
            np.testing.assert_allclose(runs.states[:, k], np.repeat([e["to"]], 2, 0),
                                       atol=1e-6)
    assert np.all(np.abs(tracked.inputs) <= 1.0)


def test_weights_are_brysons_times_the_factor_the_self_test_picks(controller):
    """Q and R by hand for the pendulum at |u| <= 1 (angle: half a turn; omega in
    [-pi, pi]; torque box half-width 1; the room rule: the distance of each step's stage
    inputs to the bound they push toward, at least 0.3), the terminal cost the goal test's
    squared distance (the goal weights are 1: the identity), and the self-test redone with a
    pendulum written here whose torque acts at 0.8 of the model's, on its clock and on one 5%
    and one 10% slower."""
    from rrtcolearn.planning.lqr import step_jacobians
    from rrtcolearn.tracking import SELF_TEST

    c, d = controller
    system, dt = pipeline.plan_system(d), d["dt"]
    Q_hand = dt * np.diag([1 / np.pi**2, 1 / np.pi**2])
    R_hand = np.array([[dt * 1.0]])
    jac = [step_jacobians(system, x, u, dt)
           for x, u in zip(c.nominal.state[:-1], c.nominal.input[:-1], strict=True)]
    A, B = np.array([a for a, _ in jac]), np.array([b for _, b in jac])
    u = c.nominal.stage_inputs[:, :, 0]
    room = np.maximum(np.where(u >= 0, 1.0 - u, u + 1.0).min(axis=1), 0.3)
    assert room.min() == 0.3 and room.max() > 0.9  # the plan rides its bound and leaves it
    R_room = (dt / room**2)[:, None, None]
    fixed = {(rule, w): TrackingController.build(system, d, ladder=(w,), input_rules=(rule,))
             for rule in ("box", "room") for w in (1.0, 1e4)}
    np.testing.assert_array_equal(c.P[-1], np.eye(2))
    for (rule, w), f in fixed.items():
        K, _ = riccati_gains(A, B, w * Q_hand, R_hand if rule == "box" else R_room, np.eye(2))
        np.testing.assert_allclose(f.K, K, rtol=1e-9, atol=1e-12)
        assert (f.input_rule, f.state_weight) == (rule, w)
    np.testing.assert_array_equal(
        TrackingController.build(system, d, ladder=(10.0,), state_weight=2.0,
                                 input_rules=("box",)).K,
        TrackingController.build(system, d, ladder=(20.0,), input_rules=("box",)).K)
    with pytest.raises(ConfigError, match="input rules"):
        TrackingController.build(system, d, ladder=(1.0,), input_rules=("bryson",))

    class SlowerWeakerPendulum:  # s (omega, sin(theta) + 0.8 u), written here
        state_names, input_names, angle_dims = ("theta", "omega"), ("torque",), (0,)
        name = "slower, weaker"
        state_low, state_high = system.state_low, system.state_high

        def __init__(self, clock):
            self.clock = clock

        def dynamics(self, x, u):
            return self.clock * np.column_stack([x[:, 1], np.sin(x[:, 0]) + 0.8 * u[:, 0]])

    assert SELF_TEST["input_scale"] == 0.8 and SELF_TEST["clocks"] == (1.0, 0.95, 0.9)
    scores = {}
    for w, f in fixed.items():
        shares, medians = [], []
        for clock in (1.0, 0.95, 0.9):
            _, runs = rollouts(f, SELF_TEST["runs"], truth=SlowerWeakerPendulum(clock),
                               noise=SELF_TEST["noise"], start_error=SELF_TEST["start_error"],
                               seed=SELF_TEST["seed"])
            dist = np.linalg.norm(runs.states[:, -1] - np.array(d["goal"]), axis=1)
            shares.append(np.mean(dist <= 2 * d["goal_tolerance"]))
            medians.append(np.median(dist))
        scores[w] = (-np.mean(shares), np.prod(medians) ** (1 / 3))
    assert len(set(scores.values())) > 1
    picked = TrackingController.build(system, d, ladder=(1.0, 1e4))
    assert (picked.input_rule, picked.state_weight) == min(scores, key=scores.get)
    np.testing.assert_array_equal(picked.K, fixed[picked.input_rule, picked.state_weight].K)


def test_tracking_corrects_a_start_error_open_loop_does_not(controller):
    c, _ = controller
    open_loop, tracked = rollouts(c, 20, start_error=0.01, noise=1e-3, seed=1)
    ol = np.linalg.norm(c.deviation(open_loop.states[:, -1], c.nominal.steps), axis=1)
    tr = np.linalg.norm(c.deviation(tracked.states[:, -1], c.nominal.steps), axis=1)
    assert np.median(tr) < 0.5 * np.median(ol), (np.median(tr), np.median(ol))
    assert np.all(np.abs(tracked.inputs) <= 1.0 + 1e-12)  # clipped to the box


def test_rollouts_are_deterministic_per_seed(controller):
    c, _ = controller
    a = rollouts(c, 5, start_error=0.01, noise=1e-3, seed=7)
    b = rollouts(c, 5, start_error=0.01, noise=1e-3, seed=7)
    other = rollouts(c, 5, start_error=0.01, noise=1e-3, seed=8)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.states, y.states)
        np.testing.assert_array_equal(x.inputs, y.inputs)
    assert not np.array_equal(a[1].states, other[1].states)


def test_controller_input_at_the_nominal_is_the_nominal_input(controller):
    c, _ = controller
    k = c.nominal.steps // 2
    t = c.nominal.t[k]
    np.testing.assert_allclose(c.input(t, c.nominal.state[k]), c.nominal.input[k], atol=1e-12)
    pushed = c.input(t, c.nominal.state[k] + np.array([0.0, 0.05]))
    assert pushed[0] != c.nominal.input[k][0] or abs(pushed[0]) == 1.0


def test_a_true_system_must_have_the_plans_states_and_inputs(limited_run):
    pendulum = make("pendulum")
    with pytest.raises(ConfigError, match="same states and inputs"):
        check_truth(pendulum, make("double_integrator"))
    check_truth(pendulum, make("examples.heavier:pendulum"))
    result = invoke("track", str(limited_run / "plan.json"), "--true-system",
                    "double_integrator", "--rollouts", "2")
    assert_one_line_error(result, 2, "same states and inputs")


# --- the commands ---------------------------------------------------------------------------

def test_track_command_reports_open_loop_beside_tracked(limited_run, tmp_path):
    figure = tmp_path / "track.png"
    args = ["track", str(limited_run / "plan.json"), "--rollouts", "6", "--start-error",
            "0.01", "--noise", "0.001", "--seed", "2", "--true-system",
            "examples.heavier:pendulum"]
    result = invoke(*args, "--plot", str(figure))
    assert result.exit_code == 0, result.output
    assert "open-loop" in result.output and "tracked" in result.output
    row = next(line for line in result.output.splitlines() if "inputs within the box" in line)
    assert row.count("True") == 2
    assert figure.stat().st_size > 10_000
    again = invoke(*args)
    table = [line for line in result.output.splitlines() if "│" in line]
    assert table == [line for line in again.output.splitlines() if "│" in line]


def test_export_gains(limited_run, tmp_path):
    out = tmp_path / "traj.csv"
    result = invoke("export", str(limited_run / "plan.json"), "--gains", "--out", str(out))
    assert result.exit_code == 0, result.output
    header, names, rows = _read_csv(tmp_path / "traj-gains.csv")
    assert names == ["t", "theta", "omega", "torque", "K_torque_theta", "K_torque_omega"]
    assert any("clip(u_nom - K (x - x_nom)" in h for h in header)
    d = pipeline.read_plan(limited_run / "plan.json")
    c = TrackingController.build(pipeline.plan_system(d), d)
    np.testing.assert_allclose(rows[:-1, 4:], c.K[:, 0, :])
    assert np.all(np.diff(rows[:, 0]) > 0)
    result = invoke("export", str(limited_run / "plan.json"), "--gains", "--format", "npz",
                    "--out", str(tmp_path / "traj.npz"))
    assert result.exit_code == 0, result.output
    with np.load(tmp_path / "traj-gains.npz", allow_pickle=False) as z:
        np.testing.assert_allclose(z["K"][:-1], c.K)


def test_animate_command_writes_a_gif(limited_run, tmp_path):
    from PIL import Image

    out = tmp_path / "swing.gif"
    result = invoke("animate", str(limited_run / "plan.json"), "--out", str(out), "--fps", "10")
    assert result.exit_code == 0, result.output
    with Image.open(out) as gif:
        assert gif.format == "GIF" and gif.n_frames > 5
    assert_one_line_error(invoke("animate", str(limited_run / "plan.json"), "--out",
                                 str(tmp_path / "x.avi")), 2, ".gif or .mp4")


def test_shipped_geometries_draw_the_bodies():
    from rrtcolearn.systems import acrobot, cartpole, pendulum, quadrotor

    (link,) = pendulum.geometry(np.array([[0.0, 0.0], [np.pi / 2, 0.0]]))
    np.testing.assert_allclose(link[:, 1], [[0.0, 1.0], [1.0, 0.0]], atol=1e-12)  # up, right
    cart, pole = cartpole.geometry(np.array([[1.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(pole[0, 1], [1.0, -0.5])  # hanging below the cart
    np.testing.assert_allclose(cart[0, [0, -1]], cart[0, [-1, 0]])  # a closed outline
    np.testing.assert_allclose(cart[0, :4].mean(axis=0), [1.0, 0.0])  # about the cart
    (arm,) = acrobot.geometry(np.array([[np.pi, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(arm[0, -1], [0.0, 3.0], atol=1e-12)  # upright: l1 + l2
    frame = quadrotor.geometry(np.array([[0.0, 1.0, 0.0, 0, 0, 0]]))[0]
    np.testing.assert_allclose(frame[0], [[-0.25, 1.0], [0.25, 1.0]])


def test_a_system_without_geometry_is_animated_as_state_plots(tmp_path):
    import dataclasses

    from PIL import Image

    from rrtcolearn.animation import animate

    system = make("pendulum")
    plain = dataclasses.replace(system, defaults={k: v for k, v in system.defaults.items()
                                                  if k != "geometry"})
    t = np.linspace(0, 1, 51)
    states = np.column_stack([np.sin(t), np.cos(t)])
    assert animate(plain, t, states, tmp_path / "s.gif", fps=10) == 11
    with Image.open(tmp_path / "s.gif") as gif:
        assert gif.n_frames == 11
