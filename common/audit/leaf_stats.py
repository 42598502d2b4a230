"""Leaf-tuple audit statistics (Table leaf_interpretability, Fig. colortrace).

Cluster labels are leaves (one carrier) or joint tuples (l1, l2, l3); class
labels are route progress cut into equal bins. Three numbers per representation:

* purity  = sum_u max_v n_uv / n: the visit-weighted share of each leaf's (tuple's)
  majority progress bin;
* NMI     = I(U;V) / ((H(U) + H(V)) / 2), arithmetic-mean normalization (the
  default of scikit-learn's normalized_mutual_info_score), natural logs;
  1 when both labelings are constant, 0 when exactly one is;
* shuffle z = (observed - mean_null) / std_null, the null drawn by permuting the
  progress labels R times (which keeps both marginals and breaks the association).
"""
from __future__ import annotations

import numpy as np

from common.audit.config import AuditConfig


def progress_bins(progress: np.ndarray, n_bins: int) -> np.ndarray:
    """Progress in [0, 1] -> bin index in 0..n_bins-1 (progress 1.0 falls in the last bin)."""
    progress = np.asarray(progress, dtype=np.float64)
    if not np.all(np.isfinite(progress)):
        raise ValueError("progress has NaN or Inf")
    return np.clip(np.floor(np.clip(progress, 0.0, 1.0) * n_bins), 0, n_bins - 1).astype(np.int64)


def encode(labels: np.ndarray) -> np.ndarray:
    """Any label array [n] or tuples [n, k] -> dense codes 0..U-1 (row-wise unique)."""
    labels = np.asarray(labels)
    if labels.ndim == 1:
        return np.unique(labels, return_inverse=True)[1].reshape(-1)
    if labels.ndim == 2:
        return np.unique(labels, axis=0, return_inverse=True)[1].reshape(-1)
    raise ValueError(f"labels must be [n] or [n, k], got shape {labels.shape}")


def _contingency(u: np.ndarray, v: np.ndarray, n_u: int, n_v: int) -> np.ndarray:
    return np.bincount(u * n_v + v, minlength=n_u * n_v).reshape(n_u, n_v)


def _entropy(counts: np.ndarray, n: int) -> float:
    p = counts[counts > 0] / n
    return float(-np.sum(p * np.log(p)))


def purity(clusters: np.ndarray, classes: np.ndarray) -> float:
    """Share of samples whose class is their cluster's majority class."""
    u, v = encode(clusters), encode(classes)
    _check(u, v)
    table = _contingency(u, v, u.max() + 1, v.max() + 1)
    return float(table.max(axis=1).sum() / len(u))


def nmi(clusters: np.ndarray, classes: np.ndarray) -> float:
    """Normalized mutual information, arithmetic-mean normalization (see module doc)."""
    u, v = encode(clusters), encode(classes)
    _check(u, v)
    table = _contingency(u, v, u.max() + 1, v.max() + 1)
    return _nmi_from_table(table)


def _nmi_from_table(table: np.ndarray) -> float:
    n = int(table.sum())
    hu, hv = _entropy(table.sum(axis=1), n), _entropy(table.sum(axis=0), n)
    if hu == 0.0 and hv == 0.0:
        return 1.0
    nz = table > 0
    outer = np.outer(table.sum(axis=1), table.sum(axis=0)) / n ** 2  # p(u) p(v)
    pij = table[nz] / n
    mi = float(np.sum(pij * np.log(pij / outer[nz])))
    return max(mi, 0.0) / (0.5 * (hu + hv))


def _check(u: np.ndarray, v: np.ndarray) -> None:
    if len(u) != len(v):
        raise ValueError(f"cluster and class labels differ in length ({len(u)} vs {len(v)})")
    if len(u) == 0:
        raise ValueError("no samples")


def association(clusters: np.ndarray, classes: np.ndarray, shuffles: int, rng: np.random.Generator) -> dict:
    """Purity, NMI and their label-shuffle z-scores for one representation."""
    u, v = encode(clusters), encode(classes)
    _check(u, v)
    n_u, n_v = int(u.max()) + 1, int(v.max()) + 1
    table = _contingency(u, v, n_u, n_v)
    obs_purity = float(table.max(axis=1).sum() / len(u))
    obs_nmi = _nmi_from_table(table)
    null_p, null_n = np.empty(shuffles), np.empty(shuffles)
    for r in range(shuffles):
        t = _contingency(u, rng.permutation(v), n_u, n_v)
        null_p[r] = t.max(axis=1).sum() / len(u)
        null_n[r] = _nmi_from_table(t)

    def z(obs, null):
        sd = null.std(ddof=1)
        return float((obs - null.mean()) / sd) if sd > 0 else float("nan")

    return {"purity": obs_purity, "nmi": obs_nmi,
            "z_purity": z(obs_purity, null_p), "z_nmi": z(obs_nmi, null_n),
            "null_purity_mean": float(null_p.mean()), "null_nmi_mean": float(null_n.mean()),
            "n_clusters": n_u, "n_samples": int(len(u))}


def leaf_audit(leaves: np.ndarray, progress: np.ndarray, cfg: AuditConfig = AuditConfig()) -> dict:
    """Table leaf_interpretability from per-step leaves [S, N] and progress [S].

    Individual leaf: each carrier's statistics, then the mean over carriers.
    Joint tuple: (l_1, ..., l_N) as one label. "Shuffle z" is the NMI z-score;
    the purity z-score is reported alongside.
    """
    leaves = np.asarray(leaves)
    if leaves.ndim != 2 or leaves.shape[0] != len(progress):
        raise ValueError(f"leaves must be [S, N] with S = len(progress); got {leaves.shape}, {len(progress)}")
    classes = progress_bins(progress, cfg.progress_bins)
    rng = np.random.default_rng(cfg.seed)
    per_carrier = [association(leaves[:, i], classes, cfg.shuffles, rng) for i in range(leaves.shape[1])]
    keys = ("purity", "nmi", "z_purity", "z_nmi")
    # a carrier that never switches leaf has a degenerate null (std 0, z undefined = NaN);
    # z means are over the carriers where z is defined, and that count is reported
    individual = {k: float(np.mean([p[k] for p in per_carrier])) for k in ("purity", "nmi")}
    for k in ("z_purity", "z_nmi"):
        vals = [p[k] for p in per_carrier if np.isfinite(p[k])]
        individual[k] = float(np.mean(vals)) if vals else float("nan")
        individual[k + "_carriers"] = len(vals)
    joint = association(leaves, classes, cfg.shuffles, rng)
    return {"config": {"progress_bins": cfg.progress_bins, "shuffles": cfg.shuffles, "seed": cfg.seed,
                       "nmi_normalization": "arithmetic mean of entropies, natural log",
                       "shuffle_z": "z of NMI against R label permutations"},
            "n_steps": int(len(progress)),
            "individual_mean": individual, "individual_per_carrier": per_carrier, "joint": joint}


def audit_markdown(result: dict) -> str:
    ind, joint = result["individual_mean"], result["joint"]
    cfg = result["config"]
    n = len(result["individual_per_carrier"])
    zn = "" if ind["z_nmi_carriers"] == n else f" ({ind['z_nmi_carriers']}/{n} carriers)"
    lines = [
        f"Leaf association with route progress ({cfg['progress_bins']} bins, {result['n_steps']} steps, "
        f"R = {cfg['shuffles']} shuffles; NMI: {cfg['nmi_normalization']}).",
        "",
        "| Representation | Purity ↑ | Shuffle z (NMI) ↑ | NMI ↑ | Shuffle z (purity) | distinct labels |",
        "|---|---|---|---|---|---|",
        f"| Individual leaf (mean over carriers) | {ind['purity']:.3f} | {ind['z_nmi']:.1f}{zn} | {ind['nmi']:.2f} "
        f"| {ind['z_purity']:.1f} | {', '.join(str(p['n_clusters']) for p in result['individual_per_carrier'])} |",
        f"| Joint tuple (ℓ1, ℓ2, ℓ3) | {joint['purity']:.3f} | {joint['z_nmi']:.1f} | {joint['nmi']:.2f} "
        f"| {joint['z_purity']:.1f} | {joint['n_clusters']} |",
    ]
    return "\n".join(lines)
