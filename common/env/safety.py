"""Affine safety rows ``C(x) a >= c(x)`` (Eq. joint_safety_rows) from one-step discrete CBFs.

The environment calls :func:`build_rows` every control step with ``x = Φ(s)``
(a :class:`SafetyGeometry`, batched over K envs) and hands the rows to the
joint CBF-QP shield (Eq. qpshield). Every row is the linearization of a
one-step discrete-time CBF condition

    h(x⁺) >= (1 - α) h(x),      x⁺ = F(x) + B(x) a                   (*)

under the linear one-step predictor below. As the paper states (Sec. III-B),
the guarantee is *predictor-level*: rows are conservative lower bounds of (*)
for the predicted state; how honest the predictor is about the real MuJoCo
step is measured by :func:`measure_honesty`, not assumed.

One-step predictor (linear in the stacked action ``a in [-1, 1]^9``):
  * carrier ``i`` moves by ``d_i = max_step_xy R(ψ_i) [Δx_i, Δy_i]`` and turns
    by ``max_step_yaw Δψ_i``;
  * the payload follows the least-squares rigid fit of the three carrier
    displacements applied at the grasps: translation ``t = mean_i d_i`` and
    small rotation ``δθ = Σ r_i × d_i / Σ |r_i|²`` about the grasp centroid
    ``g`` (``r_i`` = grasp ``i`` minus ``g``; ``Σ r_i = 0`` decouples the two),
    so a payload point ``p`` moves to ``p + t + δθ J (p - g)`` with ``J`` the
    90° rotation. For an exactly rigid carrier motion by angle ``θ`` this is
    the exact motion up to ``O(θ²)`` (``δθ = sin θ``).

Row profiles (``SafetyConfig.profile``, set from ``EnvConfig.safety_rows``):

* ``"paper"`` (default): collision rows only. Sec. III-B does not list its
  rows, but Sec. IV scores the shield by collisions (Col./1k) and reports that
  direct shielding *raises* the payload drop rate, which a shield that keeps
  the grasp from straining could not do. Slots are laid out
  ``[carrier-wall | payload-wall]``. Grasp strain is not a shield constraint:
  a drop (strain above ``EnvConfig.drop_strain``) is a task outcome (DR) that
  the shield does not prevent.
* ``"grasp"``: our extension, not in the paper. It adds the formation rows that
  keep every pair distance within ``grasp_tol`` of rest, so the grasp never
  strains; slots are ``[carrier-wall | payload-wall | formation]``, the 6
  formation rows last.

No carrier-carrier separation rows in either profile: (1) MuJoCo does not
collide carriers with each other (common/env/mjcf.py contact filter), so no
collision measure could count such a contact; (2) while the payload is held
(a drop ends the episode) the grasps, rigid on the board, keep carriers ``i, k``
at ``D_ik >= D0_ik - s_i - s_k > min D0 - 2 drop_strain = 0.894 - 0.4 = 0.494 m``
with strains ``s < drop_strain``, i.e. the 0.25 m discs (touching at 0.5 m)
could meet only with both grasps at the release threshold at once; (3) with
the shield's disc margin (``carrier_radius`` 0.30 m, 0.60 m between centres) a
separation barrier ``D - 0.60`` is only 0.29 m at rest for the short pairs and
two carriers can close 0.23 m in one step, so the row would constrain ordinary
formation motions and go negative at ~0.15 m of strain per carrier: a
one-sided formation row, which is what ``"paper"`` leaves out.

Row kinds:
  0. carrier-wall: ``h = sd(p_i, box) - carrier_radius``;
  1. payload-wall: ``h = sd(p_j, box) - payload_margin`` for payload boundary
     points, whose predicted motion couples all three carriers;
  2. formation (``"grasp"`` only): for each pair ``(i, k)`` with distance ``D``
     and rest distance ``D0``, ``h_lo = D - (D0 - grasp_tol)`` and
     ``h_hi = (D0 + grasp_tol) - D``.

Wall rows use the supporting half-plane at the closest point ``q`` of the box
with outward unit normal ``n`` (``(p - q)/|p - q|`` outside, the normal of the
nearest face inside or on the boundary):

    n · (p⁺ - q) - r >= (1 - α) h      <=>      (n^T B) a >= -α h

(using ``n · (p - q) = sd(p)`` in both cases). Why this is conservative: the
signed distance to a *convex* set is a convex function of the point, and
``n`` is a (sub)gradient of it at ``p``, so for every ``y``

    sd(y) >= sd(p) + n · (y - p) = n · (y - q).

Hence any action satisfying the row gives ``sd(p⁺) - r >= (1 - α) h`` at the
predicted point: the half-plane is an inner approximation of the box exterior.
The formation lower row is conservative for the same reason (``|·|`` is
convex); the upper row (``D⁺ <= ...``) is only first-order accurate, with error
``|Δ_⊥|² / (2D)`` for the relative displacement ``Δ_⊥`` perpendicular to the
pair; with centimetre steps and metre spacings that is far below ``grasp_tol``.

No row divides by ``h``: if a barrier is already negative (a violation), its
row still asks for the recovery ``h⁺ >= (1 - α) h`` (i.e. at least an ``α``
fraction of the violation is undone, predictor-level), which may be infeasible
inside the action box; the QP's slack answer handles that. Rows are not
normalized here (that is ``common.policy.sail.normalize_rows``); rows whose
coefficients vanish are masked instead of emitted.

Budget split for ``max_rows = M`` slots: the formation rows (6 under
``"grasp"``, 0 under ``"paper"``) always get their slots; carrier-wall rows get
``3 * walls_per_carrier`` slots; payload-wall rows get the rest,
``M - formation - 3 * walls_per_carrier``. Defaults for M = 34:
``"paper"`` 9 carrier-wall + 25 payload-wall, ``"grasp"`` 9 + 19 + 6.
Why: a row can bind (some action in the box violates it) only if one step can
close its barrier by ``α h``, i.e. ``|C|_1 > α h``; a carrier moves at most
``sqrt(2) max_step_xy`` = 0.11 m per step, so its rows bind only within
``~0.11 / α`` = 0.38 m of a wall. A convex 0.6 m disc (radius + margin) has at
most the two sides of a gate or corridor, or the two walls of a corner, that
close: 3 walls per carrier keep one spare. The payload's 60 boundary points
(0.08 m apart) face walls in runs of adjacent points, on both sides of a gate
at once, and its rows are the ones coupling all three carriers (translation
and rotation), so it gets every other slot. Measured on scripted runs with
N(0, 0.3) action noise (all 9 scenarios, 4 envs each, full episodes): at most
2 bindable walls per carrier; bindable payload candidates exceed 25 in <= 0.7%
of steps except in needle_gate (19%, its thin posts), and exceed 16 (the old
``"grasp"`` split 12 + 16 + 6) in up to 7% (36% in needle_gate).
Candidates of a kind are, per entity (carrier or payload point), its
``walls_per_*`` nearest walls with ``h <= search_radius``; if a kind has more
candidates than slots, the smallest-``h`` ones are kept. Rows within a wall
kind are ordered by ``h`` ascending and padded at the end of the kind's block
(``row_mask`` False, zero coefficients, ``h = 0``). :attr:`SafetyConfig.kind_slices`
gives each kind's slots.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from common.env import kernels
from common.env.geometry import wall_table
from common.env.layout import PAIRS
from common.spec import JOINT_ACT_DIM, N_CARRIERS

N_FORMATION_ROWS = 2 * len(PAIRS)
KIND_CARRIER_WALL, KIND_PAYLOAD_WALL, KIND_FORMATION = 0, 1, 2
PROFILES = ("paper", "grasp")   # row profiles (module docstring); "grasp" adds the formation rows
_EPS = 1e-12


@dataclass(frozen=True)
class SafetyConfig:
    """Safety model parameters (one source of defaults; lengths in metres, angles in rad)."""

    alpha: float = 0.2               # discrete CBF rate in h(x⁺) >= (1-α) h(x), in (0, 1]
    max_rows: int = 34               # M
    carrier_radius: float = 0.30     # carrier footprint as a disc
    payload_margin: float = 0.05     # clearance kept by payload boundary points
    walls_per_carrier: int = 3       # nearest walls per carrier (also sets the carrier budget, 3x this)
    walls_per_point: int = 2         # nearest walls per payload boundary point
    search_radius: float = 1.0       # walls with h above this are not candidates
    grasp_tol: float = 0.05          # allowed pair-distance deviation from rest
    max_step_xy: float = 0.05        # carrier displacement per unit action per control step
    max_step_yaw: float = 0.10       # carrier turn per unit action per control step
    profile: str = "paper"           # "paper": wall rows only; "grasp": + formation rows (our extension)

    def __post_init__(self):
        if self.profile not in PROFILES:
            raise ValueError(f"SafetyConfig.profile must be one of {PROFILES}, got {self.profile!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "profile":
                continue
            if not np.isfinite(v):
                raise ValueError(f"SafetyConfig.{f.name} must be finite, got {v!r}")
        if not 0.0 < self.alpha <= 1.0:
            raise ValueError(f"SafetyConfig.alpha must be in (0, 1], got {self.alpha}")
        for name in ("carrier_radius", "payload_margin", "grasp_tol"):
            if getattr(self, name) < 0:
                raise ValueError(f"SafetyConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("search_radius", "max_step_xy", "max_step_yaw"):
            if getattr(self, name) <= 0:
                raise ValueError(f"SafetyConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("max_rows", "walls_per_carrier", "walls_per_point"):
            v = getattr(self, name)
            if int(v) != v or v < 0:
                raise ValueError(f"SafetyConfig.{name} must be a non-negative integer, got {v!r}")
        if self.payload_budget < 0:
            raise ValueError(
                f"SafetyConfig.max_rows={self.max_rows} is smaller than the {self.formation_budget} "
                f"formation rows ({self.profile!r} profile) plus "
                f"3*walls_per_carrier={3 * self.walls_per_carrier} carrier rows")

    @property
    def carrier_budget(self) -> int:
        return N_CARRIERS * int(self.walls_per_carrier)

    @property
    def formation_budget(self) -> int:
        """Formation slots: 6 under ``"grasp"``, none under ``"paper"``."""
        return N_FORMATION_ROWS if self.profile == "grasp" else 0

    @property
    def payload_budget(self) -> int:
        return int(self.max_rows) - self.formation_budget - self.carrier_budget

    @property
    def kind_slices(self) -> dict[str, slice]:
        """Row slots of each kind the profile has: ``carrier_wall``, ``payload_wall`` and,
        under ``"grasp"`` only, ``formation`` (the last ``N_FORMATION_ROWS`` slots)."""
        cb, pb = self.carrier_budget, self.payload_budget
        out = {"carrier_wall": slice(0, cb), "payload_wall": slice(cb, cb + pb)}
        if self.formation_budget:
            out["formation"] = slice(cb + pb, cb + pb + self.formation_budget)
        return out

    @property
    def slot_kinds(self) -> np.ndarray:
        """Kind of every row slot ``[M]`` (``KIND_*``)."""
        return np.repeat([KIND_CARRIER_WALL, KIND_PAYLOAD_WALL, KIND_FORMATION],
                         [self.carrier_budget, self.payload_budget, self.formation_budget])


@dataclass
class SafetyGeometry:
    """``x = Φ(s)``: the physical variables of K envs that the safety model needs."""

    carrier_xy: np.ndarray            # [K,3,2] carrier centers (world)
    carrier_yaw: np.ndarray           # [K,3]
    payload_xy: np.ndarray            # [K,2] payload frame origin (world)
    payload_yaw: np.ndarray           # [K]
    payload_points_local: np.ndarray  # [P,2] boundary points in the payload frame
    grasp_local: np.ndarray           # [3,2] grasp points in the payload frame
    pair_rest: np.ndarray             # [3] rest distances of pairs (0,1),(0,2),(1,2)

    def __post_init__(self):
        for f in fields(self):
            arr = np.asarray(getattr(self, f.name), dtype=np.float64)
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"SafetyGeometry.{f.name} contains NaN or Inf")
            setattr(self, f.name, arr)
        K = self.carrier_xy.shape[0] if self.carrier_xy.ndim == 3 else -1
        expect = {
            "carrier_xy": (K, N_CARRIERS, 2), "carrier_yaw": (K, N_CARRIERS),
            "payload_xy": (K, 2), "payload_yaw": (K,),
            "grasp_local": (N_CARRIERS, 2), "pair_rest": (len(PAIRS),),
        }
        for name, shape in expect.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"SafetyGeometry.{name} has shape {getattr(self, name).shape}, "
                                 f"expected {shape} (K from carrier_xy [K,3,2])")
        if self.payload_points_local.ndim != 2 or self.payload_points_local.shape[1] != 2:
            raise ValueError("SafetyGeometry.payload_points_local must be [P,2], "
                             f"got {self.payload_points_local.shape}")

    @property
    def num_envs(self) -> int:
        return self.carrier_xy.shape[0]


# ----------------------------------------------------------------------------- geometry helpers

def _rot(theta: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 2, 2] for angles [...]."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _perp(v: np.ndarray) -> np.ndarray:
    """J v: rotate 2-vectors [..., 2] by +90 degrees."""
    return np.stack([-v[..., 1], v[..., 0]], -1)


def payload_points_world(geom: SafetyGeometry) -> np.ndarray:
    """Payload boundary points in world coordinates [K,P,2]."""
    R = _rot(geom.payload_yaw)                                   # [K,2,2]
    return geom.payload_xy[:, None] + np.einsum("kab,pb->kpa", R, geom.payload_points_local)


def grasp_world(geom: SafetyGeometry) -> np.ndarray:
    """Grasp points in world coordinates [K,3,2]."""
    R = _rot(geom.payload_yaw)
    return geom.payload_xy[:, None] + np.einsum("kab,pb->kpa", R, geom.grasp_local)


def _check_walls(walls: np.ndarray, K: int) -> np.ndarray:
    """Walls as [K,W,5] float64 (a shared [W,5] array is broadcast)."""
    walls = np.asarray(walls, dtype=np.float64)
    if walls.ndim == 2:
        walls = np.broadcast_to(walls, (K,) + walls.shape)
    if walls.ndim != 3 or walls.shape[0] != K or walls.shape[2] != 5:
        raise ValueError(f"walls must be [W,5] or [K,W,5] (cx, cy, hx, hy, yaw), got {walls.shape}")
    if not np.all(np.isfinite(walls)):
        raise ValueError("walls contain NaN or Inf")
    if np.any(walls[..., 2:4] < 0):
        raise ValueError("wall half-sizes hx, hy must be >= 0")
    return walls


def point_box_distance(p: np.ndarray, walls: np.ndarray):
    """Signed distance of points to oriented boxes, with closest point and normal.

    ``p [K,E,2]``, ``walls [K,W,5]`` -> ``sd, q, n`` of shapes ``[K,E,W]``,
    ``[K,E,W,2]``, ``[K,E,W,2]``: ``sd`` is positive outside, ``q`` is the
    closest boundary point and ``n`` the outward unit normal, ``(p - q)/|p - q|``
    outside and the nearest face's normal inside or on the boundary (ties go to
    the x-face, a valid subgradient either way). ``n · (p - q) = sd`` always.
    """
    center = walls[:, None, :, 0:2]                              # [K,1,W,2]
    half = walls[:, None, :, 2:4]
    R = _rot(walls[:, None, :, 4])                               # [K,1,W,2,2]
    local = np.einsum("...ba,...b->...a", R, p[:, :, None, :] - center)  # R^T (p - c)
    clamped = np.clip(local, -half, half)
    diff = local - clamped
    dist_out = np.linalg.norm(diff, axis=-1)
    inside = dist_out == 0.0                                     # on or inside the box
    # Inside: depth to the x- and y-faces; the nearest face gives q and n.
    sign = np.where(local >= 0.0, 1.0, -1.0)
    depth = half - np.abs(local)                                 # [...,2] >= 0 inside
    use_x = depth[..., 0] <= depth[..., 1]
    face_n = np.where(use_x[..., None], np.stack([sign[..., 0], 0 * sign[..., 0]], -1),
                      np.stack([0 * sign[..., 1], sign[..., 1]], -1))
    face_q = np.where(use_x[..., None], np.stack([sign[..., 0] * half[..., 0], local[..., 1]], -1),
                      np.stack([local[..., 0], sign[..., 1] * half[..., 1]], -1))
    safe = np.where(inside, 1.0, dist_out)
    n_local = np.where(inside[..., None], face_n, diff / safe[..., None])
    q_local = np.where(inside[..., None], face_q, clamped)
    sd = np.where(inside, -np.min(depth, axis=-1), dist_out)
    n = np.einsum("...ab,...b->...a", R, n_local)
    q = center + np.einsum("...ab,...b->...a", R, q_local)
    return sd, q, n


# ----------------------------------------------------------------------------- predictor

def predictor_matrices(geom: SafetyGeometry, cfg: SafetyConfig):
    """The affine one-step predictor ``x⁺ = x + B a`` for the quantities the rows use.

    Returns ``carrier_B [K,3,2,9]`` (carrier displacement), ``point_B [K,P,2,9]``
    (payload point displacement) and ``theta_B [K,9]`` (payload rotation δθ).
    """
    K = geom.num_envs
    carrier_B = np.zeros((K, N_CARRIERS, 2, JOINT_ACT_DIM))
    Rc = cfg.max_step_xy * _rot(geom.carrier_yaw)               # [K,3,2,2]
    for i in range(N_CARRIERS):
        carrier_B[:, i, :, 3 * i:3 * i + 2] = Rc[:, i]
    g = grasp_world(geom)
    r = g - g.mean(axis=1, keepdims=True)                        # [K,3,2], Σ r_i = 0
    S = np.sum(r * r, axis=(1, 2))                                # Σ |r_i|²
    if np.any(S <= _EPS):
        raise ValueError("grasp points coincide: the payload rotation fit is undefined")
    # least-squares rigid fit: t = mean d_i, δθ = Σ r_i × d_i / Σ |r_i|²  (r × d = (J r)·d)
    trans_B = carrier_B.mean(axis=1)                              # [K,2,9]
    theta_B = np.einsum("kia,kiab->kb", _perp(r), carrier_B) / S[:, None]
    lever = _perp(payload_points_world(geom) - g.mean(axis=1, keepdims=True))  # J (p - g)
    point_B = trans_B[:, None] + lever[..., None] * theta_B[:, None, None, :]
    return carrier_B, point_B, theta_B


def predict(geom: SafetyGeometry, a: np.ndarray, cfg: SafetyConfig) -> dict:
    """One-step prediction for stacked actions ``a [K,9]``.

    Returns ``carrier_xy [K,3,2]``, ``carrier_yaw [K,3]``, ``payload_points [K,P,2]``
    (affine in ``a``), ``payload_theta [K]`` (δθ) and ``payload_translation [K,2]``.
    """
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (geom.num_envs, JOINT_ACT_DIM) or not np.all(np.isfinite(a)):
        raise ValueError(f"actions must be finite [K,{JOINT_ACT_DIM}] with K={geom.num_envs}, got {a.shape}")
    carrier_B, point_B, theta_B = predictor_matrices(geom, cfg)
    return {
        "carrier_xy": geom.carrier_xy + np.einsum("kiab,kb->kia", carrier_B, a),
        "carrier_yaw": geom.carrier_yaw + cfg.max_step_yaw * a[:, 2::3],
        "payload_points": payload_points_world(geom) + np.einsum("kpab,kb->kpa", point_B, a),
        "payload_theta": np.einsum("kb,kb->k", theta_B, a),
        "payload_translation": np.einsum("kiab,kb->ka", carrier_B, a) / N_CARRIERS,
    }


# ----------------------------------------------------------------------------- barriers

def _pair_terms(carrier_xy: np.ndarray):
    """Pair distances [K,3] and unit vectors [K,3,2] for pairs (0,1),(0,2),(1,2)."""
    i, k = np.array(PAIRS).T
    diff = carrier_xy[:, i] - carrier_xy[:, k]
    dist = np.linalg.norm(diff, axis=-1)
    unit = diff / np.where(dist > _EPS, dist, 1.0)[..., None]
    return dist, unit


def barrier_values(geom: SafetyGeometry, walls: np.ndarray, cfg: SafetyConfig) -> dict:
    """True barrier values at a state (exact distances, no linearization).

    ``carrier_wall [K,3,W]``, ``payload_wall [K,P,W]``, ``formation [K,3,2]``
    (``(h_lo, h_hi)`` per pair; ``[K,0,2]`` under the ``"paper"`` profile, which
    has no formation barriers) and ``min [K]`` over all of them (``inf`` if none).
    """
    return barriers_at_points(geom.carrier_xy, payload_points_world(geom), geom.pair_rest, walls, cfg)


def barriers_at_points(carrier_xy, payload_points, pair_rest, walls, cfg: SafetyConfig) -> dict:
    """:func:`barrier_values` for explicit world points ``carrier_xy [K,3,2]``,
    ``payload_points [K,P,2]`` (e.g. the predictor's next points)."""
    K = carrier_xy.shape[0]
    walls = _check_walls(walls, K)
    sd_c = point_box_distance(carrier_xy, walls)[0] - cfg.carrier_radius
    sd_p = point_box_distance(payload_points, walls)[0] - cfg.payload_margin
    if cfg.formation_budget:
        dist, _ = _pair_terms(carrier_xy)
        form = np.stack([dist - (pair_rest - cfg.grasp_tol), (pair_rest + cfg.grasp_tol) - dist], -1)
    else:
        form = np.zeros((K, 0, 2))
    mins = [np.full(K, np.inf)]
    for h in (form, sd_c, sd_p):
        if h.size:
            mins.append(h.reshape(K, -1).min(1))
    return {"carrier_wall": sd_c, "payload_wall": sd_p, "formation": form,
            "min": np.min(np.stack(mins, -1), -1)}


def spec_barrier_min(carrier_sd, payload_sd, carrier_xy, pair_rest, cfg: SafetyConfig) -> np.ndarray:
    """Smallest true barrier of the profile's specification [K] from precomputed distances.

    ``carrier_sd [K,3]`` and ``payload_sd [K,P]`` are each point's signed distance to
    its nearest wall (the env's snapshot has them, numba-computed), ``carrier_xy
    [K,3,2]`` gives the pair distances for the ``"grasp"`` formation band. Equals
    ``barriers_at_points(...)["min"]`` (same margins, ``inf`` without any barrier) at
    O(K) extra cost; ``< 0`` is a margin violation (``BatchEnv`` ``margin_violation``).
    Computed by the numba kernel ``common.env.kernels.spec_barrier_min``;
    ``reference.spec_barrier_min`` is the same computation in numpy.
    """
    carrier_sd = np.asarray(carrier_sd, dtype=np.float64)
    payload_sd = np.asarray(payload_sd, dtype=np.float64)
    K = carrier_sd.shape[0]
    out = np.full(K, np.inf)
    if K:
        kernels.spec_barrier_min(carrier_sd.reshape(K, -1), payload_sd.reshape(K, -1),
                                 np.asarray(carrier_xy, dtype=np.float64), np.asarray(pair_rest, dtype=np.float64),
                                 cfg.carrier_radius, cfg.payload_margin, cfg.grasp_tol, bool(cfg.formation_budget),
                                 out)
    return out


# ----------------------------------------------------------------------------- rows


class SafetyModel:
    """The safety model of a batch of ``num_envs`` envs with fixed walls and config, checked and
    laid out once, so that a call is a kernel and its (fresh) outputs: ``BatchEnv``'s per-step
    path. Geometry arrays are float64 as in :class:`SafetyGeometry`.

    ``rows(carrier_xy, carrier_yaw, payload_xy, payload_yaw, payload_points_local, grasp_local,
    pair_rest)`` returns ``C, c, row_mask, h, entity, wall`` as :func:`build_rows` (ValueError on
    a non-finite state or coincident grasp points); ``barrier_min(carrier_sd, payload_sd,
    carrier_xy, pair_rest)`` is :func:`spec_barrier_min` for ``[K,3]``, ``[K,P]`` distances.
    """

    def __init__(self, walls: np.ndarray, cfg: SafetyConfig, num_envs: int):
        walls = np.asarray(walls, dtype=np.float64)
        _check_walls(walls, num_envs)
        self.tables = wall_table(walls[None] if walls.ndim == 2 else walls)   # [1 or K, 6, W]
        self.cfg = cfg
        self.num_envs = num_envs
        self._rows_prm = (float(cfg.max_step_xy), float(cfg.alpha), float(cfg.carrier_radius),
                          float(cfg.payload_margin), float(cfg.grasp_tol), float(cfg.search_radius),
                          int(cfg.walls_per_carrier), int(cfg.walls_per_point), cfg.carrier_budget,
                          cfg.payload_budget, cfg.formation_budget)
        self._barrier_prm = (float(cfg.carrier_radius), float(cfg.payload_margin), float(cfg.grasp_tol),
                             bool(cfg.formation_budget))

    def set_walls(self, k: int, walls: np.ndarray):
        """Env k's walls ``[W,5]`` from now on (a drawn layout; the model must hold per-env walls)."""
        walls = np.asarray(walls, dtype=np.float64)
        if self.tables.shape[0] != self.num_envs or walls.shape != (self.tables.shape[2], 5):
            raise ValueError(f"set_walls needs per-env walls [K,W,5] at construction and [W,5] here, got {walls.shape}")
        if not np.isfinite(walls).all() or (walls[:, 2:4] < 0).any():
            raise ValueError("walls must be finite with non-negative half-sizes")
        self.tables[k] = wall_table(walls)

    def rows(self, carrier_xy, carrier_yaw, payload_xy, payload_yaw, payload_points_local, grasp_local, pair_rest):
        K, M = self.num_envs, int(self.cfg.max_rows)
        C, c, h = np.empty((K, M, JOINT_ACT_DIM)), np.empty((K, M)), np.empty((K, M))
        mask = np.empty((K, M), dtype=bool)
        entity, wall = np.empty((K, M), dtype=np.int64), np.empty((K, M), dtype=np.int64)
        status = kernels.safety_rows(carrier_xy, carrier_yaw, payload_xy, payload_yaw, payload_points_local,
                                     grasp_local, pair_rest, self.tables, *self._rows_prm, C, c, mask, h, entity,
                                     wall)
        if status == kernels.ROWS_COINCIDE:
            raise ValueError("grasp points coincide: the payload rotation fit is undefined")
        if status:
            raise ValueError("safety geometry contains NaN or Inf")
        return C, c, mask, h, entity, wall

    def barrier_min(self, carrier_sd, payload_sd, carrier_xy, pair_rest) -> np.ndarray:
        out = np.empty(self.num_envs)
        kernels.spec_barrier_min(carrier_sd, payload_sd, carrier_xy, pair_rest, *self._barrier_prm, out)
        return out


def build_rows(geom: SafetyGeometry, walls: np.ndarray, cfg: SafetyConfig):
    """Affine rows ``C a >= c`` (Eq. joint_safety_rows) for the next stacked action.

    Returns ``C [K,M,9]``, ``c [K,M]``, ``row_mask [K,M]`` and ``info`` with
    ``h [K,M]`` (barrier value of each row at ``x``), ``kind [K,M]`` (0
    carrier-wall, 1 payload-wall, 2 formation; formation slots exist only under
    the ``"grasp"`` profile), ``entity [K,M]`` (carrier, payload point or pair
    index; -1 on padding) and ``wall [K,M]`` (-1 if none).
    See the module docstring for the derivation, conservativeness and budget.
    Computed per env by the numba kernel ``common.env.kernels.safety_rows`` (via
    :class:`SafetyModel`); ``reference.build_rows`` is the same computation in numpy.
    """
    if not isinstance(geom, SafetyGeometry):
        raise TypeError(f"geom must be a SafetyGeometry, got {type(geom).__name__}")
    K = geom.num_envs
    C, c, mask, h, entity, wall = SafetyModel(walls, cfg, K).rows(
        geom.carrier_xy, geom.carrier_yaw, geom.payload_xy, geom.payload_yaw, geom.payload_points_local,
        geom.grasp_local, geom.pair_rest)
    info = {"h": h, "kind": np.broadcast_to(cfg.slot_kinds, (K, len(cfg.slot_kinds))).copy(), "entity": entity,
            "wall": wall}
    return C, c, mask, info
