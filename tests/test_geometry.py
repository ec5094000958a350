"""Bodies among workspace shapes (rrtcolearn.geometry) against brute-force references
written here: polygons by segment crossings and point-in-polygon, discs by dense sampling."""

import numpy as np
import pytest

from rrtcolearn.geometry import Body, Box, Disc, Polygon, Workspace, shape_from_dict
from rrtcolearn.planning.problem import PlanningProblem, ProblemError
from rrtcolearn.planning.validity import obstacle_from_dict


def corners(cx, cy, w, h, a):
    """A turned rectangle's corners, written out by hand."""
    out = []
    for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        lx, ly = sx * w / 2, sy * h / 2
        out.append((cx + lx * np.cos(a) - ly * np.sin(a), cy + lx * np.sin(a) + ly * np.cos(a)))
    return out


def cross(o, a, b):
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def segments_meet(p, q, r, s):
    d1, d2, d3, d4 = cross(r, s, p), cross(r, s, q), cross(p, q, r), cross(p, q, s)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and 0 not in (d1, d2, d3, d4):
        return True

    def on(a, b, c):  # c on segment ab, given collinear
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and \
            min(a[1], b[1]) <= c[1] <= max(a[1], b[1])
    return (d1 == 0 and on(r, s, p)) or (d2 == 0 and on(r, s, q)) or \
        (d3 == 0 and on(p, q, r)) or (d4 == 0 and on(p, q, s))


def inside(pt, poly):
    """Ray casting (even-odd), any vertex order."""
    c = False
    for (x1, y1), (x2, y2) in zip(poly, poly[1:] + poly[:1], strict=True):
        if (y1 > pt[1]) != (y2 > pt[1]):
            if pt[0] < x1 + (pt[1] - y1) * (x2 - x1) / (y2 - y1):
                c = not c
    return c


def polys_meet(a, b):
    edges = lambda p: list(zip(p, p[1:] + p[:1], strict=True))  # noqa: E731
    return any(segments_meet(p, q, r, s) for p, q in edges(a) for r, s in edges(b)) \
        or inside(a[0], b) or inside(b[0], a)


def disc_distance(poly, c):
    """Distance from c to the polygon's boundary by 4000 points on each edge."""
    t = np.linspace(0, 1, 4000)[:, None]
    pts = np.concatenate([np.array(p) + t * (np.array(q) - np.array(p))
                          for p, q in zip(poly, poly[1:] + poly[:1], strict=True)])
    return np.min(np.linalg.norm(pts - c, axis=1))


BODY = Body((Box(np.zeros(2), np.array([0.5, 0.25])),), (0, 1, 2))


def test_turned_boxes_against_segment_crossings():
    rng = np.random.default_rng(1)
    hits = 0
    for _ in range(1500):
        ob = rng.uniform([-1, -1, 0.1, 0.1, -3], [1, 1, 1.0, 1.0, 3])
        ws = Workspace(BODY, [Box(ob[:2], ob[2:4], float(ob[4]))])
        x = rng.uniform([-1.2, -1.2, -3], [1.2, 1.2, 3])
        want = polys_meet(corners(*x[:2], 0.5, 0.25, x[2]), corners(*ob))
        assert ws.contains(x[None])[0] == want, (x, ob)
        hits += want
    assert 200 < hits < 1300  # both answers well represented


def test_box_against_disc_by_dense_sampling():
    rng = np.random.default_rng(2)
    checked = 0
    for _ in range(600):
        c, r = rng.uniform(-1, 1, 2), rng.uniform(0.05, 0.5)
        x = rng.uniform([-1, -1, -3], [1, 1, 3])
        body = corners(*x[:2], 0.5, 0.25, x[2])
        d = 0.0 if inside(tuple(c), body) else disc_distance(body, c)
        if abs(d - r) < 1e-3:  # the sampling's resolution
            continue
        assert Workspace(BODY, [Disc(c, r)]).contains(x[None])[0] == (d <= r)
        checked += 1
    assert checked > 550


def test_disc_body_and_polygon_obstacle():
    hexagon = [(np.cos(a), np.sin(a)) for a in np.linspace(0, 2 * np.pi, 7)[:-1]]
    disc_body = Body((Disc(np.array([0.2, 0.0]), 0.3),), (0, 1, 2))  # off the reference
    ws = Workspace(disc_body, [Polygon(np.array(hexagon))])
    rng = np.random.default_rng(3)
    for _ in range(400):
        x = rng.uniform([-2, -2, -3], [2, 2, 3])
        c = x[:2] + 0.2 * np.array([np.cos(x[2]), np.sin(x[2])])
        d = 0.0 if inside(tuple(c), hexagon) else disc_distance(hexagon, c)
        if abs(d - 0.3) > 1e-3:
            assert ws.contains(x[None])[0] == (d <= 0.3)


def test_crossing_boxes_with_no_corner_inside_collide():
    # a plus sign: no corner of either box lies in the other (a corner test misses it)
    ws = Workspace(Body((Box(np.zeros(2), np.array([2.0, 0.5])),), (0, 1, 2)),
                   [Box(np.zeros(2), np.array([0.5, 2.0]))])
    assert ws.contains(np.array([[0.0, 0.0, 0.0]]))[0]


def test_grazing_a_corner_collides_and_a_hair_away_is_free():
    eps = 2.0 ** -20
    unit = Body((Box(np.zeros(2), np.ones(2)),), (0, 1, 2))
    corner = Workspace(unit, [Box(np.array([1.5, 1.5]), np.ones(2))])  # corner (1, 1)
    assert corner.contains(np.array([[0.5, 0.5, 0.0]]))[0]
    assert not corner.contains(np.array([[0.5 - eps, 0.5, 0.0]]))[0]
    # a diamond's corner on the body's edge
    diamond = np.array([[1.0, 0.5], [1.5, 0.0], [2.0, 0.5], [1.5, 1.0]])
    ws = Workspace(unit, [Polygon(diamond)])
    assert ws.contains(np.array([[0.5, 0.5, 0.0]]))[0]
    assert not ws.contains(np.array([[0.5 - eps, 0.5, 0.0]]))[0]
    # a disc body grazing a box corner: centre (1, 1) + (0.75, 1), radius 1.25 (exact)
    disc = Body((Disc(np.zeros(2), 1.25),), (0, 1))
    ws = Workspace(disc, [Box(np.array([0.5, 0.5]), np.ones(2))])
    assert ws.contains(np.array([[1.75, 2.0]]))[0]
    assert not ws.contains(np.array([[1.75, 2.0 + eps]]))[0]


def test_vectorised_equals_one_state_at_a_time():
    ws = Workspace(BODY, [Box(np.array([0.3, 0.3]), np.array([0.5, 0.25])),
                          Disc(np.array([1.0, 0.0]), 0.3),
                          Polygon(np.array([[0.0, -1.0], [0.5, -0.8], [0.2, -0.5]]))])
    x = np.random.default_rng(4).uniform([-1, -1, -3], [2, 1, 3], (500, 3))
    batch = ws.contains(x)
    assert batch.dtype == bool and 50 < batch.sum() < 450
    assert np.array_equal(batch, [ws.contains(s[None])[0] for s in x])


def test_links_placed_by_forward_kinematics():
    # a two-link arm (unit links, thin boxes) over a ceiling box: the states' angles place it
    def fk(x):
        a1, a2 = x[:, 0], x[:, 0] + x[:, 1]
        e1 = np.stack([np.cos(a1), np.sin(a1)], 1)
        e2 = e1 + np.stack([np.cos(a2), np.sin(a2)], 1)
        return np.stack([np.column_stack([0.5 * e1, a1]),
                         np.column_stack([e1 + 0.5 * (e2 - e1), a2])], 1)

    link = Box(np.zeros(2), np.array([1.0, 0.1]))
    ws = Workspace(Body((link, link), fk=fk), [Box(np.array([0.0, 2.4]), np.array([4.0, 1.0]))])
    up, down = np.pi / 2, -np.pi / 2
    # straight up the arm reaches y = 2, into the ceiling from y = 1.9; with the elbow bent
    # level it stays below y = 1.05
    assert ws.contains(np.array([[up, 0.0]]))[0]
    assert not ws.contains(np.array([[down, 0.0], [up, np.pi / 2]])).any()


def test_spatial_boxes_and_spheres_by_sampling():
    body = Body((Box(np.zeros(3), np.array([0.4, 0.2, 0.1])),), (0, 1, 2))
    sphere_body = Body((Disc(np.zeros(3), 0.3),), (0, 1, 2))
    obstacles = [Box(np.array([1.0, 0.0, 0.0]), np.array([0.5, 0.5, 0.5])),
                 Disc(np.array([-1.0, 0.0, 0.0]), 0.4)]
    grid = np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, 41)] * 3), -1).reshape(-1, 3)
    rng = np.random.default_rng(5)
    x = rng.uniform(-1.6, 1.6, (300, 3))
    for b, pts in ((body, grid * [0.4, 0.2, 0.1]), (sphere_body, grid[np.linalg.norm(
            grid, axis=1) <= 0.5] * 0.6)):
        got = Workspace(b, obstacles).contains(x)
        for xi, g in zip(x, got, strict=True):
            p = xi + pts
            in_box = np.all(np.abs(p - obstacles[0].center) <= 0.25, axis=1)
            in_sph = np.linalg.norm(p - obstacles[1].center, axis=1) <= 0.4
            want = bool((in_box | in_sph).any())
            if want != g:  # only where the sampling grid is too coarse to see a touch
                gap = 0.0125 * np.sqrt(3)
                assert Workspace(b, obstacles).contains((xi + gap * np.eye(3)).tolist() +
                                                        (xi - gap * np.eye(3)).tolist()).any()


def test_a_problem_with_a_body_rejects_a_start_in_collision():
    from rrtcolearn.systems import make
    quad = make("quadrotor")  # x, z, theta, ...: a 0.6 x 0.2 frame that turns
    spec = {"type": "workspace", "body": {"shape": "box", "size": [0.6, 0.2], "pose": [0, 1, 2]},
            "shapes": [{"shape": "box", "center": [0.0, 1.0], "size": [0.5, 0.5]}]}
    ws = obstacle_from_dict(spec, quad.n_states)
    assert Workspace.from_dict(ws.to_dict(), quad.n_states).to_dict() == ws.to_dict()
    goal = [1, 0, 0, 0, 0, 0]
    with pytest.raises(ProblemError, match=r"start .* inside an obstacle"):
        PlanningProblem.create(quad, [0.5, 0.8, 0, 0, 0, 0], goal, obstacles=[spec])
    # level at x = 0.56 the frame's end (0.56 - 0.3) clears the box's side at 0.25, turned
    # (on any turn) too; at x = 0.54 it overlaps
    prob = PlanningProblem.create(quad, [0.56, 1.0, 0, 0, 0, 0], goal, obstacles=[spec])
    x = np.array([[0.56, 1.0, 0.0, 0, 0, 0], [0.56, 1.0, 1.0, 0, 0, 0],
                  [0.56, 1.0, 2 * np.pi + 1.0, 0, 0, 0], [0.54, 1.0, 0.0, 0, 0, 0]])
    assert prob.validity(x).tolist() == [True, True, True, False]


@pytest.mark.parametrize("spec, key", [
    ({"shape": "box", "center": [0, 0]}, "size"),
    ({"shape": "box", "size": [1, -1]}, "size"),
    ({"shape": "box", "size": [1, 1], "radius": 2}, "radius"),
    ({"shape": "disc", "center": [0, 0], "radius": "a"}, "radius"),
    ({"shape": "blob"}, "shape"),
    ({"shape": "polygon", "vertices": [[0, 0], [1, 1], [2, 2]]}, "vertices"),
    ({"shape": "polygon", "vertices": [[0, 0], [1, 0], [0, 1], [1, 1]]}, "vertices"),
    ({"shape": "box", "size": [1, 1, 1], "angle": 0.3}, "angle"),
])
def test_bad_shapes_name_the_key(spec, key):
    with pytest.raises(ValueError, match=f"^{key}"):
        shape_from_dict(spec)


def test_bad_bodies_name_the_key():
    for body, key in (({"shape": "box", "size": [1, 1]}, "pose"),
                      ({"shape": "box", "size": [1, 1], "pose": [0, 9]}, "pose"),
                      ({"shape": "box", "size": [1, 1, 1], "pose": [0, 1]}, "pose")):
        with pytest.raises(ValueError, match=f"^{key}"):
            Workspace.from_dict({"type": "workspace", "body": body, "shapes": []}, 4)
    with pytest.raises(ValueError, match=r"^shape"):
        Workspace.from_dict({"body": {"shape": "disc", "radius": 1, "pose": [0, 1]},
                             "shapes": [{"shape": "sphere", "radius": 1}]}, 4)


def test_inflation_is_conservative():
    ws = Workspace(BODY, [Box(np.array([1.0, 0.0]), np.array([0.5, 0.5]))])
    x = np.random.default_rng(6).uniform([-1, -1, -3], [3, 1, 3], (3000, 3))
    exact, grown = ws.contains(x), ws.inflated().contains(x)
    assert np.all(grown[exact]) and grown.sum() > exact.sum()


def test_config_reads_shapes_and_body_and_the_command_line_adds_them():
    from rrtcolearn.config import add_obstacles, plan_obstacles, validate
    cfg = validate({"plan": {
        "obstacles": [{"type": "box", "low": [0, 0], "high": [1, 1]},
                      {"shape": "box", "center": [1, 1], "size": [0.5, 0.5], "angle": 0.3}],
        "body": {"shape": "box", "size": [0.5, 0.25], "pose": [0, 1, 2]}}})
    cfg = add_obstacles(cfg, ["disc:2,0,0.3", "polygon:0,0,1,0,0,1", "box:2,2,3,3"])
    obs = plan_obstacles(cfg.plan)
    assert [o["type"] for o in obs] == ["box", "box", "workspace"]
    ws = obs[-1]
    assert ws["body"] == {"shape": "box", "size": [0.5, 0.25], "pose": [0, 1, 2]}
    assert [s["shape"] for s in ws["shapes"]] == ["box", "disc", "polygon"]
    assert ws["shapes"][1] == {"shape": "disc", "center": [2.0, 0.0], "radius": 0.3}
    assert Workspace.from_dict(ws).contains(np.array([[2.0, 0.4, 0.0]]))[0]


@pytest.mark.parametrize("plan, message", [
    ({"obstacles": [{"shape": "disc", "center": [0, 0], "radius": 1}]},
     "config: plan.body: workspace obstacles"),
    ({"obstacles": [{"shape": "box", "center": [0, 0]}],
      "body": {"shape": "disc", "radius": 1, "pose": [0, 1]}},
     "config: plan.obstacles.0.shape.size: a box needs it"),
    ({"body": {"shape": "disc", "radius": 1}}, "config: plan.body.pose"),
    ({"obstacles": [{"shape": "box", "center": [0, 0], "sise": [1, 1]}]},
     "config: unknown key 'plan.obstacles.0.shape.sise' (did you mean 'size'?)"),
    ({"obstacles": [{"kind": "box"}]}, "config: plan.obstacles.0: an obstacle needs type"),
])
def test_config_errors_are_one_line_naming_the_key(plan, message):
    from rrtcolearn.config import validate
    from rrtcolearn.errors import ConfigError
    with pytest.raises(ConfigError) as info:
        validate({"plan": plan})
    assert str(info.value).startswith(message) and "\n" not in str(info.value)
    from rrtcolearn.config import parse_obstacle
    with pytest.raises(ConfigError, match="rect:cx,cy,w,h"):
        parse_obstacle("rect:1,2,3")
