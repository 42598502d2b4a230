"""`sage bench learner`: thread CPU time (and wall time) of one learner update
per method on the same synthetic batch, as ratios to HAPPO (same run, same
machine). Thread CPU time is the figure of merit: on a loaded machine wall time
also counts the time the learner waited for a core. ``--profile`` adds where one
update's time goes, by kind (``update_profile``)."""
from __future__ import annotations

import copy
import cProfile
import json
import pstats
import statistics
import time

import numpy as np
import torch
from torch import Tensor

from common.algos.config import AlgoConfig
from common.algos.methods import make_method
from common.algos.synthetic import BanditTask, collect
from common.env.observations import OBS_DIM
from sage.bench.machine import machine
from sage.errors import nonneg_int, positive_int

BENCH_METHODS = ("happo", "sail_cbf", "talo_cbf", "sage")
TARGET_RATIO = 2.0   # sage's update vs happo's, thread CPU (issue 14)


def default_obs_dim() -> tuple[int, str]:
    """The environment's observation size (and where it came from)."""
    return OBS_DIM, "env"


def bench_learner(T: int = 64, K: int = 32, obs_dim: int | None = None, rows: int = 34,
                  repeats: int = 3, methods=BENCH_METHODS, threads: int = 1, seed: int = 0,
                  progress: float = 0.5, profile: bool = False) -> dict:
    """Median thread CPU and wall seconds per ``update`` (after one warm-up
    update) for each method, their ratios to happo and samples per second. Every update
    (the warm-up and each timed one) starts from the method's state that collected the
    batch. ``profile``: one more update per method under cProfile, untimed, its time
    split by kind (``update_profile``)."""
    if T < 1 or K < 1 or repeats < 1 or rows < 1:
        raise ValueError("bench learner: T, K, rows and repeats must be >= 1")
    if "happo" not in methods:
        raise ValueError("bench learner: ratios are relative to happo; include it")
    source = "argument"
    if obs_dim is None:
        obs_dim, source = default_obs_dim()
    torch.set_num_threads(threads)
    cfg = AlgoConfig(seed=seed)
    task = BanditTask(obs_dim=obs_dim, seed=seed, n_rows=rows, human_rate=0.05)
    learners = {}
    for name in methods:
        method = make_method(name, cfg, obs_dim, obs_dim * 3)
        # same contexts for every method (same rng seed); proposals are each method's own
        batch = collect(method, task, T, K, progress, np.random.default_rng(seed))
        # every update starts from the state that collected the batch, as each of training's
        # does: the same work every repeat, none on a batch its policy has drifted from
        start = copy.deepcopy(method.state_dict())
        method.update(batch, progress)                      # warm-up
        learners[name] = method, batch, start
    times: dict[str, list[float]] = {name: [] for name in methods}
    cpu: dict[str, list[float]] = {name: [] for name in methods}   # thread CPU: robust under load
    last_diag: dict[str, dict] = {}
    for _ in range(repeats):
        # round robin, so that a change in the machine's load hits every method alike
        for name, (method, batch, start) in learners.items():
            method.load_state_dict(start)
            t0, c0 = time.perf_counter(), time.thread_time()
            last_diag[name] = method.update(batch, progress)
            times[name].append(time.perf_counter() - t0)
            cpu[name].append(time.thread_time() - c0)
    update_s = {k: statistics.median(v) for k, v in times.items()}
    minibatches = min(cfg.minibatches, T * K)
    steps = cfg.epochs * minibatches                        # critic steps per update
    critic_step = critic_step_ab(learners["happo"][0], T * K // minibatches)
    update_cpu_s = {k: statistics.median(v) for k, v in cpu.items()}
    out = {
        "bench": "learner",
        "T": T, "K": K, "samples": T * K, "obs_dim": obs_dim, "obs_dim_source": source,
        "rows": rows, "epochs": cfg.epochs, "minibatches": cfg.minibatches,
        "repeats": repeats, "torch_threads": threads,
        "update_s": update_s,
        "update_s_all": times,
        "ratio_vs_happo": {k: v / update_s["happo"] for k, v in update_s.items()},
        "update_cpu_s": update_cpu_s,
        "cpu_ratio_vs_happo": {k: v / update_cpu_s["happo"] for k, v in update_cpu_s.items()},
        "samples_per_cpu_s": {k: T * K / v for k, v in update_cpu_s.items()},
        "cpu_us_per_sample": {k: 1e6 * v / (T * K) for k, v in update_cpu_s.items()},
        "samples_per_s": {k: T * K / v for k, v in update_s.items()},
        "target": f"sage update <= {TARGET_RATIO:g}x happo update (thread CPU)",
        "sage_within_target": (update_cpu_s["sage"] / update_cpu_s["happo"] <= TARGET_RATIO)
        if "sage" in update_cpu_s else None,
        "w_gap": {k: d.get("w_gap") for k, d in last_diag.items()},
        "critic_step": critic_step,
        # the paper critic's arithmetic in an update: its steps' matrix products alone
        "critic_gemm_floor_us_per_sample": critic_step["gemms_us"] * steps / (T * K),
        "machine": machine(),
    }
    if profile:
        out["profile"] = {name: profiled_update(method, batch, start, progress)
                          for name, (method, batch, start) in learners.items()}
    return out


def profiled_update(method, batch, start, progress: float) -> dict:
    """One update of ``method`` from ``start`` (its state when it collected ``batch``) under
    cProfile: ``update_profile`` of it."""
    method.load_state_dict(start)
    profiler = cProfile.Profile()
    profiler.runcall(method.update, batch, progress)
    return update_profile(pstats.Stats(profiler).stats, batch["reward"].size)


# where an update's time goes, by kind: (kind, source file or None for C functions, names or None for all)
PROFILE_KINDS = (
    ("tree kernels", "common/policy/tree_grad_kernels.py", None),
    ("SAIL kernels", "common/policy/sail_kernels.py", None),
    ("chain kernels", "common/algos/surrogate_kernels.py", None),
    ("QP solver", "common/shield/qp_solver.py", None),
    ("matrix products", None, ("mm", "addmm", "bmm", "matmul")),
    ("critic tanh", "common/algos/critic.py", ("_tanh_",)),
    ("critic tanh", None, ("tanh_backward",)),
    ("gather", None, ("index_select",)),
)


def _c_function_name(label: str) -> str:
    """``<method 'mm' of 'torch._C.TensorBase' objects>`` -> ``mm``;
    ``<built-in method torch.addmm>`` -> ``addmm``."""
    if label.startswith("<method '"):
        return label.split("'")[1]
    return label.rstrip(">").split(" ")[-1].rsplit(".", 1)[-1]


def profile_kind(file: str, name: str) -> str:
    """The kind of a cProfile entry (its ``file`` and function ``name``): one of
    ``PROFILE_KINDS``'s, else "other torch and numpy calls" for a C function (cProfile's
    file "~") and "Python" for the rest."""
    c_function = file == "~"
    short = _c_function_name(name) if c_function else name
    for kind, source, names in PROFILE_KINDS:
        if (source is None) == c_function and (source is None or file.replace("\\", "/").endswith(source)) \
                and (names is None or short in names):
            return kind
    return "other torch and numpy calls" if c_function else "Python"


def update_profile(stats: dict, samples: int) -> dict:
    """One profiled update's own time (``pstats.Stats.stats``: (file, line, name) ->
    (primitive calls, calls, own time, cumulative, callers)) split by ``profile_kind``:
    microseconds per sample, each kind's share, and how many torch functions it called.
    cProfile charges its own overhead per call, which weighs most on the Python rows."""
    own: dict[str, float] = {}
    torch_calls = 0
    for (file, _line, name), (_cc, calls, tottime, _ct, _callers) in stats.items():
        kind = profile_kind(file, name)
        own[kind] = own.get(kind, 0.0) + tottime
        if file == "~" and "torch" in name:
            torch_calls += calls
    total = sum(own.values())
    return {"us_per_sample": 1e6 * total / samples,
            "share": {k: v / total for k, v in sorted(own.items(), key=lambda kv: -kv[1])} if total else {},
            "torch_calls": torch_calls}


def critic_step_ab(method, minibatch: int, blocks: int = 20, steps: int = 10) -> dict:
    """The learner's critic step (written-out gradient) against the autograd reference
    step (``TeamCritic.forward``, ``backward``), each with the same clip and Adam, and
    against the step's matrix products alone (``critic_gemms``: its arithmetic at this
    machine's GEMM rate), on one random minibatch of ``minibatch`` samples: thread CPU per
    step in rotating blocks of ``steps``, and the medians of the per-round ratios (what a
    change in the machine's speed moves least). Runs on a copy of the critic; ``method`` is
    untouched."""
    from common.algos.adam import Adam
    from common.algos.critic import value_step

    cfg = method.cfg
    critic = copy.deepcopy(method.critic)
    opt = Adam(critic.parameters(), lr=cfg.critic_lr, eps=1e-5)
    B = max(1, int(minibatch))
    gen = torch.Generator().manual_seed(cfg.seed)
    obs = torch.randn(B, method.n_agents, method.obs_dim, generator=gen)
    state = torch.randn(B, critic.state_dim, generator=gen) if critic.state_dim else None
    target = torch.randn(B, generator=gen)

    def step(by_autograd: bool):
        return lambda: value_step(critic, opt, obs, state, target, cfg.vf_coef, cfg.max_grad_norm, by_autograd)

    steps_of = {"autograd": step(True), "written": step(False), "gemms": critic_gemms(critic, obs, state)}
    cpu: dict[str, list[float]] = {name: [] for name in steps_of}
    for f in steps_of.values():
        f()                                                   # warm-up
    names = list(steps_of)
    for b in range(blocks):
        for name in names[b % 3:] + names[:b % 3]:
            c0 = time.thread_time()
            for _ in range(steps):
                steps_of[name]()
            cpu[name].append((time.thread_time() - c0) / steps)

    def ratio(num: str, den: str):
        r = [n / d for n, d in zip(cpu[num], cpu[den]) if d > 0]
        return statistics.median(r) if r else None

    return {"minibatch": B, "blocks": blocks,
            "autograd_us": 1e6 * statistics.median(cpu["autograd"]),
            "written_us": 1e6 * statistics.median(cpu["written"]),
            "gemms_us": 1e6 * statistics.median(cpu["gemms"]),
            "written_over_autograd": ratio("written", "autograd"),
            "written_over_gemms": ratio("written", "gemms")}


def critic_gemms(critic, obs: Tensor, state: Tensor | None):
    """A function running the matrix products of one written-out critic step
    (``TeamCritic.value_loss_and_grads``: five forward ``addmm``, nine backward ``mm``) at its
    shapes, on activations and cotangents fixed once: no tanh, no loss, no optimizer. Its
    time is the step's floor at this machine's GEMM rate."""
    with torch.no_grad():
        layers = critic._layers()
        x0, a1, a2, inp, h1, h2, _ = critic._forward_parts(obs, state, layers)
    (w1, b1), (w2, b2), (u1, c1), (u2, c2), (u3, c3) = layers
    B, N = obs.shape[0], critic.n_agents
    z0, latent = N * critic.obs_dim, w2.shape[0]
    g_v = torch.ones(B, 1)
    g_a2 = torch.ones(B * N, latent)

    def gemms():
        torch.addmm(b1, x0, w1.t()), torch.addmm(b2, a1, w2.t())
        torch.addmm(c1, inp, u1.t()), torch.addmm(c2, h1, u2.t()), torch.addmm(c3, h2, u3.t())
        g = g_v.mm(u3)
        g_v.t().mm(h2), g.t().mm(h1)
        g = g.mm(u2)
        g.t().mm(inp), g.mm(u1[:, z0:z0 + latent])
        g_a2.t().mm(a1)
        g = g_a2.mm(w2)
        g.t().mm(x0)

    return gemms


# ----------------------------------------------------------------- command line
def register(commands, bench) -> None:
    p = bench.add_parser(
        "learner", help="thread CPU (and wall) seconds per learner update for happo, sail_cbf, talo_cbf, "
                        "sage (ratios to happo)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--T", type=positive_int, default=64, help="rollout length per env")
    p.add_argument("--K", type=positive_int, default=32, help="envs per batch")
    p.add_argument("--obs-dim", type=positive_int, default=None, help="default: the env's obs_dim (else 40)")
    p.add_argument("--rows", type=positive_int, default=34, help="safety rows M")
    p.add_argument("--repeats", type=positive_int, default=3, help="timed updates per method (median)")
    p.add_argument("--threads", type=positive_int, default=1, help="torch intra-op threads")
    p.add_argument("--seed", type=nonneg_int, default=0)
    p.add_argument("--profile", action="store_true",
                   help="also one update per method under cProfile, its time split by kind")
    p.set_defaults(func=_bench_handler)


def _bench_handler(args) -> int:
    out = bench_learner(T=args.T, K=args.K, obs_dim=args.obs_dim, rows=args.rows,
                        repeats=args.repeats, threads=args.threads, seed=args.seed, profile=args.profile)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"learner update, {out['samples']} samples ({out['T']}x{out['K']}), obs_dim {out['obs_dim']}, "
              f"{out['epochs']} epochs x {out['minibatches']} minibatches")
        for name, cpu in out["update_cpu_s"].items():
            print(f"  {name:10s} thread CPU {cpu:7.3f} s ({out['cpu_ratio_vs_happo'][name]:5.2f}x happo), "
                  f"{out['samples_per_cpu_s'][name]:7.0f} samples/CPU-s "
                  f"({out['cpu_us_per_sample'][name]:5.0f} us/sample)   wall {out['update_s'][name]:7.3f} s "
                  f"({out['ratio_vs_happo'][name]:5.2f}x)")
        print(f"  target: {out['target']}: {'met' if out['sage_within_target'] else 'not met'}")
        cs = out["critic_step"]
        print(f"  critic step ({cs['minibatch']} samples): written-out {cs['written_us']:.0f} us, "
              f"autograd {cs['autograd_us']:.0f} us, ratio {cs['written_over_autograd']:.2f}; its matrix products "
              f"alone {cs['gemms_us']:.0f} us (written-out / them {cs['written_over_gemms']:.2f}; medians of "
              f"{cs['blocks']} blocks): the update's critic floor {out['critic_gemm_floor_us_per_sample']:.1f} us/sample")
        for name, prof in out.get("profile", {}).items():
            shares = ", ".join(f"{k} {100 * v:.0f}%" for k, v in prof["share"].items())
            print(f"  profiled {name}: {prof['us_per_sample']:.0f} us/sample under cProfile, {prof['torch_calls']} "
                  f"torch calls; {shares}")
        m = out["machine"]
        print(f"  machine: {m['cpu_model']}, {m['cpus_available']} CPUs, torch {m['torch_cpu_capability']}")
    return 0
