"""Rigid bodies among workspace obstacles: the robot's shape, placed by its state, tested
exactly against boxes, discs and convex polygons in the plane (boxes and spheres in 3-D).

A `Workspace` is an obstacle of the planner's kind (`planning.validity`): ``contains(states)``
is True where a body touches an obstacle, for all states (N, n) of an edge in one compiled
call (every RK4 step, as state-space obstacles are). Exact, not inflated: convex polygons
(boxes are four-vertex polygons, turned by the heading) by the separating-axis test, a disc
against a polygon by its closest point. Closed sets: a body touching an obstacle collides.
Compiled (numba) because an edge has tens of states and a library call per edge costs more
than the test (bench/dynobench_bench.py measures shapely 2's vectorised predicates on the
same edges).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numba
import numpy as np

Poses = Callable[[np.ndarray], np.ndarray]
"""Forward kinematics: states (N, n) -> poses (N, B, 3) (x, y, heading) of B planar links."""


def _floats(value, what: str, length: int | tuple[int, ...] | None = None) -> np.ndarray:
    """``value`` as finite floats of ``length`` values; ValueError naming ``what``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers, got {value!r}") from None
    lengths = (length,) if isinstance(length, int) else length
    if a.ndim != 1 or (lengths is not None and a.size not in lengths):
        want = " or ".join(map(str, lengths)) if lengths else "some"
        raise ValueError(f"{what} must be a list of {want} numbers, got {value!r}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be finite, got {value!r}")
    return a


@dataclass(frozen=True)
class Box:
    """A box of side lengths ``size`` centred at ``center``, turned by ``angle`` (rad,
    2-D only); 2-D or 3-D by the length of ``center``."""

    center: np.ndarray
    size: np.ndarray
    angle: float = 0.0

    @property
    def dim(self) -> int:
        return self.center.size

    def vertices(self) -> np.ndarray:
        """(4, 2) corners counter-clockwise (2-D)."""
        hx, hy = self.size / 2.0
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        c, s = np.cos(self.angle), np.sin(self.angle)
        return local @ np.array([[c, s], [-s, c]]) + self.center

    def to_dict(self) -> dict:
        d = {"shape": "box", "center": self.center.tolist(), "size": self.size.tolist()}
        return {**d, "angle": self.angle} if self.angle else d


@dataclass(frozen=True)
class Disc:
    """A disc (2-D) or sphere (3-D) of ``radius`` centred at ``center``."""

    center: np.ndarray
    radius: float

    @property
    def dim(self) -> int:
        return self.center.size

    def to_dict(self) -> dict:
        return {"shape": "disc" if self.dim == 2 else "sphere", "center": self.center.tolist(),
                "radius": self.radius}


@dataclass(frozen=True)
class Polygon:
    """A convex polygon (2-D), vertices (K, 2) counter-clockwise."""

    points: np.ndarray
    dim: int = field(default=2, init=False)

    def vertices(self) -> np.ndarray:
        return self.points

    def to_dict(self) -> dict:
        return {"shape": "polygon", "vertices": self.points.tolist()}


Shape = Box | Disc | Polygon


def _convex_ccw(points: np.ndarray) -> np.ndarray:
    """``points`` (K, 2) counter-clockwise; ValueError unless a strictly convex polygon."""
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 3:
        raise ValueError("a polygon needs at least 3 vertices [x, y]")
    if not np.all(np.isfinite(points)):
        raise ValueError("polygon vertices must be finite")
    area = 0.5 * np.sum(points[:, 0] * np.roll(points[:, 1], -1)
                        - np.roll(points[:, 0], -1) * points[:, 1])
    if area < 0:
        points = points[::-1].copy()
    e = np.roll(points, -1, axis=0) - points
    turn = e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1)
    if area == 0 or np.any(turn <= 0):
        raise ValueError("a polygon must be convex with its vertices in order (no three "
                         "in a line)")
    return points


def shape_from_dict(spec: dict, dim: int | None = None) -> Shape:
    """A shape from its config form (``shape`` = box, disc, polygon, sphere); ValueError
    naming the key on a malformed one. ``dim`` (2 or 3) when the workspace's is known."""
    if not isinstance(spec, dict):
        raise ValueError(f"a shape must be a table, got {spec!r}")
    kind = spec.get("shape")
    known = {"box": {"shape", "center", "size", "angle"},
             "disc": {"shape", "center", "radius"}, "sphere": {"shape", "center", "radius"},
             "polygon": {"shape", "vertices"}}
    if kind not in known:
        raise ValueError(f"shape: unknown {kind!r}; use box, disc, polygon or sphere")
    extra = set(spec) - known[kind] - {"type"}
    if extra:
        raise ValueError(f"{sorted(extra)[0]}: not a key of a {kind} (keys: "
                         f"{', '.join(sorted(known[kind] - {'shape'}))})")
    for key in sorted(known[kind] - {"shape", "angle"}):
        if key not in spec and not (key == "center" and kind != "polygon"):
            raise ValueError(f"{key}: a {kind} needs it")
    dims = (dim,) if dim else (2, 3)
    if kind == "polygon":
        if dim == 3:
            raise ValueError("vertices: a polygon is 2-D, the workspace is 3-D")
        try:
            pts = np.asarray(spec["vertices"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"vertices must be [x, y] pairs, got {spec['vertices']!r}") from None
        try:
            return Polygon(_convex_ccw(pts))
        except ValueError as exc:
            raise ValueError(f"vertices: {exc}") from None
    if kind == "box":
        size = _floats(spec["size"], "size", dims)
        center = _floats(spec.get("center", np.zeros(size.size)), "center", size.size)
        if np.any(size <= 0):
            raise ValueError(f"size must be positive, got {spec['size']!r}")
        angle = spec.get("angle", 0.0)
        if not isinstance(angle, int | float) or isinstance(angle, bool) \
                or not np.isfinite(angle):
            raise ValueError(f"angle must be a number (rad), got {angle!r}")
        if angle and size.size == 3:
            raise ValueError("angle: 3-D boxes are axis-aligned")
        return Box(center, size, float(angle))
    want = (2,) if kind == "disc" else (3,)
    if dim and want != (dim,):
        raise ValueError(f"shape: a {kind} is {want[0]}-D, the workspace is {dim}-D")
    center = _floats(spec.get("center", np.zeros(want[0])), "center", want)
    radius = spec["radius"]
    if not isinstance(radius, int | float) or isinstance(radius, bool) \
            or not np.isfinite(radius) or radius < 0:
        raise ValueError(f"radius must be a number >= 0, got {radius!r}")
    return Disc(center, float(radius))


@dataclass(frozen=True)
class Body:
    """Rigid bodies the state places in the workspace.

    ``shapes`` are in the body's frame (a box's ``center`` is its offset from the reference
    point). The state places them by ``pose``: planar (ix, iy) or (ix, iy, itheta) state
    indices (position and heading), or 3-D (ix, iy, iz) (position; 3-D bodies do not turn);
    or, for links (an arm), by ``fk``: states (N, n) -> poses (N, len(shapes), 3), one
    planar pose per shape; a function, or its ``module:attribute`` name (so that a plan
    file records it and `check_plan` rebuilds it, as a system is named)."""

    shapes: tuple[Shape, ...]
    pose: tuple[int, ...] = ()
    fk: Poses | str | None = None

    def __post_init__(self) -> None:
        if not self.shapes:
            raise ValueError("shape: a body needs a shape")
        dims = {s.dim for s in self.shapes}
        if len(dims) != 1:
            raise ValueError("shape: a body's shapes must all be 2-D or all 3-D")
        if (self.fk is None) == (not self.pose):
            raise ValueError("pose: give the state indices of the pose, or a forward "
                             "kinematics function (not both)")
        if self.fk is not None and self.dim != 2:
            raise ValueError("fk: forward kinematics places planar links only")
        if self.pose and len(self.pose) not in ((2, 3) if self.dim == 2 else (3,)):
            want = "(ix, iy) or (ix, iy, itheta)" if self.dim == 2 else "(ix, iy, iz)"
            raise ValueError(f"pose: {want} state indices, got {list(self.pose)}")

    @property
    def dim(self) -> int:
        return self.shapes[0].dim

    def poses(self, states: np.ndarray) -> np.ndarray:
        """(N, B, 3) planar poses (x, y, heading) or 3-D positions of the shapes' frames."""
        x = np.atleast_2d(states)
        if self.fk is not None:
            fk = _named_function(self.fk) if isinstance(self.fk, str) else self.fk
            p = np.asarray(fk(x), dtype=np.float64)
            if p.shape != (len(x), len(self.shapes), 3):
                raise ValueError(f"fk must return poses of shape ({len(x)}, "
                                 f"{len(self.shapes)}, 3), got {p.shape}")
            return p
        p = np.zeros((len(x), 1, 3))
        p[:, 0, : len(self.pose)] = x[:, list(self.pose)]
        return np.repeat(p, len(self.shapes), axis=1)

    def to_dict(self) -> dict:
        d = (self.shapes[0].to_dict() if len(self.shapes) == 1
             else {"shapes": [s.to_dict() for s in self.shapes]})
        if self.pose:
            return {**d, "pose": list(self.pose)}
        return {**d, "fk": self.fk if isinstance(self.fk, str) else "a function"}

    @classmethod
    def from_dict(cls, spec: dict, n_states: int | None = None) -> Body:
        """A body from its config form: a shape's keys and ``pose`` (state indices);
        ValueError naming the key."""
        if not isinstance(spec, dict):
            raise ValueError(f"body must be a table, got {spec!r}")
        if "fk" in spec:
            fk = spec["fk"]
            if not isinstance(fk, str) or ":" not in fk or "pose" in spec:
                raise ValueError(f"fk: a body placed by forward kinematics is read from a "
                                 f"file by the function's module:attribute name (and no "
                                 f"pose), got {fk!r}")
            _named_function(fk)
            rest = {k: v for k, v in spec.items() if k != "fk"}
            shapes = rest.pop("shapes", None)
            parts = [shape_from_dict(s) for s in shapes] if shapes is not None and not rest \
                else [shape_from_dict(rest)]
            return cls(tuple(parts), fk=fk)
        if "pose" not in spec:
            raise ValueError("pose: a body needs the state indices of its pose")
        pose = spec["pose"]
        if not isinstance(pose, list | tuple) or not all(
                isinstance(i, int) and not isinstance(i, bool) for i in pose):
            raise ValueError(f"pose must be a list of state indices, got {pose!r}")
        if n_states is not None and any(not 0 <= i < n_states for i in pose):
            raise ValueError(f"pose: indices must lie in 0..{n_states - 1}, got {pose!r}")
        rest = {k: v for k, v in spec.items() if k != "pose"}
        shapes = rest.pop("shapes", None)
        parts = [shape_from_dict(s) for s in shapes] if shapes is not None and not rest \
            else [shape_from_dict(rest)]
        return cls(tuple(parts), tuple(pose))


def _named_function(name: str) -> Poses:
    """The function ``module:attribute`` names; ValueError naming it otherwise."""
    import importlib

    module, _, attribute = name.partition(":")
    try:
        fn = getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError, ValueError) as exc:
        raise ValueError(f"fk: cannot find {name!r} ({exc})") from None
    if not callable(fn):
        raise ValueError(f"fk: {name!r} is not a function")
    return fn


def _polygon_arrays(shapes: Sequence[Shape]) -> tuple[np.ndarray, ...]:
    """The kernel's form of 2-D shapes: vertices (M, K, 2) padded, vertex counts (M,) (0: a
    disc), disc radii (M,), and a bounding circle (M, 3) (centre, radius) for the
    broad phase."""
    verts = [s.vertices() if not isinstance(s, Disc) else s.center[None] for s in shapes]
    k = max([len(v) for v in verts] + [1])
    out = np.zeros((len(shapes), k, 2))
    count = np.zeros(len(shapes), dtype=np.int64)
    radius = np.zeros(len(shapes))
    bound = np.zeros((len(shapes), 3))
    for i, (s, v) in enumerate(zip(shapes, verts, strict=True)):
        out[i, : len(v)] = v
        if isinstance(s, Disc):
            radius[i] = s.radius
            bound[i] = (*s.center, s.radius)
        else:
            count[i] = len(v)
            c = v.mean(axis=0)
            bound[i] = (*c, np.sqrt(np.max(np.sum((v - c) ** 2, axis=1))))
    return out, count, radius, bound


@numba.njit(cache=True)
def _overlap_polys(a, na, b, nb) -> bool:
    """Whether convex polygons a[:na], b[:nb] (counter-clockwise) share a point: no
    edge normal of either separates them (separating-axis theorem; touching overlaps)."""
    for poly, n in ((a, na), (b, nb)):
        for k in range(n):
            j = (k + 1) % n
            nx = poly[j, 1] - poly[k, 1]
            ny = poly[k, 0] - poly[j, 0]
            lo_a, hi_a = np.inf, -np.inf
            for i in range(na):
                p = a[i, 0] * nx + a[i, 1] * ny
                lo_a, hi_a = min(lo_a, p), max(hi_a, p)
            lo_b, hi_b = np.inf, -np.inf
            for i in range(nb):
                p = b[i, 0] * nx + b[i, 1] * ny
                lo_b, hi_b = min(lo_b, p), max(hi_b, p)
            if hi_a < lo_b or hi_b < lo_a:
                return False
    return True


@numba.njit(cache=True)
def _overlap_poly_disc(a, na, cx, cy, r) -> bool:
    """Whether convex polygon a[:na] (counter-clockwise) and the closed disc (cx, cy, r)
    share a point: the centre inside, or the closest point of an edge within r."""
    inside = True
    best = np.inf
    for k in range(na):
        j = (k + 1) % na
        ex, ey = a[j, 0] - a[k, 0], a[j, 1] - a[k, 1]
        dx, dy = cx - a[k, 0], cy - a[k, 1]
        if ex * dy - ey * dx < 0:
            inside = False
        t = min(1.0, max(0.0, (dx * ex + dy * ey) / (ex * ex + ey * ey)))
        qx, qy = dx - t * ex, dy - t * ey
        best = min(best, qx * qx + qy * qy)
    return inside or best <= r * r


@numba.njit(cache=True)
def _collide_planar(poses, bverts, bcount, brad, bbound, overts, ocount, orad, obound, out):
    """out[i] = whether any body at poses[i] (B, 3) touches any obstacle."""
    n_bodies, k = bverts.shape[0], bverts.shape[1]
    world = np.empty((k, 2))
    for i in range(poses.shape[0]):
        hit = False
        for b in range(n_bodies):
            x, y, th = poses[i, b, 0], poses[i, b, 1], poses[i, b, 2]
            c, s = np.cos(th), np.sin(th)
            nv = bcount[b]
            for v in range(max(nv, 1)):
                world[v, 0] = x + c * bverts[b, v, 0] - s * bverts[b, v, 1]
                world[v, 1] = y + s * bverts[b, v, 0] + c * bverts[b, v, 1]
            bx = x + c * bbound[b, 0] - s * bbound[b, 1]
            by = y + s * bbound[b, 0] + c * bbound[b, 1]
            for o in range(overts.shape[0]):
                dx, dy = bx - obound[o, 0], by - obound[o, 1]
                reach = bbound[b, 2] + obound[o, 2]
                if dx * dx + dy * dy > reach * reach * (1.0 + 1e-9) + 1e-12:
                    continue  # the bounding circles are apart
                no = ocount[o]
                if nv > 0 and no > 0:
                    hit = _overlap_polys(world, nv, overts[o], no)
                elif nv > 0:
                    hit = _overlap_poly_disc(world, nv, overts[o, 0, 0], overts[o, 0, 1],
                                             orad[o])
                elif no > 0:
                    hit = _overlap_poly_disc(overts[o], no, world[0, 0], world[0, 1], brad[b])
                else:
                    dx, dy = world[0, 0] - overts[o, 0, 0], world[0, 1] - overts[o, 0, 1]
                    hit = dx * dx + dy * dy <= (brad[b] + orad[o]) ** 2
                if hit:
                    break
            if hit:
                break
        out[i] = hit


def _collide_spatial(body: Body, obstacles: Sequence[Shape], states: np.ndarray) -> np.ndarray:
    """3-D: axis-aligned boxes and spheres, by interval overlap and closest point."""
    pos = body.poses(states)  # (N, B, 3)
    hit = np.zeros(len(pos), dtype=bool)
    for bs in body.shapes:
        c = pos[:, 0] + bs.center  # 3-D bodies are placed by one position, unturned
        for ob in obstacles:
            if isinstance(bs, Box) and isinstance(ob, Box):
                gap = np.abs(c - ob.center) - (bs.size + ob.size) / 2.0
                hit |= np.all(gap <= 0, axis=1)
            elif isinstance(bs, Disc) and isinstance(ob, Disc):
                hit |= np.sum((c - ob.center) ** 2, axis=1) <= (bs.radius + ob.radius) ** 2
            else:
                box, sph = (bs, ob) if isinstance(bs, Box) else (ob, bs)
                centre_b = c if box is bs else np.broadcast_to(box.center, c.shape)
                centre_s = c if sph is bs else np.broadcast_to(sph.center, c.shape)
                near = np.clip(centre_s, centre_b - box.size / 2, centre_b + box.size / 2)
                hit |= np.sum((centre_s - near) ** 2, axis=1) <= sph.radius ** 2
    return hit


class Workspace:
    """The planner's obstacle for a body among workspace shapes: ``contains(states)`` (N,)
    is True where the body touches one of ``obstacles`` (2-D: boxes, discs, convex
    polygons; 3-D: axis-aligned boxes, spheres)."""

    def __init__(self, body: Body, obstacles: Sequence[Shape]):
        self.body = body
        self.obstacles = tuple(obstacles)
        if any(o.dim != body.dim for o in self.obstacles):
            raise ValueError(f"obstacles: the body is {body.dim}-D, every obstacle must be too")
        if body.dim == 2:
            self._body = _polygon_arrays(body.shapes)
            self._obstacles = _polygon_arrays(self.obstacles)

    def contains(self, states: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(states, dtype=np.float64))
        if not self.obstacles:
            return np.zeros(len(x), dtype=bool)
        if self.body.dim == 3:
            return _collide_spatial(self.body, self.obstacles, x)
        out = np.empty(len(x), dtype=bool)
        _collide_planar(np.ascontiguousarray(self.body.poses(x)), *self._body,
                        *self._obstacles, out)
        return out

    def to_dict(self) -> dict:
        return {"type": "workspace", "body": self.body.to_dict(),
                "shapes": [o.to_dict() for o in self.obstacles]}

    @classmethod
    def from_dict(cls, spec: dict, n_states: int | None = None) -> Workspace:
        """A workspace from its plan-file form {type, body, shapes}; ValueError naming the
        key on a malformed one."""
        if "body" not in spec:
            raise ValueError("body: workspace obstacles need the robot's body")
        body = Body.from_dict(spec["body"], n_states)
        shapes = spec.get("shapes", [])
        if not isinstance(shapes, list):
            raise ValueError(f"shapes must be a list of shapes, got {shapes!r}")
        return cls(body, [shape_from_dict(s, body.dim) for s in shapes])

    def inflated(self) -> Workspace:
        """The conservative stand-in this module replaces (a comparison row of the bench):
        a point at the body's reference among axis-aligned boxes grown by the body's
        half-diagonal on every side (2-D boxes only)."""
        if self.body.dim != 2 or not all(isinstance(o, Box) and not o.angle
                                         for o in self.obstacles):
            raise ValueError("inflation is defined here for axis-aligned 2-D boxes")
        reach = max(np.max(np.linalg.norm(s.vertices(), axis=1)) if not isinstance(s, Disc)
                    else np.linalg.norm(s.center) + s.radius for s in self.body.shapes)
        point = Body((Disc(np.zeros(2), 0.0),), self.body.pose[:2])
        return Workspace(point, [Box(o.center, o.size + 2.0 * reach) for o in self.obstacles])
