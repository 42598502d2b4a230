"""Safety rows (common/env/safety.py) against independent references.

References used here and not in the module: point-to-polygon distance via
edge segments and a cross-product inside test, a generic least-squares rigid
fit (numpy lstsq), exact rigid transforms, central finite differences, and a
brute-force Python candidate selection.
"""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from common.env.safety import (
    KIND_CARRIER_WALL,
    KIND_FORMATION,
    KIND_PAYLOAD_WALL,
    PAIRS,
    SafetyConfig,
    SafetyGeometry,
    barrier_values,
    build_rows,
    predict,
)

HYP = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ----------------------------------------------------------------------------- references

def box_corners(wall):
    cx, cy, hx, hy, yaw = wall
    c, s = math.cos(yaw), math.sin(yaw)
    local = [(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)]  # counter-clockwise
    return [np.array([cx + c * x - s * y, cy + s * x + c * y]) for x, y in local]


def ref_point_box(p, wall):
    """(sd, q, n) by walking the polygon edges; n is the outward normal used by the rows."""
    corners = box_corners(wall)
    best = None
    inside = True
    for j in range(4):
        a, b = corners[j], corners[(j + 1) % 4]
        e = b - a
        L2 = float(e @ e)
        t = 0.0 if L2 == 0 else min(1.0, max(0.0, float((p - a) @ e) / L2))
        q = a + t * e
        d = float(np.linalg.norm(p - q))
        cross = e[0] * (p[1] - a[1]) - e[1] * (p[0] - a[0])
        if cross < 0:
            inside = False
        edge_n = np.array([e[1], -e[0]]) / math.sqrt(L2) if L2 > 0 else None  # outward for CCW
        if best is None or d < best[0]:
            best = (d, q, edge_n)
    d, q, edge_n = best
    if inside:
        return -d, q, edge_n
    return d, q, (p - q) / d


def rot(t):
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


# ----------------------------------------------------------------------------- strategies

GRASP = np.array([[0.6, 0.0], [-0.3, 0.5], [-0.3, -0.5]])
POINTS = np.array([[x, y] for x in (-0.7, 0.0, 0.7) for y in (-0.55, 0.55)])
REST = np.array([np.linalg.norm(GRASP[i] - GRASP[k]) for i, k in PAIRS])
finite = dict(allow_nan=False, allow_infinity=False)


@st.composite
def scenes(draw, k_max=3, w_max=6):
    """Random walls (oriented boxes), payload and carrier poses, and actions."""
    K = draw(st.integers(1, k_max))
    W = draw(st.integers(1, w_max))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    walls = np.column_stack([
        rng.uniform(-2.5, 2.5, (W, 2)), rng.uniform(0.02, 1.2, (W, 2)), rng.uniform(-np.pi, np.pi, W)])
    pxy = rng.uniform(-1.0, 1.0, (K, 2))
    pyaw = rng.uniform(-np.pi, np.pi, K)
    jitter = draw(st.floats(0.0, 0.1, **finite))
    cxy = np.stack([pxy[k] + (rot(pyaw[k]) @ GRASP.T).T for k in range(K)])
    cxy = cxy + jitter * rng.normal(size=cxy.shape)
    geom = SafetyGeometry(cxy, rng.uniform(-np.pi, np.pi, (K, 3)), pxy, pyaw, POINTS, GRASP, REST)
    a = rng.uniform(-1, 1, (K, 9))
    return geom, walls, a


def entity_point(geom, pred, kind, k, e):
    """Current and predicted position of the row's entity."""
    if kind == KIND_CARRIER_WALL:
        return geom.carrier_xy[k, e], pred["carrier_xy"][k, e]
    p = geom.payload_xy[k] + rot(geom.payload_yaw[k]) @ geom.payload_points_local[e]
    return p, pred["payload_points"][k, e]


def is_upper(C, m):
    """Formation rows ("grasp" profile) fill the last 6 slots as (lower, upper) per pair."""
    return (C.shape[1] - 1 - m) % 2 == 0


GRASP_ROWS = SafetyConfig(profile="grasp")   # the default split plus the formation rows
BIG = SafetyConfig(max_rows=6 + 3 * 6 + 6 * 6, walls_per_carrier=6, walls_per_point=6,
                   search_radius=50.0, alpha=0.3, carrier_radius=0.25, payload_margin=0.04, profile="grasp")


# ----------------------------------------------------------------------------- rows = linearized predicted barrier

@HYP
@given(scenes(), st.sampled_from([SafetyConfig(), GRASP_ROWS, BIG]))
def test_rows_equal_supporting_halfplane_of_predicted_barrier(scene, cfg):
    geom, walls, a = scene
    C, c, mask, info = build_rows(geom, walls, cfg)
    pred = predict(geom, a, cfg)
    residual = np.einsum("kmb,kb->km", C, a) - c
    for k in range(geom.num_envs):
        for m in np.flatnonzero(mask[k]):
            kind, e, w = info["kind"][k, m], info["entity"][k, m], info["wall"][k, m]
            if kind == KIND_FORMATION:
                i, j = PAIRS[e]
                d0 = geom.carrier_xy[k, i] - geom.carrier_xy[k, j]
                D = np.linalg.norm(d0)
                u = d0 / D
                D_lin = D + u @ ((pred["carrier_xy"][k, i] - pred["carrier_xy"][k, j]) - d0)
                sign = -1.0 if is_upper(C, m) else 1.0  # h_lo = D - (D0 - tol), h_hi = D0 + tol - D
                h = sign * (D - REST[e]) + cfg.grasp_tol
                h_lin = sign * (D_lin - REST[e]) + cfg.grasp_tol
            else:
                margin = cfg.carrier_radius if kind == KIND_CARRIER_WALL else cfg.payload_margin
                p, p_next = entity_point(geom, pred, kind, k, e)
                sd, q, n = ref_point_box(p, walls[w])
                h = sd - margin
                h_lin = n @ (p_next - q) - margin
            assert info["h"][k, m] == pytest.approx(h, abs=1e-9)
            assert residual[k, m] == pytest.approx(h_lin - (1 - cfg.alpha) * h, abs=1e-9)


@settings(HYP, max_examples=20)
@given(scenes())
@pytest.mark.sweep
def test_row_gradient_matches_finite_difference_of_true_barrier(scene):
    """C equals d/da of the exact barrier at the predicted state (central differences at a=0)."""
    geom, walls, _ = scene
    cfg = BIG
    C, c, mask, info = build_rows(geom, walls, cfg)
    K = geom.num_envs
    eps = 1e-6

    def barrier_of_row(pred, k, m):
        kind, e, w = info["kind"][k, m], info["entity"][k, m], info["wall"][k, m]
        if kind == KIND_FORMATION:
            i, j = PAIRS[e]
            D = np.linalg.norm(pred["carrier_xy"][k, i] - pred["carrier_xy"][k, j])
            return -D if is_upper(C, m) else D
        _, p_next = entity_point(geom, pred, kind, k, e)
        return ref_point_box(p_next, walls[w])[0]

    now = predict(geom, np.zeros((K, 9)), cfg)
    rows = []
    for k in range(K):
        for m in np.flatnonzero(mask[k]):
            kind, e, w = info["kind"][k, m], info["entity"][k, m], info["wall"][k, m]
            if kind != KIND_FORMATION:
                p, _ = entity_point(geom, now, kind, k, e)
                local = rot(walls[w, 4]).T @ (p - walls[w, :2])
                depth = walls[w, 2:4] - np.abs(local)
                # skip kinks of sd (medial axis inside, boundary) where no derivative exists
                if np.all(depth > -1e-5) and (abs(depth[0] - depth[1]) < 1e-4 or depth.min() < 1e-4):
                    continue
            rows.append((k, m))
    for b in range(9):
        step = np.zeros((K, 9))
        step[:, b] = eps
        plus, minus = predict(geom, step, cfg), predict(geom, -step, cfg)
        for k, m in rows:
            fd = (barrier_of_row(plus, k, m) - barrier_of_row(minus, k, m)) / (2 * eps)
            assert C[k, m, b] == pytest.approx(fd, abs=2e-6)


# ----------------------------------------------------------------------------- conservativeness

@HYP
@given(scenes(), st.floats(0.0, 1.0, **finite))
@pytest.mark.sweep
def test_wall_rows_are_conservative_for_exact_distance(scene, shrink):
    """Any action on or inside a wall row keeps the exact predicted clearance >= (1-α)h."""
    geom, walls, a = scene
    cfg = BIG
    C, c, mask, info = build_rows(geom, walls, cfg)
    for k in range(geom.num_envs):
        for m in np.flatnonzero(mask[k]):
            kind, e, w = info["kind"][k, m], info["entity"][k, m], info["wall"][k, m]
            # move a onto the row boundary, then (shrink) optionally deeper into it
            gap = c[k, m] - C[k, m] @ a[k]
            a_row = a[k] + (max(gap, 0.0) + shrink * 0.01) * C[k, m] / (C[k, m] @ C[k, m])
            assert C[k, m] @ a_row >= c[k, m] - 1e-12
            a_all = a.copy()
            a_all[k] = a_row
            pred = predict(geom, a_all, cfg)
            if kind == KIND_FORMATION:
                if is_upper(C, m):
                    continue  # the upper formation row is first-order only (documented)
                i, j = PAIRS[e]
                D_next = np.linalg.norm(pred["carrier_xy"][k, i] - pred["carrier_xy"][k, j])
                h_next = D_next - (REST[e] - cfg.grasp_tol)
            else:
                margin = cfg.carrier_radius if kind == KIND_CARRIER_WALL else cfg.payload_margin
                _, p_next = entity_point(geom, pred, kind, k, e)
                h_next = ref_point_box(p_next, walls[w])[0] - margin
            assert h_next >= (1 - cfg.alpha) * info["h"][k, m] - 1e-9


def test_violated_barrier_asks_for_recovery_without_blowup():
    """A carrier inside a wall gets the recovery row h⁺ >= (1-α)h with c = -αh > 0."""
    cfg = SafetyConfig(alpha=0.5)
    pxy = np.array([[0.0, 0.0]])
    cxy = (GRASP + pxy)[None]
    geom = SafetyGeometry(cxy, np.zeros((1, 3)), pxy, np.zeros(1), POINTS, GRASP, REST)
    walls = np.array([[0.6, 0.1, 0.5, 0.5, 0.0]])  # carrier 0 at (0.6, 0) is 0.4 deep
    C, c, mask, info = build_rows(geom, walls, cfg)
    row = np.flatnonzero(mask[0] & (info["kind"][0] == KIND_CARRIER_WALL) & (info["entity"][0] == 0))
    assert len(row) == 1
    m = row[0]
    h = -0.4 - cfg.carrier_radius
    assert info["h"][0, m] == pytest.approx(h)
    assert c[0, m] == pytest.approx(-cfg.alpha * h)
    # nearest face is y = -0.4 (depth 0.4, vs 0.5 to the x-faces): the row pushes carrier 0 in -y
    assert C[0, m] == pytest.approx([0, -cfg.max_step_xy, 0, 0, 0, 0, 0, 0, 0])


# ----------------------------------------------------------------------------- predictor

@HYP
@given(scenes(k_max=2), st.floats(-0.2, 0.2, **finite), st.floats(-0.1, 0.1, **finite),
       st.floats(-0.1, 0.1, **finite))
def test_predictor_is_rigid_transform_to_second_order(scene, theta, tx, ty):
    geom, _, _ = scene
    cfg = SafetyConfig()
    K = geom.num_envs
    T = np.array([tx, ty])
    a = np.zeros((K, 9))
    exact = []
    for k in range(K):
        Rp = rot(geom.payload_yaw[k])
        g = geom.payload_xy[k] + (Rp @ GRASP.T).T
        gc = g.mean(0)
        for i in range(3):  # carrier displacement = rigid motion of its grasp
            d = T + (rot(theta) - np.eye(2)) @ (g[i] - gc)
            a[k, 3 * i:3 * i + 2] = rot(geom.carrier_yaw[k, i]).T @ d / cfg.max_step_xy
        p = geom.payload_xy[k] + (Rp @ POINTS.T).T
        exact.append(gc + T + ((rot(theta)) @ (p - gc).T).T)
    pred = predict(geom, a, cfg)
    for k in range(K):
        err = np.linalg.norm(pred["payload_points"][k] - exact[k], axis=1)
        Rp = rot(geom.payload_yaw[k])
        g = geom.payload_xy[k] + (Rp @ GRASP.T).T
        r_p = np.linalg.norm(geom.payload_xy[k] + (Rp @ POINTS.T).T - g.mean(0), axis=1)
        # linear predictor p + T + sinθ J(p-g) misses exactly (1-cosθ)|p-g| = O(θ²)
        assert err == pytest.approx((1 - math.cos(theta)) * r_p, abs=1e-10)
        assert pred["payload_theta"][k] == pytest.approx(math.sin(theta), abs=1e-12)
        assert pred["payload_translation"][k] == pytest.approx(T, abs=1e-12)
    if theta == 0.0:
        assert np.allclose(pred["payload_points"], np.stack(exact), atol=1e-12)


def test_predictor_pure_translation_is_exact():
    cfg = SafetyConfig()
    pxy = np.array([[0.3, -0.2]])
    yaw = np.array([0.7])
    cxy = (pxy + (rot(0.7) @ GRASP.T).T)[None]
    cyaw = np.array([[0.1, -2.0, 1.3]])
    geom = SafetyGeometry(cxy, cyaw, pxy, yaw, POINTS, GRASP, REST)
    T = np.array([0.03, -0.04])
    a = np.concatenate([np.r_[rot(cyaw[0, i]).T @ T / cfg.max_step_xy, 0.5] for i in range(3)])[None]
    pred = predict(geom, a, cfg)
    p = pxy[0] + (rot(0.7) @ POINTS.T).T
    assert np.allclose(pred["payload_points"][0], p + T, atol=1e-14)
    assert np.allclose(pred["carrier_xy"][0], cxy[0] + T, atol=1e-14)
    assert np.allclose(pred["carrier_yaw"], cyaw + 0.5 * cfg.max_step_yaw)


@HYP
@given(scenes(k_max=1))
def test_predictor_rotation_is_least_squares_rigid_fit(scene):
    """δθ and t equal the generic lstsq fit of d_i ≈ t + ω J r_i (first-order rigid motion)."""
    geom, _, a = scene
    cfg = SafetyConfig()
    pred = predict(geom, a, cfg)
    Rp = rot(geom.payload_yaw[0])
    g = geom.payload_xy[0] + (Rp @ GRASP.T).T
    r = g - g.mean(0)
    d = pred["carrier_xy"][0] - geom.carrier_xy[0]
    A = np.zeros((6, 3))
    for i in range(3):
        A[2 * i:2 * i + 2, :2] = np.eye(2)
        A[2 * i:2 * i + 2, 2] = [-r[i, 1], r[i, 0]]
    sol = np.linalg.lstsq(A, d.reshape(-1), rcond=None)[0]
    assert pred["payload_translation"][0] == pytest.approx(sol[:2], abs=1e-12)
    assert pred["payload_theta"][0] == pytest.approx(sol[2], abs=1e-10)


# ----------------------------------------------------------------------------- masking and ordering

def _simple_geom(K=1):
    pxy = np.zeros((K, 2))
    cxy = np.broadcast_to(GRASP, (K, 3, 2)).copy()
    return SafetyGeometry(cxy, np.zeros((K, 3)), pxy, np.zeros(K), POINTS, GRASP, REST)


def test_few_candidates_pad_with_masked_rows():
    cfg = SafetyConfig(search_radius=0.5, profile="grasp")
    geom = _simple_geom()
    # one wall within reach of carrier 0 (h=0.45) and payload point (0.7, 0.55) (h=0.45) only
    walls = np.array([[1.3, 0.55, 0.1, 0.1, 0.0], [50.0, 50.0, 1.0, 1.0, 0.0]])
    C, c, mask, info = build_rows(geom, walls, cfg)
    hv = barrier_values(geom, walls, cfg)
    n_car = int(np.sum(hv["carrier_wall"] <= cfg.search_radius))
    n_pay = int(np.sum(np.sort(hv["payload_wall"], 1)[:, :cfg.walls_per_point] <= cfg.search_radius))
    kinds = info["kind"][0]
    assert mask[0, kinds == KIND_CARRIER_WALL].sum() == n_car == 1
    assert mask[0, kinds == KIND_PAYLOAD_WALL].sum() == n_pay == 1
    assert info["h"][0, mask[0] & (kinds != KIND_FORMATION)] == pytest.approx([0.45, 0.45])
    assert mask[0, kinds == KIND_FORMATION].all()
    assert mask.shape == (1, 34) and mask.sum() == 1 + 1 + 6
    pad = ~mask[0]
    assert np.all(C[0, pad] == 0) and np.all(c[0, pad] == 0) and np.all(info["entity"][0, pad] == -1)
    # active rows are never all-zero
    assert np.all(np.abs(C[0, mask[0]]).max(-1) > 0)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_many_candidates_keep_smallest_h(seed):
    rng = np.random.default_rng(seed)
    cfg = SafetyConfig(search_radius=3.0, walls_per_carrier=2, walls_per_point=3)
    geom = _simple_geom()
    W = 12
    walls = np.column_stack([rng.uniform(-3, 3, (W, 2)), rng.uniform(0.05, 0.3, (W, 2)),
                             rng.uniform(-3, 3, W)])
    C, c, mask, info = build_rows(geom, walls, cfg)
    hv = barrier_values(geom, walls, cfg)
    for kind, key, per, budget in [(KIND_CARRIER_WALL, "carrier_wall", 2, cfg.carrier_budget),
                                   (KIND_PAYLOAD_WALL, "payload_wall", 3, cfg.payload_budget)]:
        cand = []  # brute force: per-entity nearest `per`, within radius
        for e, row in enumerate(hv[key][0]):
            for w in sorted(range(W), key=lambda w: row[w])[:per]:
                if row[w] <= cfg.search_radius:
                    cand.append((row[w], e, w))
        cand.sort()
        kept = cand[:budget]
        sel = (info["kind"][0] == kind) & mask[0]
        got_h = info["h"][0, sel]
        assert np.all(np.diff(got_h) >= 0)  # ordered by h
        assert got_h == pytest.approx([h for h, _, _ in kept], abs=1e-12)
        if len(cand) > budget:
            assert sel.sum() == budget
            assert got_h.max() <= cand[budget][0] + 1e-12


# ----------------------------------------------------------------------------- barrier values, shapes, errors

@HYP
@given(scenes())
def test_barrier_values_match_reference_distances(scene):
    geom, walls, _ = scene
    cfg = GRASP_ROWS
    hv = barrier_values(geom, walls, cfg)
    for k in range(geom.num_envs):
        for w in range(len(walls)):
            for i in range(3):
                sd = ref_point_box(geom.carrier_xy[k, i], walls[w])[0]
                assert hv["carrier_wall"][k, i, w] == pytest.approx(sd - cfg.carrier_radius, abs=1e-9)
            for j in range(len(POINTS)):
                p = geom.payload_xy[k] + rot(geom.payload_yaw[k]) @ POINTS[j]
                sd = ref_point_box(p, walls[w])[0]
                assert hv["payload_wall"][k, j, w] == pytest.approx(sd - cfg.payload_margin, abs=1e-9)
        for pi, (i, j) in enumerate(PAIRS):
            D = np.linalg.norm(geom.carrier_xy[k, i] - geom.carrier_xy[k, j])
            assert hv["formation"][k, pi] == pytest.approx(
                [D - REST[pi] + cfg.grasp_tol, REST[pi] + cfg.grasp_tol - D], abs=1e-12)
    mins = [hv[key][k].min() for key in ("carrier_wall", "payload_wall", "formation")
            for k in range(geom.num_envs)]
    assert hv["min"] == pytest.approx(np.min(np.reshape(mins, (3, -1)), 0))


def test_per_env_walls_equal_shared_walls_and_no_walls():
    geom = _simple_geom(K=2)
    cfg = SafetyConfig()
    walls = np.array([[1.2, 0.0, 0.1, 1.0, 0.2], [0.0, -1.0, 1.0, 0.1, 0.0]])
    shared = build_rows(geom, walls, cfg)
    per_env = build_rows(geom, np.stack([walls, walls]), cfg)
    for x, y in zip(shared[:3], per_env[:3]):
        assert np.array_equal(x, y)
    C, c, mask, info = build_rows(geom, np.zeros((0, 5)), cfg)
    assert mask.sum(1).tolist() == [0, 0]   # "paper": wall rows only
    C, c, mask, info = build_rows(geom, np.zeros((0, 5)), GRASP_ROWS)
    assert mask.sum(1).tolist() == [6, 6]
    assert np.all(info["kind"][mask] == KIND_FORMATION)


def test_bad_input_is_rejected():
    geom = _simple_geom()
    cfg = SafetyConfig()
    with pytest.raises(ValueError, match="walls"):
        build_rows(geom, np.zeros((3, 4)), cfg)
    with pytest.raises(ValueError, match="NaN"):
        build_rows(geom, np.full((1, 5), np.nan), cfg)
    with pytest.raises(ValueError, match="carrier_yaw"):
        SafetyGeometry(geom.carrier_xy, np.zeros((2, 3)), geom.payload_xy, geom.payload_yaw,
                       POINTS, GRASP, REST)
    with pytest.raises(ValueError, match="NaN"):
        SafetyGeometry(geom.carrier_xy * np.nan, geom.carrier_yaw, geom.payload_xy,
                       geom.payload_yaw, POINTS, GRASP, REST)
    with pytest.raises(ValueError, match="alpha"):
        SafetyConfig(alpha=0.0)
    with pytest.raises(ValueError, match="max_rows"):
        SafetyConfig(max_rows=10, walls_per_carrier=4)
    with pytest.raises(ValueError, match="actions"):
        predict(geom, np.zeros((1, 8)), cfg)
