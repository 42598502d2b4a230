"""The numba fast path of the environment against its numpy references.

``build_rows``, ``grasp_strain``, the ``WallSet`` queries and ``Route.project`` vs their references
in common/env/reference.py, and a whole
``BatchEnv`` rollout (with resets, drops and the human slot) against a twin env
with those entry points patched to their references. ``BatchEnv.step`` now calls
the fused kernels of ``common/env/kernels.py`` directly, so the rollout twin
exercises the references only where the env still goes through those entry
points; the whole rollout with every kernel swapped for its reference is in
tests/test_env_kernels.py.
"""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.env import batch_env, geometry, physics, reference, scenarios
from common.env import safety as S
from common.env.config import EnvConfig
from common.env.geometry import WallSet
from common.env.layout import GRASP_LOCAL, PAIR_REST, PAYLOAD_POINTS_LOCAL
from common.env.scenarios import SCENARIOS, Route

HYP = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _geometry(rng, K, jitter):
    pxy = rng.uniform([0.0, -2.0], [10.0, 2.0], (K, 2))
    pyaw = rng.uniform(-3.2, 3.2, K)
    c, s = np.cos(pyaw)[:, None], np.sin(pyaw)[:, None]
    grasp = np.stack([c * GRASP_LOCAL[:, 0] - s * GRASP_LOCAL[:, 1], s * GRASP_LOCAL[:, 0] + c * GRASP_LOCAL[:, 1]], -1)
    cxy = pxy[:, None] + grasp + rng.normal(0.0, jitter, (K, 3, 2))
    return S.SafetyGeometry(cxy, rng.uniform(-3.2, 3.2, (K, 3)), pxy, pyaw, PAYLOAD_POINTS_LOCAL, GRASP_LOCAL,
                            PAIR_REST)


def _assert_rows_equal(fast, ref):
    for a, b in zip(fast[:3], ref[:3]):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast[3]["h"], ref[3]["h"], rtol=0, atol=1e-12)
    for key in ("kind", "entity", "wall"):
        np.testing.assert_array_equal(fast[3][key], ref[3][key])


CONFIGS = [S.SafetyConfig(), S.SafetyConfig(profile="grasp"),
           S.SafetyConfig(search_radius=5.0, walls_per_carrier=2, walls_per_point=3, max_rows=24, profile="grasp"),
           S.SafetyConfig(walls_per_carrier=0, walls_per_point=1, max_rows=10, alpha=1.0)]


@HYP
@given(st.sampled_from(sorted(SCENARIOS)), st.integers(0, 2**31), st.sampled_from(CONFIGS),
       st.floats(0.0, 0.3))
def test_build_rows_matches_reference(name, seed, cfg, jitter):
    geom = _geometry(np.random.default_rng(seed), 12, jitter)
    walls = SCENARIOS[name].walls_array()
    _assert_rows_equal(S.build_rows(geom, walls, cfg), reference.build_rows(geom, walls, cfg))


def test_build_rows_ties_per_env_walls_and_edge_cases():
    """Exact distance ties (duplicated walls), per-env walls, no walls, coincident grasps."""
    rng = np.random.default_rng(3)
    geom = _geometry(rng, 5, 0.05)
    walls = SCENARIOS["maze"].walls_array()
    dup = np.concatenate([walls, walls])  # every distance tied with a later wall
    per_env = np.stack([walls + rng.normal(0, 0.1, walls.shape) * [1, 1, 0, 0, 1] for _ in range(5)])
    none = np.zeros((0, 5))
    for cfg in (S.SafetyConfig(), S.SafetyConfig(profile="grasp")):
        _assert_rows_equal(S.build_rows(geom, dup, cfg), reference.build_rows(geom, dup, cfg))
        _assert_rows_equal(S.build_rows(geom, per_env, cfg), reference.build_rows(geom, per_env, cfg))
        _assert_rows_equal(S.build_rows(geom, none, cfg), reference.build_rows(geom, none, cfg))
    flat = S.SafetyGeometry(geom.carrier_xy, geom.carrier_yaw, geom.payload_xy, geom.payload_yaw,
                            PAYLOAD_POINTS_LOCAL, np.zeros((3, 2)), PAIR_REST)
    for fn in (S.build_rows, reference.build_rows):
        with pytest.raises(ValueError, match="coincide"):
            fn(flat, walls, cfg)


@HYP
@given(st.sampled_from(sorted(SCENARIOS)), st.integers(0, 2**31))
def test_wallset_and_route_kernels_match_reference(name, seed):
    rng = np.random.default_rng(seed)
    ws, route = WallSet(SCENARIOS[name].walls_array()), Route(SCENARIOS[name].route)
    pts = rng.uniform([-1.0, -3.0], [11.0, 3.0], (6, 8, 2))
    np.testing.assert_array_equal(ws.signed_distance(pts), reference.signed_distance(ws, pts))
    for a, b in zip(ws.nearest(pts), reference.nearest(ws, pts)):
        np.testing.assert_array_equal(a, b)
    yaw = rng.uniform(-4.0, 4.0, (6, 3, 4))
    dirs = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    dirs[0, 0, :2] = [[1.0, 0.0], [0.0, -1.0]]  # axis-aligned rays hit the 1e-12 slab guard
    origin = np.broadcast_to(pts[:, :3, None, :], dirs.shape)
    np.testing.assert_array_equal(ws.ray_distance(origin, dirs, 2.3), reference.ray_distance(ws, origin, dirs, 2.3))
    s_prev = rng.uniform(-1.0, route.length + 1.0, 6)
    np.testing.assert_array_equal(route.project(pts[:, 0], s_prev), reference.route_project(route, pts[:, 0], s_prev))


@pytest.fixture
def reference_env(monkeypatch):
    """A factory of BatchEnvs whose geometry runs the numpy references (patched on the classes
    while the reference env is built and stepped)."""

    def patch():
        monkeypatch.setattr(geometry.WallSet, "signed_distance", reference.signed_distance)
        monkeypatch.setattr(geometry.WallSet, "nearest", reference.nearest)
        monkeypatch.setattr(geometry.WallSet, "ray_distance", reference.ray_distance)
        monkeypatch.setattr(scenarios.Route, "project", reference.route_project)
        monkeypatch.setattr(S, "build_rows", reference.build_rows)
        monkeypatch.setattr(physics.TransportPhysics, "grasp_strain", reference.grasp_strain)

    return patch


KEYS_EXACT = ("row_mask", "fixed_mask", "terminated", "truncated", "collision", "margin_violation", "drop",
              "success")
KEYS_CLOSE = ("obs", "state", "C", "c", "human_action", "progress", "reward", "final_obs", "final_state")


@pytest.mark.parametrize("name,human,rows", [("maze", None, "paper"), ("tilt_gate", 1, "grasp")])
def test_batch_env_matches_reference_path(name, human, rows, reference_env, monkeypatch):
    """Same seed and actions: every output of every step equals the numpy-reference env's."""
    cfg = EnvConfig(name, human_slot=human, max_steps=40, safety_rows=rows)
    fast = batch_env.BatchEnv(cfg, num_envs=6, seed=5)
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1.0, 1.0, (90, 6, 9))
    out_fast = [fast.reset()] + [fast.step(a) for a in acts]
    reference_env()
    ref = batch_env.BatchEnv(cfg, num_envs=6, seed=5)
    out_ref = [ref.reset()] + [ref.step(a) for a in acts]
    monkeypatch.undo()
    n_episodes = 0
    for a, b in zip(out_fast, out_ref):
        for key in KEYS_EXACT:
            if key in b:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        for key in KEYS_CLOSE:
            if key in b:
                np.testing.assert_allclose(a[key], b[key], rtol=0, atol=1e-9, err_msg=key)
        ea, eb = a.get("episodes", []), b.get("episodes", [])
        assert len(ea) == len(eb)
        for x, y in zip(ea, eb):
            assert x.keys() == y.keys()
            for key in x:
                assert x[key] == y[key] or (x[key] != x[key] and y[key] != y[key]), key  # NaN == NaN
        n_episodes += len(b.get("episodes", []))
    assert n_episodes >= 6  # resets (time limit and drops) were exercised


def test_env_grasp_tol_sets_the_formation_rows():
    """`--set env.grasp_tol=...` reaches the rows the shield sees: at the same reset
    state a looser tolerance gives looser formation rows and leaves wall rows alone."""
    out = {}
    for tol in (0.05, 0.1):
        env = batch_env.BatchEnv(EnvConfig(scenario="narrow_gate", grasp_tol=tol, safety_rows="grasp"), 2, seed=4)
        assert env.safety_cfg.grasp_tol == tol
        out[tol] = env.reset()
    n_form = 2 * len(S.PAIRS)
    tight, loose = out[0.05], out[0.1]
    np.testing.assert_array_equal(tight["C"], loose["C"])
    np.testing.assert_array_equal(tight["c"][:, :-n_form], loose["c"][:, :-n_form])
    # c = -alpha * h and h grows by the 5 cm of extra tolerance on every formation row
    alpha = EnvConfig().alpha
    np.testing.assert_allclose(tight["c"][:, -n_form:] - loose["c"][:, -n_form:], alpha * 0.05, atol=1e-12)
