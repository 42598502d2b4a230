"""Top-down scenario figures (matplotlib): walls, reference route, goal, and the payload
poses of a scripted rollout (as the paper's nine-scenario figure), over the outlines of
further layouts drawn from the scenario's family (the spread; eval layout stream)."""
from __future__ import annotations

import numpy as np

from common.env.config import EnvConfig
from common.env.layout import CARRIER_RADIUS, GRASP_LOCAL, PAYLOAD_HALF
from common.env.scenarios import SCENARIOS, Route


def scripted_rollout(name: str, seed: int = 0, cfg: EnvConfig | None = None):
    """One scripted episode (env 0's first layout of the eval stream): list of (payload_xy,
    payload_yaw, carrier_xy [3,2]) per step, its record, and its layout."""
    from common.env.batch_env import BatchEnv

    env = BatchEnv(cfg or EnvConfig(name), num_envs=1, seed=seed, layout_purpose="eval")
    env.reset()
    layout = env.scene.layouts[0]
    poses = [(env.snap.pxy[0].copy(), float(env.snap.pyaw[0]), env.snap.cxy[0].copy())]
    while True:
        out = env.step(env.scripted_actions())
        if out["episodes"]:
            return poses, out["episodes"][0], layout
        poses.append((env.snap.pxy[0].copy(), float(env.snap.pyaw[0]), env.snap.cxy[0].copy()))


def drawn_layouts(name: str, n: int, seed: int = 0, cfg: EnvConfig | None = None):
    """The first-episode layouts of envs 0..n-1 (eval stream), as ``BatchEnv`` draws them."""
    from common.env.batch_env import BatchEnv

    env = BatchEnv(cfg or EnvConfig(name), num_envs=n, seed=seed, layout_purpose="eval")
    return [env.draw_layout(k, 0) for k in range(n)]


def _corners(walls):
    c, s = np.cos(walls[:, 4:5]), np.sin(walls[:, 4:5])
    pts = []
    for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        lx, ly = sx * walls[:, 2:3], sy * walls[:, 3:4]
        pts.append(np.concatenate([walls[:, 0:1] + c * lx - s * ly, walls[:, 1:2] + s * lx + c * ly], axis=1))
    return np.concatenate(pts)


def _box(ax, cx, cy, hx, hy, yaw, **kw):
    from matplotlib.patches import Polygon

    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    pts = corners @ np.array([[c, s], [-s, c]]) + [cx, cy]
    ax.add_patch(Polygon(pts, closed=True, **kw))


def draw_scenario(ax, name: str, seed: int = 0, every: int = 12, layouts: int = 6):
    """The scripted rollout in the first of ``layouts`` drawn layouts (solid walls), over the wall
    outlines of the others (the family's spread); returns the rollout's record."""
    from matplotlib.patches import Circle

    spec = SCENARIOS[name]
    poses, rec, layout = scripted_rollout(name, seed)
    others = drawn_layouts(name, layouts, seed)[1:] if layouts > 1 else []
    for j, lay in enumerate(others):
        for k, w in enumerate(lay.walls):
            _box(ax, *w, facecolor="none", edgecolor="tab:red", lw=0.5, alpha=0.45,
                 label="walls of other drawn layouts" if j == 0 and k == 0 else None)
    for j, w in enumerate(layout.walls):
        _box(ax, *w, facecolor="0.35", edgecolor="0.2", lw=0.5, alpha=0.85, label="wall" if j == 0 else None)
    for lay in others:
        ax.plot(lay.route[:, 0], lay.route[:, 1], ":", color="tab:green", lw=0.5, alpha=0.6)
    route = Route(layout.route)
    ax.plot(route.points[:, 0], route.points[:, 1], "--", color="tab:green", lw=1.0, label="reference route")
    sel = list(range(0, len(poses), every)) + [len(poses) - 1]
    cmap = __import__("matplotlib").colormaps["viridis"]
    for j, t in enumerate(sel):
        pxy, yaw, cxy = poses[t]
        col = cmap(j / max(len(sel) - 1, 1))
        first = j == 0
        _box(ax, pxy[0], pxy[1], PAYLOAD_HALF[0], PAYLOAD_HALF[1], yaw, facecolor=col, alpha=0.35, edgecolor=col,
             label=f"payload every {every} steps (dark → light)" if first else None)
        for i in range(len(GRASP_LOCAL)):
            ax.add_patch(Circle(cxy[i], CARRIER_RADIUS, facecolor="none", edgecolor=col, lw=0.6,
                                label="carriers" if first and i == 0 else None))
    track = np.array([p[0] for p in poses])
    ax.plot(track[:, 0], track[:, 1], color="tab:orange", lw=1.0, label="payload centre")
    corners = _corners(np.concatenate([layout.walls] + [lay.walls for lay in others]))
    lo, hi = corners.min(axis=0) - 0.1, corners.max(axis=0) + 0.1
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    spread = f", {1 + len(others)} layouts" if others else ""
    ax.set_title(f"{spec.title} ({spec.family}{spread})" + ("" if rec["success"] else " [scripted run failed]"),
                 fontsize=9)
    ax.set_xlabel("x (m)", fontsize=7)
    ax.set_ylabel("y (m)", fontsize=7)
    ax.tick_params(labelsize=6)
    return rec


def render(out: str, names: list[str], seed: int = 0, layouts: int = 6):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(names)
    cols = 3 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    records = {}
    for ax, name in zip(axes.flat, names):
        records[name] = draw_scenario(ax, name, seed, layouts=layouts)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    # one legend for the figure (every panel draws the same kinds of things)
    fig.legend(*axes.flat[0].get_legend_handles_labels(), loc="upper center", ncol=3 if n > 1 else 2,
               fontsize=7 if n > 1 else 6)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / (3.4 * rows)))
    fig.savefig(out, dpi=130)
    plt.close(fig)
    return records
