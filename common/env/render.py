"""Top-down scenario figures (matplotlib): walls, reference route, goal, and the payload
poses of a scripted rollout (as the paper's nine-scenario figure)."""
from __future__ import annotations

import numpy as np

from common.env.config import EnvConfig
from common.env.layout import CARRIER_RADIUS, GRASP_LOCAL, PAYLOAD_HALF
from common.env.scenarios import SCENARIOS, Route


def scripted_rollout(name: str, seed: int = 0, cfg: EnvConfig | None = None):
    """One scripted episode: list of (payload_xy, payload_yaw, carrier_xy [3,2]) per step, and its record."""
    from common.env.batch_env import BatchEnv

    env = BatchEnv(cfg or EnvConfig(name), num_envs=1, seed=seed)
    env.reset()
    poses = [(env.snap.pxy[0].copy(), float(env.snap.pyaw[0]), env.snap.cxy[0].copy())]
    while True:
        out = env.step(env.scripted_actions())
        if out["episodes"]:
            return poses, out["episodes"][0]
        poses.append((env.snap.pxy[0].copy(), float(env.snap.pyaw[0]), env.snap.cxy[0].copy()))


def _box(ax, cx, cy, hx, hy, yaw, **kw):
    from matplotlib.patches import Polygon

    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    pts = corners @ np.array([[c, s], [-s, c]]) + [cx, cy]
    ax.add_patch(Polygon(pts, closed=True, **kw))


def draw_scenario(ax, name: str, seed: int = 0, every: int = 12):
    from matplotlib.patches import Circle

    spec = SCENARIOS[name]
    for j, w in enumerate(spec.walls):
        _box(ax, *w, facecolor="0.35", edgecolor="0.2", lw=0.5, label="wall" if j == 0 else None)
    route = Route(spec.route)
    ax.plot(route.points[:, 0], route.points[:, 1], "--", color="tab:green", lw=1.0, label="reference route")
    poses, rec = scripted_rollout(name, seed)
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
    ax.set_xlim(spec.bounds[0], spec.bounds[1])
    ax.set_ylim(spec.bounds[2], spec.bounds[3])
    ax.set_aspect("equal")
    ax.set_title(f"{spec.title} ({spec.family})" + ("" if rec["success"] else " [scripted run failed]"), fontsize=9)
    ax.set_xlabel("x (m)", fontsize=7); ax.set_ylabel("y (m)", fontsize=7)
    ax.tick_params(labelsize=6)
    return rec


def render(out: str, names: list[str], seed: int = 0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(names)
    cols = 3 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    records = {}
    for ax, name in zip(axes.flat, names):
        records[name] = draw_scenario(ax, name, seed)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    # one legend for the figure (every panel draws the same kinds of things)
    fig.legend(*axes.flat[0].get_legend_handles_labels(), loc="upper center", ncol=3 if n > 1 else 2,
               fontsize=7 if n > 1 else 6)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / (3.4 * rows)))
    fig.savefig(out, dpi=130)
    plt.close(fig)
    return records
