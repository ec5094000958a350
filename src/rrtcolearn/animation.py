"""Pictures of motion: a plan animated (bodies where the system declares them, else state
plots) and the spread of tracked against open-loop rollouts.

A system declares its drawing in ``defaults["geometry"]``: ``"module:function"`` naming a
function of states (K, n) that returns polylines (K, P, 2), each drawn as a chain of links
(the shipped pendulum, cart-pole, acrobot and planar quadrotor do; see their modules). A
string, not the function, so that the system's plain fields stay data (build records). Every
figure function returns its figure and never shows it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rrtcolearn.errors import ConfigError, EnvironmentProblem
from rrtcolearn.systems.base import System

__all__ = ["animate", "geometry_of", "tracking_figure"]

_MAX_FRAMES = 120  # GIFs of a few hundred kB at most


def geometry_of(system: System) -> Callable[[np.ndarray], list[np.ndarray]] | None:
    """The system's declared drawing function (module docstring), or None."""
    spec = system.defaults.get("geometry")
    if not spec:
        return None
    module, _, attribute = str(spec).partition(":")
    try:
        return getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"system {system.name!r}: its geometry {spec!r} cannot be loaded "
                          f"({exc})") from None


def _frames(t: np.ndarray, fps: float) -> np.ndarray:
    """Sample indices for real-time frames at ``fps`` (at most _MAX_FRAMES: slower then)."""
    count = min(_MAX_FRAMES, max(2, int(np.ceil(t[-1] * fps)) + 1))
    return np.unique(np.searchsorted(t, np.linspace(t[0], t[-1], count)).clip(0, len(t) - 1))


def animate(system: System, t: np.ndarray, states: np.ndarray, out: str | Path, *,
            fps: float = 20.0, title: str = "", dpi: int = 72) -> int:
    """Write an animation of ``states`` (K, n) at times ``t`` (K,) to ``out`` (.gif with
    pillow, .mp4 with ffmpeg): the bodies where the system declares a geometry, else its
    state coordinates against time with a moving cursor. Returns the number of frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation

    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ConfigError(f"--out {out}: give a .gif or .mp4 file")
    if suffix == ".mp4" and not animation.writers.is_available("ffmpeg"):
        raise EnvironmentProblem("writing .mp4 needs ffmpeg on the PATH (not found): write "
                                 "a .gif instead")
    frames = _frames(np.asarray(t, float), fps)
    shape = geometry_of(system)
    if shape is not None:
        polylines = shape(np.asarray(states, float))
        pts = np.concatenate([p.reshape(-1, 2) for p in polylines])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre, half = 0.5 * (lo + hi), 0.55 * max(float((hi - lo).max()), 1e-3)
        fig, ax = plt.subplots(figsize=(4, 4))
        ax.set_aspect("equal")  # a square view: the bodies undistorted
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.grid(alpha=0.3)
        tip = polylines[-1][:, -1]
        (trail,) = ax.plot([], [], color="0.6", lw=1)
        links = [ax.plot([], [], "o-", lw=3, ms=5, color=f"C{i}")[0]
                 for i in range(len(polylines))]

        def draw(i: int):
            k = frames[i]
            for line, p in zip(links, polylines, strict=True):
                line.set_data(p[k, :, 0], p[k, :, 1])
            trail.set_data(tip[: k + 1, 0], tip[: k + 1, 1])
            ax.set_title(f"{title}  t = {t[k]:.2f} s".strip(), fontsize=9)
            return [*links, trail]
    else:
        n = system.n_states
        fig, axes = plt.subplots(n, 1, figsize=(5, 1.2 * n + 0.6), sharex=True, squeeze=False)
        cursors = []
        for j, ax in enumerate(axes[:, 0]):
            ax.plot(t, states[:, j], lw=1)
            ax.set_ylabel(system.state_names[j], fontsize=8)
            cursors.append(ax.plot([], [], "o", color="C3")[0])
        axes[-1, 0].set_xlabel("t (s)")

        def draw(i: int):
            k = frames[i]
            for j, c in enumerate(cursors):
                c.set_data([t[k]], [states[k, j]])
            axes[0, 0].set_title(f"{title}  t = {t[k]:.2f} s".strip(), fontsize=9)
            return cursors
    fig.tight_layout(rect=(0, 0, 1, 0.95))  # room for the title's time
    anim = animation.FuncAnimation(fig, draw, frames=len(frames), blit=False)
    writer = animation.PillowWriter(fps=fps) if suffix == ".gif" else \
        animation.FFMpegWriter(fps=fps)
    out.parent.mkdir(parents=True, exist_ok=True)
    anim.save(str(out), writer=writer, dpi=dpi)
    plt.close(fig)
    return len(frames)


def tracking_figure(system: System, t: np.ndarray, nominal: np.ndarray,
                    runs: dict[str, np.ndarray], title: str = ""):
    """One panel per state coordinate: the nominal (t (K,), nominal (K, n)) and, per entry
    of ``runs`` (label -> states (N, K, n)), the median and the 5-95% band of the N runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = system.n_states
    fig, axes = plt.subplots(n, 1, figsize=(6, 1.5 * n + 0.8), sharex=True, squeeze=False)
    for j, ax in enumerate(axes[:, 0]):
        for c, (label, states) in enumerate(runs.items()):
            with np.errstate(all="ignore"):
                lo, mid, hi = np.nanpercentile(states[:, :, j], [5, 50, 95], axis=0)
            ax.fill_between(t, lo, hi, color=f"C{c + 1}", alpha=0.25, lw=0)
            ax.plot(t, mid, color=f"C{c + 1}", lw=1, label=f"{label} (median, 5-95%)")
        ax.plot(t, nominal[:, j], "k--", lw=1, label="nominal")
        ax.set_ylabel(system.state_names[j], fontsize=8)
        lim = (nominal[:, j].min(), nominal[:, j].max())
        pad = 0.5 * max(lim[1] - lim[0], 1e-3)
        ax.set_ylim(lim[0] - pad, lim[1] + pad)
    axes[0, 0].legend(fontsize=7, loc="best")
    axes[0, 0].set_title(title, fontsize=9)
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    return fig
