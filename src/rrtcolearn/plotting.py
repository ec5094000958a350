"""Figures. Functions take an ``ax`` and return artists; they never call ``show()``."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.patches import Circle, Polygon, Rectangle

from rrtcolearn.data.store import atomic_write_bytes
from rrtcolearn.planning.tree import Plan


def plot_obstacles(ax, obstacles: list[dict], *, turns: tuple[int, ...] = (-1, 0, 1),
                   angle_dim: int | None = 0) -> list:
    """Shade obstacles (config dicts) in the first two state coordinates.

    Obstacles cover every turn of an angle coordinate, so boxes are drawn shifted by
    ``2*pi*k`` for each k in ``turns`` along ``angle_dim``.
    """
    artists = []
    style = {"facecolor": "tab:gray", "alpha": 0.35, "edgecolor": "k", "lw": 0.8}
    for k, ob in enumerate(obstacles):
        label = "obstacle" if k == 0 else None
        if ob["type"] == "box":
            lo, hi = np.asarray(ob["low"])[:2], np.asarray(ob["high"])[:2]
            for t in turns if angle_dim is not None else (0,):
                shift = np.zeros(2)
                if angle_dim is not None and angle_dim < 2:
                    shift[angle_dim] = 2 * np.pi * t
                artists.append(ax.add_patch(Rectangle(
                    tuple(lo + shift), *(hi - lo), label=label if t == 0 else None, **style)))
        elif ob["type"] == "halfplane":
            normal, offset = np.asarray(ob["normal"])[:2], float(ob["offset"])
            x0, x1 = ax.get_xlim()
            y0, y1 = ax.get_ylim()
            corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
            poly = _clip_halfplane(corners, normal, offset)
            if len(poly):
                artists.append(ax.add_patch(Polygon(poly, label=label, **style)))
    return artists


def plot_workspace(ax, spec: dict, states: np.ndarray, n_bodies: int = 12) -> list:
    """A planar workspace obstacle (`rrtcolearn.geometry`, plan-file form): its shapes, and
    the body at ``n_bodies`` states evenly spaced along ``states`` (the path), first and
    last included."""
    from rrtcolearn.geometry import Disc, Workspace
    ws = Workspace.from_dict(spec, states.shape[1])
    if ws.body.dim != 2:
        return []
    artists = []
    style = {"facecolor": "tab:gray", "alpha": 0.45, "edgecolor": "k", "lw": 0.8}
    for k, ob in enumerate(ws.obstacles):
        label = "workspace obstacle" if k == 0 else None
        patch = Circle(tuple(ob.center), ob.radius, label=label, **style) \
            if isinstance(ob, Disc) else Polygon(ob.vertices(), label=label, **style)
        artists.append(ax.add_patch(patch))
    ax.set_aspect("equal", adjustable="datalim")  # the bodies' true shapes
    picks = np.unique(np.linspace(0, len(states) - 1, n_bodies).round().astype(int))
    poses = ws.body.poses(states[picks])
    body_style = {"fill": False, "edgecolor": "tab:purple", "lw": 0.9}
    for i in range(len(picks)):
        for b, shape in enumerate(ws.body.shapes):
            x, y, th = poses[i, b]
            rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
            label = "body" if i == 0 and b == 0 else None
            if isinstance(shape, Disc):
                patch = Circle(tuple(rot @ shape.center + (x, y)), shape.radius, label=label,
                               **body_style)
            else:
                patch = Polygon(shape.vertices() @ rot.T + (x, y), label=label, **body_style)
            artists.append(ax.add_patch(patch))
    return artists


def _clip_halfplane(poly: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """The part of a convex polygon where normal . x >= offset (Sutherland-Hodgman)."""
    out = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        da, db = a @ normal - offset, b @ normal - offset
        if da >= 0:
            out.append(a)
        if da * db < 0:
            out.append(a + (b - a) * da / (da - db))
    return np.array(out)


def plot_tree(ax, plan: Plan, *, max_edges: int | None = None,
              dims: tuple[int, int] = (0, 1), labels: tuple[str, str] | None = None) -> list:
    """The tree projected on the state coordinates ``dims`` with the solution path
    highlighted (paper Fig. 2: the pendulum's (theta, omega) plane)."""
    i, j = dims
    tree = plan.tree
    trajs = tree.trajectories[1 : tree.n_nodes]
    if max_edges is not None:
        trajs = trajs[:max_edges]
    artists = []
    if trajs:
        lc = LineCollection([t[:, [i, j]] for t in trajs], colors="0.6", linewidths=0.6)
        artists.append(ax.add_collection(lc))
    states = tree.states[: tree.n_nodes]
    artists.append(ax.plot(states[:, i], states[:, j], ".", color="0.35", ms=2.5)[0])
    path = plan.path_nodes
    if len(path) > 1:
        pts = np.vstack([tree.trajectories[k][:, [i, j]] for k in path[1:]])
        artists.append(ax.plot(pts[:, 0], pts[:, 1], "-", color="tab:red", lw=1.8,
                               label=f"path (cost {plan.path_cost:.2f})")[0])
    artists.append(ax.plot(*plan.start[[i, j]], "o", color="tab:blue", label="start")[0])
    for k, goal in enumerate(_goal_images(plan, states, (i, j))):
        artists.append(ax.add_patch(Circle(tuple(goal), plan.goal_tolerance, fill=False,
                                           color="tab:green", lw=1.5)))
        artists.append(ax.plot(*goal, "*", color="tab:green", ms=10,
                               label="goal" if k == 0 else None)[0])
    if plan.obstacles and dims == (0, 1):
        ax.autoscale_view()
        artists += plot_obstacles(ax, plan.obstacles)
    for ob in plan.obstacles:
        if ob["type"] == "workspace" and tuple(ob["body"].get("pose", ())[:2]) == dims:
            path_states = np.vstack([tree.trajectories[k] for k in path[1:]]) \
                if len(path) > 1 else plan.start[None]
            artists += plot_workspace(ax, ob, path_states)
    xl, yl = labels or (r"$\theta$ [rad]", r"$\omega$ [rad/s]")
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    limit = f", |u| <= {plan.symmetric_limit:g}" if plan.symmetric_limit is not None else ""
    ax.set_title(f"{plan.system}{limit}: {plan.status}, {plan.nodes} nodes, "
                 f"{plan.iterations} iterations")
    ax.legend(loc="best", fontsize=8)
    ax.autoscale_view()
    return artists


def _goal_images(plan: Plan, states: np.ndarray, dims: tuple[int, int]) -> list[np.ndarray]:
    """The goal in the plane ``dims``, and with a goal test modulo a turn (``goal_angles``) its
    copies whole turns away that lie within the tree's extent."""
    goal = plan.goal[list(dims)]
    images = [goal]
    for axis, d in enumerate(dims):
        if d not in plan.goal_angles:
            continue
        lo, hi = states[:, d].min(), states[:, d].max()
        for base in list(images):
            for turns in (-2, -1, 1, 2):
                value = base[axis] + 2.0 * np.pi * turns
                if lo - plan.goal_tolerance <= value <= hi + plan.goal_tolerance:
                    image = base.copy()
                    image[axis] = value
                    images.append(image)
    return images


def save_figure(fig, path: str | Path, dpi: int = 120) -> None:
    """Save a figure atomically and close it."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".") or "png", dpi=dpi,
                bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def tree_figure(plan: Plan, state_names: tuple[str, ...] | None = None):
    """The tree in the (theta, omega) plane, or for n > 2 states one panel per
    (coordinate, its rate) pair, the first n/2 coordinates being positions."""
    n = len(plan.start)
    if n <= 2 or state_names is None or n % 2:
        fig, ax = plt.subplots(figsize=(6.4, 4.8))
        named = state_names is not None and n >= 2 and plan.system != "pendulum"
        plot_tree(ax, plan, labels=tuple(state_names[:2]) if named else None)
        return fig
    half = n // 2
    # a body among workspace shapes gets a panel of its own: the tree in its (x, y)
    planes = [tuple(ob["body"]["pose"][:2]) for ob in plan.obstacles
              if ob["type"] == "workspace" and len(ob["body"].get("pose", ())) in (2, 3)]
    panels = [(k, k + half) for k in range(half)] + planes[:1]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.4))
    for (i, j), ax in zip(panels, np.atleast_1d(axes), strict=True):
        plot_tree(ax, plan, dims=(i, j), labels=(state_names[i], state_names[j]))
    return fig
