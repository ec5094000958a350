"""When each strategy is on: the one place that switches random controls and the goal
connections on, and the thresholds it switches them at.

From the start, by the settings: random controls with ``plan.control_edges = true`` (or no
learned functions), shooting with ``plan.goal_connect = true``, a funnel of
``plan.goal_funnel`` extremals, the LQR connection with ``plan.goal_lqr = true``. Left to the
planner (the setting None), each switches on when the tree stalls, by the rules below; a
setting false keeps it off.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rrtcolearn.planning.contracts import Progress
from rrtcolearn.planning.settings import PlannerSettings

# Shooting and the LQR connection switch on once this many goal-biased iterations in a row
# brought no node nearer the goal: the learned steering has stopped closing in, and a
# connection tried at every goal-biased iteration before then would spend CPU where the
# steering still gets nearer by itself. (Chosen with the derived settings of issue 16,
# commit 8ae003d; docs/derived_settings.md states the rule.)
CONNECT_AFTER = 50
# Random-control edges switch on once this many iterations in a row brought no node nearer
# the goal. 30, not 100: measured side by side on every problem with an input box
# (docs/derived_settings.md), the earlier switch cut the median CPU on the sparse_rrt
# acrobot and cart-pole and the quadrotor by 2-7x and on the torque-limited pendulum rows by
# 0.67-0.81x, at up to 15% higher first-path cost on the pendulum; a switch at once (1) was
# faster still there but raised that cost by 54%.
CONTROLS_AFTER = 30
# The automatic funnel switches on with shooting (same rule, CONNECT_AFTER), at FUNNEL_START
# extremals, and doubles, up to AUTO_FUNNEL, each time CONNECT_AFTER goal-biased iterations in
# a row found no tree node within its radius: a small funnel is cheap to build, a large one
# is near more nodes. Until issue 31 (docs/derived_settings.md, "The funnel's switch-on")
# the funnel was built at its full size only once shooting had failed from 20 nodes: on the
# unbounded cart-pole and acrobot that came thousands of iterations after the tree was near
# enough for the funnel to connect at its first or second try, and the 20 000 extremals'
# build took most of the CPU of a plan that then connected at once. Each part (the first and
# each doubling) is built once per query and reused by the query's later solves
# (`funnel.FunnelStream`; docs/anytime.md, "One funnel per query").
AUTO_FUNNEL = 20_000
FUNNEL_START = AUTO_FUNNEL // 8


@dataclass
class Allowance:
    """How often a goal connection whose attempt is a Newton solve from a tree node
    (shooting, the funnel's continuation: tens of ms to seconds each, where an iteration
    takes about one) may start one: each goal-biased iteration grants it 1 / (tries + 1) of
    an attempt, at most one held in reserve, so the k-th attempt in vain is followed by k
    goal-biased iterations of the tree's own growth before the next. Anytime planning's
    allowance (gains + 1) / (tries + 1) (`anytime`), with no gains: a connection that
    succeeds ends the solve. Counted in iterations, not CPU: the plan stays a function of the
    seed."""

    tries: int = 0
    waited: int = 1  # goal-biased iterations since the last attempt (at most tries + 1)

    def accrue(self) -> None:
        """A goal-biased iteration's grant (call once per `Connection.connect`); counted in
        whole iterations (tries + 1 of them make an attempt), so no rounding."""
        self.waited = min(self.waited + 1, self.tries + 1)

    def take(self) -> bool:
        """Start an attempt now, if the allowance holds one (then it is spent)."""
        if self.waited < self.tries + 1:
            return False
        self.waited = 0
        self.tries += 1
        return True


@dataclass
class Schedule:
    """Which strategies one solve may switch on by itself, which are on, and when each was
    switched on (``switched``: name -> iteration, recorded in the plan)."""

    controls: bool  # random-control edges possible (an input box, not plan.control_edges false)
    exploring: bool  # random-control edges on
    auto_connect: bool  # the planner may switch shooting on
    auto_funnel: bool  # ... and the funnel
    auto_lqr: bool  # ... and the LQR connection
    goal_lqr: bool = True  # the goal admits an LQR connection (`connections_due`)
    switched: dict = field(default_factory=dict)

    @classmethod
    def start(cls, settings: PlannerSettings, controls: bool, learned: bool,
              can_connect: bool, goal_lqr: bool = True) -> Schedule:
        """A new solve's schedule: ``controls`` whether random-control edges are possible,
        ``learned`` whether there are learned functions, ``can_connect`` whether shooting
        and the funnel can run (learned functions and ``params_from_costate``),
        ``goal_lqr`` whether the goal admits an LQR connection."""
        s = settings
        return cls(controls=controls,
                   exploring=controls and (s.control_edges is True or not learned),
                   auto_connect=s.goal_connect is None and can_connect,
                   auto_funnel=s.goal_funnel is None and can_connect,
                   auto_lqr=s.goal_lqr is None, goal_lqr=goal_lqr)

    @staticmethod
    def initial(settings: PlannerSettings) -> dict[str, int | bool]:
        """The connections on from the start by the settings: name -> True, or for the
        funnel its number of extremals."""
        s = settings
        return {name: on for name, on in (("shooting", s.goal_connect is True),
                                          ("funnel", s.goal_funnel),
                                          ("lqr", bool(s.goal_lqr))) if on}

    def controls_due(self, progress: Progress) -> bool:
        """Switch random controls on now (an ordinary iteration's start): the learned
        steering stalls."""
        if self.controls and not self.exploring and \
                progress.since_growth_nearer >= CONTROLS_AFTER:
            self.exploring = True
            self.switched["controls"] = progress.iterations
            return True
        return False

    def connections_due(self, progress: Progress, on: dict) -> list[str]:
        """The connections to switch on at this goal-biased iteration, before any is tried
        (``on``: the connections on, by name). The LQR connection also while random controls
        explore (where it works, it is what gets the random-control tree into a small goal
        region); shooting and the funnel then only where the goal admits no LQR connection
        (where it does, in the external problems shooting never reached the goal then, and
        took up to a third of the CPU; where it does not, nothing else connects: dynobench's
        second-order unicycle was solved in 0 of 10 seeds of 60 s)."""
        due = []
        if progress.since_nearer >= CONNECT_AFTER:
            if self.auto_lqr and on.get("lqr") is None:
                due.append("lqr")
            if not self.exploring or not self.goal_lqr:
                due += [name for name, auto in (("shooting", self.auto_connect),
                                                ("funnel", self.auto_funnel))
                        if auto and on.get(name) is None]
        for name in due:
            self.switched[name] = progress.iterations
        return due
