"""Audit figures: decision traces (Fig. tree) and leaf-tuple occupancy (Fig. colortrace)."""
from __future__ import annotations

from collections import Counter

import numpy as np

from common.audit.config import AuditConfig
from common.audit.params import CarrierTree, feature_names, feature_units_of, split_carriers
from common.audit.recording import Recording
from common.audit.tree_view import _cmd, _num, format_predicate

ROUTE_COLORS = ("#1e9e4a", "#8e3fb0")  # green and purple routes, as in Fig. tree


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _route_of(tree: CarrierTree, leaf: int) -> list[int]:
    node, out = tree.n_internal + leaf, []
    while node > 0:
        out.append(node)
        node = (node - 1) // 2
    return [0] + out[::-1]


def representative_steps(rec: Recording, carrier: int, candidates: int = 6) -> list[int]:
    """Two decisions of one carrier: among its most visited leaves, the pair whose routes
    part earliest (ties: more visits); for each leaf the visit nearest its median progress."""
    leaves = rec.leaf[:, carrier].astype(np.int64)
    counts = Counter(leaves.tolist()).most_common(candidates)
    top = [l for l, _ in counts]
    visits = dict(counts)
    if len(top) == 1:
        pair = (top[0], top[0])
    else:
        depth = rec.nodes.shape[2]

        def score(a, b):
            # leaf index bits, most significant first, are the route's sides (0 = left)
            ra, rb = format(a, f"0{depth}b"), format(b, f"0{depth}b")
            shared = next((k for k in range(depth) if ra[k] != rb[k]), depth)
            return (shared, -(visits[a] + visits[b]))
        pair = min(((a, b) for i, a in enumerate(top) for b in top[i + 1:]), key=lambda p: score(*p))
    steps = []
    for k, l in enumerate(pair):
        idx = np.flatnonzero(leaves == l)
        if pair[0] == pair[1] and len(idx) > 1:  # one leaf only: two visits far apart in progress
            order = idx[np.argsort(rec.progress[idx])]
            idx = order[: len(order) // 2] if k == 0 else order[len(order) // 2:]
        med = np.median(rec.progress[idx])
        steps.append(int(idx[np.argmin(np.abs(rec.progress[idx] - med))]))
    return steps


def draw_trace(rec: Recording, path: str, carrier: int = 0, steps: list[int] | None = None,
               cfg: AuditConfig = AuditConfig()) -> list[int]:
    """Fig. tree: two complete root-to-leaf routes of one carrier's tree, siblings
    collapsed; each node's predicate and the value the carrier saw, each leaf's
    nominal command a_ST and what the exact CBF-QP (Eq. qpshield) executed instead."""
    if not rec.params:
        raise ValueError("the recording holds no policy params; cannot draw predicates")
    trees = split_carriers(rec.params)
    if not 0 <= carrier < len(trees):
        raise ValueError(f"carrier {carrier} out of range 0..{len(trees) - 1}")
    tree = trees[carrier]
    names = feature_names(tree.obs_dim, rec.meta.get("feature_names"))
    units = feature_units_of(names)
    steps = representative_steps(rec, carrier) if steps is None else list(steps)
    w = tree.unit_W()
    routes = []
    for s in steps:
        leaf = int(rec.leaf[s, carrier])
        route = _route_of(tree, leaf)
        if list(rec.nodes[s, carrier]) != route[:-1]:
            raise ValueError(f"step {s}: recorded route {list(rec.nodes[s, carrier])} does not end in leaf {leaf}")
        routes.append(route)
    on_route = {n for r in routes for n in r}
    collapsed = {2 * n + 1 + side for n in on_route if n < tree.n_internal for side in (0, 1)} - on_route

    # Layout: x = depth, displayed terminals (route leaves and collapsed stubs) get y slots in order.
    pos, slot = {}, [0]

    def place(n: int, depth: int) -> float:
        if n in collapsed or n >= tree.n_internal:
            y = -slot[0]
            slot[0] += 1 if n not in collapsed else 0.55
        else:
            y = 0.5 * (place(2 * n + 1, depth + 1) + place(2 * n + 2, depth + 1))
        pos[n] = (float(depth), y)
        return y

    place(0, 0)
    plt = _plt()
    height = max(4.5, 1.2 * slot[0] + 1.5)
    fig, ax = plt.subplots(figsize=(2.9 * (tree.depth + 1) + 2.0, height))
    for n in sorted(on_route):
        if n >= tree.n_internal:
            continue
        for child in (2 * n + 1, 2 * n + 2):
            (x0, y0), (x1, y1) = pos[n], pos[child]
            users = [k for k, r in enumerate(routes) if n in r and child in r]
            if users:
                for j, k in enumerate(users):
                    off = 0.06 * (j - 0.5 * (len(users) - 1))
                    ax.plot([x0, x1], [y0 + off, y1 + off], color=ROUTE_COLORS[k], lw=3, zorder=1)
            else:
                ax.plot([x0, x1], [y0, y1], color="0.75", lw=1, ls="--", zorder=1)
            ax.text(0.5 * (x0 + x1), 0.5 * (y0 + y1), "yes" if child == 2 * n + 2 else "no", fontsize=7,
                    color="0.3", ha="center", va="center", bbox=dict(fc="white", ec="none", pad=0.3), zorder=2)
    for n in collapsed:
        x, y = pos[n]
        n_leaves = 2 ** (tree.depth - int(np.floor(np.log2(n + 1))))
        label = f"L{n - tree.n_internal}" if n >= tree.n_internal else f"… {n_leaves} leaves"
        ax.text(x, y, label, fontsize=7, color="0.45", ha="center", va="center", zorder=3,
                bbox=dict(boxstyle="round,pad=0.2", fc="0.95", ec="0.75"))
    for n in sorted(on_route):
        x, y = pos[n]
        if n < tree.n_internal:
            lines = [f"N{n}: {format_predicate(w[n], tree.b[n], names, units, 2)}"]
            ax.text(x, y, lines[0], fontsize=8, ha="center", va="center", zorder=3,
                    bbox=dict(boxstyle="round,pad=0.3", fc="#eef3fb", ec="#4a6fa5"))
            for k, (r, s) in enumerate(zip(routes, steps)):
                if n in r:
                    val = float(w[n] @ rec.obs[s, carrier])
                    used = np.flatnonzero(np.abs(w[n]) >= 0.005)
                    if units is not None and len(used) == 1:   # a crisp split: the quantity itself
                        j = int(used[0])
                        scale, unit = units[names[j]]
                        seen = f"{names[j]} = {_num(float(rec.obs[s, carrier, j]) * scale)} {unit}".rstrip()
                    else:
                        seen = f"w·o = {_num(val)}"
                    ax.text(x, y - 0.32 - 0.22 * k, f"{seen} → {'yes' if val > tree.b[n] else 'no'}",
                            fontsize=7, color=ROUTE_COLORS[k], ha="center", va="center", zorder=3)
        else:
            for k, (r, s) in enumerate(zip(routes, steps)):
                if n != r[-1]:
                    continue
                a = rec.a_st[s, 3 * carrier:3 * carrier + 3]
                e = rec.a_exec[s, 3 * carrier:3 * carrier + 3]
                txt = f"L{n - tree.n_internal}: [Δx, Δy, Δψ] = {_cmd(a)}"
                # the exact QP's correction of this command (Eq. qpshield), shown even when nil
                n_active = int(np.sum(rec.active[s]))
                rows = f"{n_active} row{'' if n_active == 1 else 's'} active"
                if np.allclose(a, e, atol=5e-3):
                    txt += f"\nCBF-QP: executed as proposed ({rows})"
                else:
                    txt += f"\nCBF-QP executed {_cmd(e)}, correction ‖Δa‖ = {_num(float(np.linalg.norm(e - a)))} ({rows})"
                txt += f"\nepisode {int(rec.episode[s])}, t = {int(rec.t[s])}, progress {rec.progress[s]:.2f}"
                same_leaf = len(routes) > 1 and routes[0][-1] == routes[1][-1]
                ax.text(x - 0.05, y + (0.45 - 0.9 * k) * same_leaf, txt,
                        fontsize=8, ha="left", va="center", zorder=3,
                        bbox=dict(boxstyle="round,pad=0.35", fc="white", ec=ROUTE_COLORS[k], lw=2))
    ax.set_xlim(-0.9, tree.depth + 1.6)
    ax.set_ylim(-slot[0] - 0.3, 0.8)
    ax.axis("off")
    ax.set_title(f"Carrier {carrier}: two recorded decisions (predicates in the carrier's body frame; leaf "
                 "command is the nominal tree action, then the exact CBF-QP's correction)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=140)
    plt.close(fig)
    return steps


def tuple_labels(leaves: np.ndarray) -> list[tuple[int, ...]]:
    return [tuple(int(v) for v in row) for row in leaves]


def colortrace(rec: Recording, path: str, cfg: AuditConfig = AuditConfig(), episode: int | None = None,
               fig_bins: int = 20) -> dict:
    """Fig. colortrace: (a) occupancy of the most frequent joint tuples over route progress,
    all episodes; (b) one episode's payload path colored by tuple, others as 'other'."""
    tuples = tuple_labels(rec.leaf)
    top = [t for t, _ in Counter(tuples).most_common(cfg.top_tuples)]
    index = {t: k for k, t in enumerate(top)}
    cat = np.array([index.get(t, len(top)) for t in tuples])
    labels = [f"({', '.join(str(v) for v in t)})" for t in top] + ["other"]
    plt = _plt()
    cmap = plt.get_cmap("tab20")
    colors = [cmap(k % 20) for k in range(len(top))] + [(0.7, 0.7, 0.7, 1.0)]

    bins = np.clip(np.floor(np.clip(rec.progress, 0, 1) * fig_bins), 0, fig_bins - 1).astype(int)
    occ = np.zeros((len(labels), fig_bins))
    np.add.at(occ, (cat, bins), 1.0)
    totals = occ.sum(axis=0, keepdims=True)
    share = np.divide(occ, totals, out=np.zeros_like(occ), where=totals > 0)

    if episode is None:  # the episode that got furthest (ties: longest)
        eps = np.unique(rec.episode)
        best = [(rec.progress[rec.episode == e].max(), (rec.episode == e).sum(), -e) for e in eps]
        episode = int(-max(best)[2])
    sel = rec.episode == episode
    if not sel.any():
        raise ValueError(f"episode {episode} not in the recording")
    xy = rec.payload_pose[sel, :2]

    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(14, 5.5), gridspec_kw=dict(width_ratios=[1.15, 1]))
    centers = (np.arange(fig_bins) + 0.5) / fig_bins
    bottom = np.zeros(fig_bins)
    for k in range(len(labels)):  # one stacked bar per progress bin: no interpolation between bins
        ax_a.bar(centers, share[k], width=1.0 / fig_bins, bottom=bottom, color=colors[k], label=labels[k],
                 edgecolor="white", linewidth=0.3)
        bottom += share[k]
    ax_a.set_xlim(0, 1)
    ax_a.set_ylim(0, 1)
    ax_a.set_xlabel("route progress")
    ax_a.set_ylabel("share of steps")
    ax_a.set_title(f"(a) joint tuple (ℓ1, ℓ2, ℓ3) occupancy, {rec.n_episodes} episodes", fontsize=10)
    from matplotlib.patches import Rectangle
    from matplotlib.transforms import Affine2D

    walls = np.asarray(rec.meta.get("walls", []), np.float64)
    if walls.ndim == 3:   # one layout per episode (issue 29); a 2-D list is an older, shared one
        walls = walls[episode] if episode < len(walls) else walls[:0, 0]
    for cx, cy, hx, hy, yaw in walls.reshape(-1, 5):  # oriented boxes (cx, cy, hx, hy, yaw)
        ax_b.add_patch(Rectangle((-hx, -hy), 2 * hx, 2 * hy, color="0.55", zorder=0,
                                 transform=Affine2D().rotate(yaw).translate(cx, cy) + ax_b.transData))
    ax_b.plot(xy[:, 0], xy[:, 1], color="0.8", lw=1, zorder=1)
    ecat = cat[sel]
    for k in range(len(labels)):
        m = ecat == k
        if m.any():
            ax_b.scatter(xy[m, 0], xy[m, 1], s=12, color=colors[k], zorder=2)
    ax_b.scatter(*xy[0], marker="s", s=90, color="black", zorder=3, label="start")
    goals = rec.meta.get("goal_xy")
    goal = goals[episode] if goals and episode < len(goals) else xy[-1]
    ax_b.scatter(*goal, marker="*", s=220, color="red", zorder=3, label="goal" if goals else "end")
    ax_b.set_aspect("equal", adjustable="datalim")
    ax_b.set_xlabel("payload x [m]")
    ax_b.set_ylabel("payload y [m]")
    ax_b.set_title(f"(b) episode {episode} payload path colored by tuple", fontsize=10)
    ax_b.legend(loc="best", fontsize=8)
    handles, lbls = ax_a.get_legend_handles_labels()
    fig.legend(handles, lbls, loc="center right", fontsize=8, title="(ℓ1, ℓ2, ℓ3)", frameon=False)
    fig.tight_layout(rect=(0, 0, 0.88, 1))
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return {"episode": episode, "top_tuples": labels[:-1],
            "top_share": float(np.isin(cat, np.arange(len(top))).mean())}
