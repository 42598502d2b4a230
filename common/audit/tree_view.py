"""Human-readable views of a hard oblique tree (Sec. III-B, Sec. IV-C).

Every internal node k is the predicate ``w_k . o > b_k`` (Eq. hard_gate) written
with the environment's named features, largest |w| first; every leaf is the
affine command ``c_a + s_a * tanh(K_l o + beta_l)`` (Eq. hard_tree_policy),
summarized by its bias command (its value at o = 0) and its largest gains.
Views: plain text, JSON, Graphviz dot source and a matplotlib PNG.
"""
from __future__ import annotations

import json

import numpy as np

from common.audit.config import AuditConfig
from common.audit.params import CarrierTree

ACTION_NAMES = ("Δx", "Δy", "Δψ")


def _num(x: float, digits: int = 2) -> str:
    s = f"{x:.{digits}f}"
    return "0." + "0" * digits if s.startswith("-") and float(s) == 0 else s


def format_linear(weights: np.ndarray, names: list[str], top: int, continued: bool = False) -> str:
    """``0.82·a − 0.41·b + (7 more, |w|≤0.1)``: the ``top`` largest-|w| terms, the rest folded.
    ``continued``: the sum follows another term, so the first term gets a "+ "/"− " too."""
    weights = np.asarray(weights, dtype=np.float64)
    order = np.argsort(-np.abs(weights), kind="stable")
    # terms that would print as 0.00 are folded into the remainder too
    n_shown = max(1, min(top, int(np.sum(np.abs(weights) >= 0.005))))
    shown = order[:n_shown]
    rest = np.array([j for j in order[n_shown:] if weights[j] != 0], dtype=np.int64)   # a sparse split's zeros are not terms
    parts = []
    for n, j in enumerate(shown):
        w = weights[j]
        mag = f"{_num(abs(w))}·{names[j]}"
        parts.append(("−" if w < 0 else "") + mag if n == 0 and not continued else ("− " if w < 0 else "+ ") + mag)
    if len(rest):
        parts.append(f"+ ({len(rest)} more, |w|≤{_num(float(np.max(np.abs(weights[rest]))))})")
    return " ".join(parts)


# A vector with at most this many non-zero weights (a split_k / leaf_k sparse
# tree) prints every term; a denser one its top_terms largest and a count.
FULL_TERMS = 8


def _in_units(w: np.ndarray, names: list[str], units: dict) -> tuple[np.ndarray, list[str], list[str]]:
    """Feature j is quantity_j / scale_j, so ``w.o = sum_j (w_j / scale_j) q_j``:
    the coefficients on the quantities, the names labelled ``name[unit]`` and the units."""
    scale = np.array([units[n][0] if n in units else 1.0 for n in names])
    unit = [units[n][1] if n in units else "" for n in names]
    return np.asarray(w, np.float64) / scale, [f"{n}[{u}]" if u else n for n, u in zip(names, unit)], unit


def _terms_shown(w: np.ndarray, top: int) -> int:
    used = int(np.sum(np.abs(w) >= 0.005))
    return max(top, used) if used <= FULL_TERMS else top


def format_predicate(w: np.ndarray, b: float, names: list[str], units: dict | None, top: int) -> str:
    """The split ``w.o > b`` (Eq. hard_gate) in physical, unit-carrying
    quantities of the carrier's body frame (``_in_units``). A one-feature split
    reads as a threshold on the quantity itself (``goal_dx > 1.55 m``); when all
    its terms share a unit the split is rescaled to a unit normal in that
    quantity space, so the threshold is a signed distance in that unit
    (``0.82·goal_dx[m] − 0.57·wall_dist_front[m] > 0.31 m``); mixed units keep
    per-unit coefficients. A sparse split lists every term, a dense one its
    ``top`` largest and how many more. Without ``units``: the scaled features."""
    w = np.asarray(w, dtype=np.float64)
    if units is None:
        return f"{format_linear(w, names, top)} > {_num(b)}"
    coef, labelled, unit = _in_units(w, names, units)
    used = np.flatnonzero(np.abs(w) >= 0.005)
    if len(used) == 1:
        j = int(used[0])
        thr = b / coef[j]
        return f"{names[j]} {'>' if coef[j] > 0 else '<'} {_num(thr)}{' ' + unit[j] if unit[j] else ''}"
    shared = {unit[j] for j in used}
    if len(shared) == 1 and "" not in shared:
        norm = float(np.linalg.norm(coef[used]))
        return f"{format_linear(coef / norm, labelled, _terms_shown(w, top))} > {_num(b / norm)} {shared.pop()}"
    return f"{format_linear(coef, labelled, _terms_shown(w, top))} > {_num(b)}"


def format_gain(k_row: np.ndarray, beta: float, names: list[str], units: dict | None, top: int) -> str:
    """One leaf gain row, ``tanh(beta + K_l[a].o)`` of Eq. (hard_tree_policy), in
    the same unit-carrying quantities as the predicates (every term when sparse)."""
    if units is None:
        return f"tanh({_num(beta)} {format_linear(k_row, names, top, continued=True)})"
    coef, labelled, _ = _in_units(k_row, names, units)
    return f"tanh({_num(beta)} {format_linear(coef, labelled, _terms_shown(k_row, top), continued=True)})"


def leaf_path(tree: CarrierTree, leaf: int) -> list[tuple[int, bool]]:
    """Root-to-leaf (node id, side) pairs; side True = right (``w.o > b``)."""
    node = tree.n_internal + leaf
    path = []
    while node > 0:
        parent = (node - 1) // 2
        path.append((parent, node == 2 * parent + 2))
        node = parent
    return path[::-1]


def describe_tree(tree: CarrierTree, names: list[str], cfg: AuditConfig = AuditConfig(),
                  visits: np.ndarray | None = None, units: dict | None = None) -> dict:
    """JSON-ready description: internal predicates (in physical units with
    ``units``, ``common.env.observations.feature_units``), leaf commands, bounds and visits."""
    if len(names) != tree.obs_dim:
        raise ValueError(f"{len(names)} feature names for obs_dim {tree.obs_dim}")
    if visits is not None and len(visits) != tree.n_leaves:
        raise ValueError(f"visits has {len(visits)} entries for {tree.n_leaves} leaves")
    w = tree.unit_W()
    nodes = []
    for k in range(tree.n_internal):
        nodes.append({
            "id": k,
            "depth": int(np.floor(np.log2(k + 1))),
            "predicate": format_predicate(w[k], tree.b[k], names, units, cfg.top_terms),
            "n_features": int(np.sum(w[k] != 0)),
            "left": 2 * k + 1, "right": 2 * k + 2,   # left: predicate false, right: true
            "w": w[k].tolist(), "b": float(tree.b[k]),
        })
    bias = tree.bias_command()
    total = None if visits is None else int(np.sum(visits))
    leaves = []
    for leaf in range(tree.n_leaves):
        gains = {
            ACTION_NAMES[a] if a < len(ACTION_NAMES) else f"a{a}":
                format_gain(tree.K[leaf, a], tree.beta[leaf, a], names, units, cfg.top_terms)
            for a in range(tree.act_dim)
        }
        entry = {
            "leaf": leaf, "id": tree.n_internal + leaf,
            "bias_command": [round(float(v), 4) for v in bias[leaf]],
            "gains": gains,
            "bounds": [[float(c - s), float(c + s)] for c, s in zip(tree.c_a, tree.s_a)],
            "path": [{"node": k, "side": "right" if s else "left"} for k, s in leaf_path(tree, leaf)],
            "K": tree.K[leaf].tolist(), "beta": tree.beta[leaf].tolist(),
        }
        if visits is not None:
            entry["visits"] = int(visits[leaf])
            entry["visit_share"] = float(visits[leaf] / total) if total else 0.0
        leaves.append(entry)
    return {"depth": tree.depth, "obs_dim": tree.obs_dim, "feature_names": list(names),
            "c_a": tree.c_a.tolist(), "s_a": tree.s_a.tolist(), "nodes": nodes, "leaves": leaves}


def _cmd(values) -> str:
    return "[" + ", ".join(_num(v) for v in values) + "]"


def _scale_text(c_a, s_a) -> str:
    return ", ".join(f"{n}∈[{_num(c - s)}, {_num(c + s)}]" for n, c, s in zip(ACTION_NAMES, c_a, s_a))


def tree_text(desc: dict, title: str = "") -> str:
    """Indented text: a predicate line per internal node, its false branch then its true branch."""
    lines = [title] if title else []
    lines.append(f"depth {desc['depth']}, {len(desc['leaves'])} leaves; action bounds {_scale_text(desc['c_a'], desc['s_a'])}")
    lines.append("leaf command = c_a + s_a ⊙ tanh(K·o + β); [Δx, Δy, Δψ] shown at o = 0")
    n_int = len(desc["nodes"])

    def walk(node: int, indent: str, label: str) -> None:
        if node < n_int:
            nd = desc["nodes"][node]
            lines.append(f"{indent}{label}N{node}: {nd['predicate']}")
            walk(nd["left"], indent + "    ", "no  → ")
            walk(nd["right"], indent + "    ", "yes → ")
        else:
            lf = desc["leaves"][node - n_int]
            visits = f"  visits {lf['visits']} ({100 * lf['visit_share']:.1f}%)" if "visits" in lf else ""
            lines.append(f"{indent}{label}L{lf['leaf']}: {_cmd(lf['bias_command'])}{visits}")
            for name, g in lf["gains"].items():
                lines.append(f"{indent}      {name} ← {g}")

    walk(0, "", "")
    return "\n".join(lines)


def tree_json(desc: dict) -> str:
    return json.dumps(desc, indent=1, ensure_ascii=False)


def tree_dot(desc: dict, title: str = "") -> str:
    """Graphviz source (render elsewhere with ``dot -Tpng``; the binary is not needed here)."""
    esc = lambda s: s.replace("\\", "\\\\").replace('"', '\\"')
    out = ["digraph tree {", '  node [shape=box, fontname="Helvetica", fontsize=10];']
    if title:
        out.append(f'  label="{esc(title)}"; labelloc=t;')
    for nd in desc["nodes"]:
        out.append(f'  n{nd["id"]} [label="N{nd["id"]}\\n{esc(nd["predicate"])}"];')
        out.append(f'  n{nd["id"]} -> n{nd["left"]} [label="no"];')
        out.append(f'  n{nd["id"]} -> n{nd["right"]} [label="yes"];')
    for lf in desc["leaves"]:
        visits = f"\\nvisits {lf['visits']}" if "visits" in lf else ""
        out.append(f'  n{lf["id"]} [shape=ellipse, label="L{lf["leaf"]}\\n{esc(_cmd(lf["bias_command"]))}{visits}"];')
    out.append("}")
    return "\n".join(out)


def node_positions(depth: int) -> dict[int, tuple[float, float]]:
    """Left-to-right layout: x = depth, leaves evenly spaced in y, parents centred on children."""
    n_internal = 2 ** depth - 1
    pos = {n_internal + l: (float(depth), -float(l)) for l in range(2 ** depth)}
    for k in range(n_internal - 1, -1, -1):
        pos[k] = (float(np.floor(np.log2(k + 1))), 0.5 * (pos[2 * k + 1][1] + pos[2 * k + 2][1]))
    return pos


def tree_png(desc: dict, path: str, title: str = "") -> None:
    """Whole tree, left to right; each box: node predicate (as `describe_tree` words it) or leaf command and visits."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    depth = desc["depth"]
    n_int = len(desc["nodes"])
    pos = node_positions(depth)
    n_leaves = 2 ** depth
    fig, ax = plt.subplots(figsize=(3.8 * (depth + 1), max(4.0, 0.62 * n_leaves + 1)))
    max_visits = max((lf.get("visits", 0) for lf in desc["leaves"]), default=0)
    for k in range(n_int):
        for child, side in ((2 * k + 1, "no"), (2 * k + 2, "yes")):
            (x0, y0), (x1, y1) = pos[k], pos[child]
            ax.plot([x0, x1], [y0, y1], color="0.6", lw=1, zorder=1)
            ax.text(0.5 * (x0 + x1), 0.5 * (y0 + y1), side, fontsize=7, color="0.35",
                    ha="center", va="center", bbox=dict(fc="white", ec="none", pad=0.5), zorder=2)
    for nd in desc["nodes"]:
        x, y = pos[nd["id"]]
        ax.text(x, y, f"N{nd['id']}: {nd['predicate']}", fontsize=8.5,   # as `sage tree show` prints it
                ha="center", va="center", zorder=3,
                bbox=dict(boxstyle="round,pad=0.3", fc="#eef3fb", ec="#4a6fa5"))
    for lf in desc["leaves"]:
        x, y = pos[lf["id"]]
        shade = 0.0 if not max_visits else lf.get("visits", 0) / max_visits
        label = f"L{lf['leaf']}  {_cmd(lf['bias_command'])}"
        if "visits" in lf:
            label += f"  n={lf['visits']}"
        ax.text(x, y, label, fontsize=8, ha="left", va="center", zorder=3,
                bbox=dict(boxstyle="round,pad=0.3", fc=(1.0, 1.0 - 0.45 * shade, 0.75 - 0.45 * shade),
                          ec="#a07020"))
    ax.set_xlim(-0.7, depth + 1.2)
    ax.set_ylim(-n_leaves + 0.3, 0.7)
    ax.axis("off")
    ax.set_title(title or "hard oblique tree: node predicates w·o > b ('yes' branch), leaf [Δx, Δy, Δψ] at o = 0",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
