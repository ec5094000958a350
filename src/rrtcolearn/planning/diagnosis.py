"""Why an unsolved plan stopped, in one line: the iterations' outcomes
(`contracts.OUTCOMES`) read as advice on what to change."""

from __future__ import annotations

_ADVICE = {
    "out_of_reach": "random targets lie beyond the data's reach of every node: widen "
                    "generate.max_state_distance or set plan.extend_distance",
    "invalid_query": "the validity model V rejects the queries from the tree (the data do "
                     "not cover these states): check that the start lies in the sampling box, "
                     "generate more simulations or raise learn.validity_threshold",
    "no_costate": "the steering parameters drawn around U's prediction give no costate on "
                  "H* = 0 (with tight input limits many directions have none): raise "
                  "plan.sigma or generate more data near the start",
    "input_limit": "edges break the input limit",
    "state_box": "edges leave the state constraints in a non-angle coordinate: widen them "
                 "(plan.state_low/state_high, default the sampling box generate.state_low/"
                 "state_high) so that they hold the motion",
    "obstacle": "edges run into obstacles at once: the start is boxed in, or the obstacles "
                "are thicker than the data's segments are long",
    "nonfinite": "integration overflowed: the dynamics blow up in the box, lower generate.dt",
}


def diagnose(outcomes: dict, stalled: bool, nodes: int, truncating: bool,
             progress: tuple[float, float] | None = None) -> str:
    """One line: why an unsolved plan stopped, what most often rejected a candidate and, with
    ``progress`` (the start's and the nearest node's distance to the goal region), how far
    the tree got toward the goal."""
    failed = {k: v for k, v in outcomes.items() if k != "added" and v}
    total = sum(outcomes.values())
    if not total:
        return "no iteration ran: raise the time or iteration limit"
    nodes_s = f"{nodes} node{'s' if nodes != 1 else ''}"
    if stalled:
        head = (f"the tree stopped growing ({nodes_s}, no new node for "
                "plan.stall_iterations iterations)")
    else:
        head = f"limit reached after {total} iteration{'s' if total != 1 else ''} with {nodes_s}"
    # targets out of reach are the normal lot of a small tree: name them only when nothing
    # else failed
    named = {k: v for k, v in failed.items() if k != "out_of_reach"} or failed
    worst = max(named, key=named.get) if named else None
    added = outcomes.get("added", 0)
    if worst is None or (not stalled and (2 * added >= total or 2 * failed[worst] < total)):
        # the limit stopped a tree that most iterations still grew, or that no one rejection
        # held back: the limit is to blame
        line = (f"{head}; {added / total:.0%} of the iterations added a node"
                + (": the tree was still growing" if 2 * added >= total else "")
                + " — raise the time or iteration limit")
        if worst is not None:
            line += (f" (most common rejection: {worst.replace('_', ' ')}, in "
                     f"{failed[worst]})")
    else:
        advice = _ADVICE[worst]
        if truncating and worst in ("invalid_query", "input_limit"):
            advice += _TRUNCATION_ADVICE
        line = (f"{head}; {failed[worst] / total:.0%} of the iterations: "
                f"{worst.replace('_', ' ')} — {advice}")
    if progress is not None:
        start, best = progress
        # (the goal test's distance: to the goal state for a ball, the user's to a region)
        line += (f"; nearest node {best:.3g} from the goal (the start: {start:.3g})"
                 + (": no progress toward the goal" if best >= 0.99 * start else ""))
    return line


# where limits are met by truncating unconstrained extremals, that is the likely cause
_TRUNCATION_ADVICE = (" (with limit_mode 'truncate', extremals that break the limit at once "
                      "leave no data: use 'saturate', where the optimal control rides the "
                      "limit)")

