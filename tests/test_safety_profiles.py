"""Safety-row profiles ("paper": wall rows only; "grasp": + formation rows) and the
margin-violation collision measure (common/env/safety.py, common/env/batch_env.py).

Hand-built geometries use the real team layout (common/env/layout.py): payload at the
origin with yaw 0, carrier 0 at the front grasp (0.8, 0), carrier 1 at the back grasp
(-0.8, 0), carrier 2 at the right grasp (0, -0.4).
"""
import dataclasses
import math

import numpy as np
import pytest

from common.env import reference
from common.env import safety as S
from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.layout import FACING, GRASP_LOCAL, PAIR_REST, PAIRS, PAYLOAD_POINTS_LOCAL
from common.env.metrics import aggregate
from common.env.scenarios import SCENARIOS

PAPER, GRASP = S.SafetyConfig(profile="paper"), S.SafetyConfig(profile="grasp")


def team(carrier_offset=None):
    """One env in formation at the origin; ``carrier_offset [3,2]`` displaces the carriers."""
    cxy = GRASP_LOCAL.copy()[None]
    if carrier_offset is not None:
        cxy = cxy + np.asarray(carrier_offset)[None]
    return S.SafetyGeometry(cxy, FACING[None].copy(), np.zeros((1, 2)), np.zeros(1),
                            PAYLOAD_POINTS_LOCAL, GRASP_LOCAL, PAIR_REST)


def rows_both_paths(geom, walls, cfg):
    """build_rows (numba) after checking it equals reference.build_rows (numpy)."""
    fast, ref = S.build_rows(geom, walls, cfg), reference.build_rows(geom, walls, cfg)
    for a, b in zip(fast[:3], ref[:3]):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast[3]["h"], ref[3]["h"], rtol=0, atol=1e-12)
    for key in ("kind", "entity", "wall"):
        np.testing.assert_array_equal(fast[3][key], ref[3][key])
    return fast


def enforced(mask, info, kind):
    sel = mask[0] & (info["kind"][0] == kind)
    return np.flatnonzero(sel)


# ----------------------------------------------------------------------------- layout and budget

def test_default_profile_is_paper_and_the_budget_split():
    assert EnvConfig().safety_rows == "paper" and S.SafetyConfig().profile == "paper"
    assert (PAPER.carrier_budget, PAPER.payload_budget, PAPER.formation_budget) == (9, 25, 0)
    assert (GRASP.carrier_budget, GRASP.payload_budget, GRASP.formation_budget) == (9, 19, 6)
    assert PAPER.kind_slices == {"carrier_wall": slice(0, 9), "payload_wall": slice(9, 34)}
    assert GRASP.kind_slices == {"carrier_wall": slice(0, 9), "payload_wall": slice(9, 28),
                                 "formation": slice(28, 34)}
    for cfg in (PAPER, GRASP):
        assert len(cfg.slot_kinds) == cfg.max_rows == 34
        for name, kind in (("carrier_wall", S.KIND_CARRIER_WALL), ("payload_wall", S.KIND_PAYLOAD_WALL),
                           ("formation", S.KIND_FORMATION)):
            sl = cfg.kind_slices.get(name, slice(0, 0))
            assert np.array_equal(np.flatnonzero(cfg.slot_kinds == kind), np.arange(34)[sl])


def test_unknown_profiles_are_rejected():
    with pytest.raises(ValueError, match="safety_rows"):
        EnvConfig(safety_rows="formation")
    with pytest.raises(ValueError, match="profile"):
        S.SafetyConfig(profile="strict")
    # the "paper" profile frees the formation slots: 9 wall slots fit where "grasp" needs 15
    assert S.SafetyConfig(max_rows=9, walls_per_carrier=3).payload_budget == 0
    with pytest.raises(ValueError, match="max_rows"):
        S.SafetyConfig(max_rows=9, walls_per_carrier=3, profile="grasp")


# ----------------------------------------------------------------------------- hand-built geometries

@pytest.mark.parametrize("cfg", [PAPER, GRASP], ids=["paper", "grasp"])
def test_carrier_next_to_a_wall_gives_a_carrier_wall_row(cfg):
    # a 0.1 m post 0.5 m in front of carrier 0 (x = 1.3..1.4 at y = 0): h = 0.5 - 0.30
    walls = np.array([[1.35, 0.0, 0.05, 0.05, 0.0]])
    C, c, mask, info = rows_both_paths(team(), walls, cfg)
    rows = enforced(mask, info, S.KIND_CARRIER_WALL)
    assert len(rows) == 1
    m = rows[0]
    assert info["entity"][0, m] == 0 and info["wall"][0, m] == 0
    assert info["h"][0, m] == pytest.approx(0.5 - cfg.carrier_radius)
    assert c[0, m] == pytest.approx(-cfg.alpha * info["h"][0, m])
    # only carrier 0's block; its local x points to the payload centre (world -x, away from
    # the post): the barrier grows by max_step_xy per unit local-x action
    assert np.all(C[0, m, 3:] == 0)
    assert C[0, m, :3] == pytest.approx([cfg.max_step_xy, 0.0, 0.0], abs=1e-12)
    assert np.all(info["kind"][0] != S.KIND_FORMATION) == (cfg.profile == "paper")


@pytest.mark.parametrize("cfg", [PAPER, GRASP], ids=["paper", "grasp"])
def test_payload_corner_next_to_a_wall_gives_a_payload_wall_row(cfg):
    # a small box diagonally off the front-left corner (0.8, 0.4): sd = 0.15 sqrt(2);
    # search_radius 0.2 keeps the carriers (h >= 0.27) and the corner's neighbours (h = 0.225) out
    cfg = dataclasses.replace(cfg, search_radius=0.2)
    walls = np.array([[1.0, 0.6, 0.05, 0.05, 0.0]])
    C, _, mask, info = rows_both_paths(team(), walls, cfg)
    assert len(enforced(mask, info, S.KIND_CARRIER_WALL)) == 0
    rows = enforced(mask, info, S.KIND_PAYLOAD_WALL)
    assert len(rows) == 1
    m = rows[0]
    corner = int(np.flatnonzero(np.all(np.isclose(PAYLOAD_POINTS_LOCAL, [0.8, 0.4]), 1))[0])
    assert info["entity"][0, m] == corner
    assert info["h"][0, m] == pytest.approx(0.15 * math.sqrt(2) - cfg.payload_margin)
    # the payload row couples all three carriers (rigid-fit translation and rotation)
    for i in range(3):
        assert np.abs(C[0, m, 3 * i:3 * i + 2]).max() > 1e-6
    # the row's block of slots is where the profile's layout says
    assert cfg.kind_slices["payload_wall"].start <= m < cfg.kind_slices["payload_wall"].stop


def test_strained_pairs_give_formation_rows_under_grasp_only():
    # carrier 2 pulled 15 cm outward (-y): pairs (0,2) and (1,2) stretch 7.6 cm, past grasp_tol; no walls
    geom = team([[0.0, 0.0], [0.0, 0.0], [0.0, -0.15]])
    no_walls = np.zeros((0, 5))
    D = np.array([np.linalg.norm(geom.carrier_xy[0, i] - geom.carrier_xy[0, k]) for i, k in PAIRS])
    dev = D - PAIR_REST
    assert dev[0] == pytest.approx(0.0) and np.all(dev[1:] > GRASP.grasp_tol)

    C, c, mask, info = rows_both_paths(geom, no_walls, GRASP)
    rows = enforced(mask, info, S.KIND_FORMATION)
    assert rows.tolist() == list(range(28, 34))
    h = info["h"][0, rows].reshape(3, 2)          # (h_lo, h_hi) per pair
    np.testing.assert_allclose(h[:, 0], dev + GRASP.grasp_tol, atol=1e-12)
    np.testing.assert_allclose(h[:, 1], GRASP.grasp_tol - dev, atol=1e-12)
    assert np.all(h[1:, 1] < 0)                   # the stretched pairs violate their upper rows
    assert np.array_equal(info["entity"][0, rows], np.repeat([0, 1, 2], 2))
    hv = S.barrier_values(geom, no_walls, GRASP)
    assert hv["formation"].shape == (1, 3, 2) and hv["min"][0] == pytest.approx(h.min())

    C, c, mask, info = rows_both_paths(geom, no_walls, PAPER)
    assert not mask.any() and not np.any(info["kind"] == S.KIND_FORMATION)
    assert np.all(C == 0) and np.all(c == 0)
    hv = S.barrier_values(geom, no_walls, PAPER)
    assert hv["formation"].shape == (1, 0, 2) and hv["min"][0] == np.inf


@pytest.mark.parametrize("name", ["narrow_gate", "needle_gate", "maze"])
def test_paper_rows_are_the_grasp_wall_rows_with_more_payload_slots(name):
    """Both profiles pick wall candidates the same way; "paper" keeps the first
    19 payload rows of "grasp" and adds more, and never a formation row."""
    rng = np.random.default_rng(7)
    K = 16
    pxy = rng.uniform([0.0, -1.0], [10.0, 1.0], (K, 2))
    pyaw = rng.uniform(-0.5, 0.5, K)
    c, s = np.cos(pyaw)[:, None], np.sin(pyaw)[:, None]
    cxy = pxy[:, None] + np.stack([c * GRASP_LOCAL[:, 0] - s * GRASP_LOCAL[:, 1],
                                   s * GRASP_LOCAL[:, 0] + c * GRASP_LOCAL[:, 1]], -1)
    geom = S.SafetyGeometry(cxy + rng.normal(0, 0.03, cxy.shape), pyaw[:, None] + FACING, pxy, pyaw,
                            PAYLOAD_POINTS_LOCAL, GRASP_LOCAL, PAIR_REST)
    walls = SCENARIOS[name].walls_array()
    paper, grasp = rows_both_paths(geom, walls, PAPER), rows_both_paths(geom, walls, GRASP)
    wall_slots = slice(0, 28)
    for a, b in zip(paper[:3], grasp[:3]):
        np.testing.assert_array_equal(a[:, wall_slots], b[:, wall_slots])
    assert not np.any(paper[3]["kind"] == S.KIND_FORMATION)
    assert np.all(grasp[2][:, 28:])               # formation rows always enforced under "grasp"


# ----------------------------------------------------------------------------- spec barriers

@pytest.mark.parametrize("cfg", [PAPER, GRASP], ids=["paper", "grasp"])
def test_spec_barrier_min_equals_barrier_values_min(cfg):
    from common.env.geometry import WallSet

    rng = np.random.default_rng(3)
    walls = SCENARIOS["chicane"].walls_array()
    ws = WallSet(walls)
    K = 32
    pxy = rng.uniform([0.0, -2.0], [10.0, 2.0], (K, 2))
    geom = S.SafetyGeometry(pxy[:, None] + GRASP_LOCAL + rng.normal(0, 0.05, (K, 3, 2)), rng.uniform(-3, 3, (K, 3)),
                            pxy, np.zeros(K), PAYLOAD_POINTS_LOCAL, GRASP_LOCAL, PAIR_REST)
    carrier_sd = ws.signed_distance(geom.carrier_xy).min(-1)
    payload_sd, _ = ws.nearest(S.payload_points_world(geom))
    got = S.spec_barrier_min(carrier_sd, payload_sd, geom.carrier_xy, PAIR_REST, cfg)
    np.testing.assert_allclose(got, S.barrier_values(geom, walls, cfg)["min"], rtol=0, atol=1e-12)
    assert np.any(got < 0) and np.any(got > 0)


# ----------------------------------------------------------------------------- margin violation in the env

def _drive(env, world_dir):
    """Carrier-frame actions that move every carrier along ``world_dir`` at full speed."""
    yaw = env.snap.cyaw
    c, s = np.cos(yaw), np.sin(yaw)
    v = np.asarray(world_dir, float)
    return np.stack([c * v[0] + s * v[1], -s * v[0] + c * v[1], np.zeros_like(c)], -1).reshape(env.K, 9)


@pytest.mark.parametrize("rows", ["paper", "grasp"])
def test_margin_violation_fires_no_later_than_contact_driving_into_a_wall(rows):
    env = BatchEnv(EnvConfig("narrow_gate", safety_rows=rows, randomize=False, max_steps=60), 2, seed=0)
    env.reset()
    margin, contact, episodes = [], [], []
    for _ in range(60):                          # straight at the left side wall (+y)
        out = env.step(_drive(env, [0.0, 1.0]))
        margin.append(out["margin_violation"].copy())
        contact.append(out["collision"].copy())
        assert out["margin_violation"].dtype == bool and out["margin_violation"].shape == (2,)
        episodes += out["episodes"]
        if out["episodes"]:
            break
    margin, contact = np.array(margin), np.array(contact)
    assert contact.any(0).all(), "the scripted crash must reach the wall"
    for k in range(2):
        assert np.argmax(margin[:, k]) <= np.argmax(contact[:, k])
        assert not np.any(contact[:, k] & ~margin[:, k])   # contact implies a margin violation
    assert len(episodes) == 2                     # both ended (the crash strains the grasps)
    for k, ep in enumerate(episodes):
        n = ep["steps"]
        assert ep["margin_violation_steps"] == int(margin[:n, k].sum()) > 0
        assert ep["margin_violation_steps"] >= ep["collision_steps"] > 0
        assert ep["margin_col_per_1k"] == pytest.approx(1000.0 * ep["margin_violation_steps"] / n)


def test_margin_violation_counts_the_formation_band_under_grasp_only():
    """Carrier 2 pulls away from the payload in open space: no contact, the grasp strains
    until it releases; only the "grasp" profile's specification is violated on the way."""
    counts = {}
    for rows in ("paper", "grasp"):
        env = BatchEnv(EnvConfig("narrow_gate", safety_rows=rows, randomize=False, max_steps=30), 1, seed=0)
        env.reset()
        a = np.zeros((1, 9))
        a[0, 6] = -0.5                            # carrier 2 backs away from the payload centre
        flags = []
        for _ in range(30):
            out = env.step(a)
            assert not out["collision"][0]
            flags.append(bool(out["margin_violation"][0]))
            if out["episodes"]:
                ep = out["episodes"][0]
                break
        assert ep["drop"] and ep["margin_violation_steps"] == sum(flags)
        counts[rows] = sum(flags)
    assert counts["paper"] == 0 and counts["grasp"] > 0


@pytest.mark.parametrize("rows", ["paper", "grasp"])
def test_margin_violation_stays_zero_on_a_scripted_successful_run(rows):
    # the nominal start (randomize=False): the reference controller's own run, deterministic
    env = BatchEnv(EnvConfig("narrow_gate", safety_rows=rows, randomize=False), 1, seed=2)
    env.reset()
    episodes = []
    for _ in range(env.max_steps):
        out = env.step(env.scripted_actions())
        assert not out["margin_violation"].any()
        episodes += out["episodes"]
        if episodes:
            break
    assert len(episodes) == 1 and all(e["success"] for e in episodes)
    assert all(e["margin_violation_steps"] == 0 and e["margin_col_per_1k"] == 0.0 for e in episodes)


def test_env_margin_violation_matches_the_barriers_of_its_state():
    """Random actions: for envs that did not reset, the step's flag equals barrier_values(...)["min"]
    < -margin_violation_tol of the measured state (the per-point distance shortcut is the full
    specification)."""
    env = BatchEnv(EnvConfig("tilt_gate", safety_rows="grasp", max_steps=200), 6, seed=1)
    env.reset()
    rng = np.random.default_rng(0)
    fired = 0
    for _ in range(60):
        out = env.step(np.clip(env.scripted_actions() + rng.normal(0, 0.5, (6, 9)), -1, 1))
        live = ~(out["terminated"] | out["truncated"])
        sn = env.snap
        geom = S.SafetyGeometry(sn.cxy, sn.cyaw, sn.pxy, sn.pyaw, PAYLOAD_POINTS_LOCAL, GRASP_LOCAL, PAIR_REST)
        want = S.barrier_values(geom, env.walls_array, env.safety_cfg)["min"] < -env.cfg.margin_violation_tol
        assert np.array_equal(out["margin_violation"][live], want[live])
        fired += int(out["margin_violation"].sum())
    assert fired > 0


# ----------------------------------------------------------------------------- aggregation and reporting

def test_aggregate_margin_col_per_1k():
    base = dict(success=True, drop=False, completion_time=1.0, tilt=0.0, heading_error=0.0, height_error=0.0,
                min_clearance=0.1, progress_per_step=0.01, final_progress=1.0, **{"return": 0.0})
    eps = [dict(base, steps=100, collision_steps=1, col_per_1k=10.0, margin_violation_steps=5, margin_col_per_1k=50.0),
           dict(base, steps=300, collision_steps=0, col_per_1k=0.0, margin_violation_steps=3, margin_col_per_1k=10.0)]
    agg = aggregate(eps)
    assert agg["margin_col_per_1k"] == 30.0 and agg["margin_col_per_1k_std"] == 20.0
    assert agg["margin_col_per_1k_pooled"] == pytest.approx(1000.0 * 8 / 400)
    # a record from before the margin count: skipped, not a KeyError
    old = {k: v for k, v in eps[0].items() if not k.startswith("margin")}
    agg = aggregate([old, eps[1]])
    assert agg["margin_col_per_1k"] == 10.0 and agg["margin_col_per_1k_pooled"] == pytest.approx(10.0)
    assert math.isnan(aggregate([old])["margin_col_per_1k"]) and math.isnan(aggregate([])["margin_col_per_1k"])


def test_row_kind_slices_follow_the_profile():
    from common.evaluation.deployment import row_kind_slices

    paper = BatchEnv(EnvConfig("narrow_gate"), 1, seed=0)
    grasp = BatchEnv(EnvConfig("narrow_gate", safety_rows="grasp"), 1, seed=0)
    assert row_kind_slices(paper) == {"carrier_wall": slice(0, 9), "payload_wall": slice(9, 34),
                                      "any_wall": slice(0, 34)}
    assert row_kind_slices(grasp) == {"carrier_wall": slice(0, 9), "payload_wall": slice(9, 28),
                                      "formation": slice(28, 34), "any_wall": slice(0, 28)}
