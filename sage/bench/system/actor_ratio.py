"""``ratio_vs_local_qp``: steps/s of one actor process with the shield
service in the loop over the same actor with a local in-process QP call
(``LocalQPActor``, synchronous: nothing to overlap a local call with) -- no
learner, parameters from the bench; both with the default settings
(synchronous, pruned rows: the local QP solves the same pruned rows).

``pipelining_gain``: the pipelined actor (``actor.pipeline``) over the
default synchronous one; ``row_pruning_gain``: pruned rows
(``actor.prune_rows``) over full rows, all with the shield service. Each
variant is measured ``actor_rounds`` times in turn (A B C D A B C D ...) and
its median is reported, so a slow spell of the machine does not land on one
variant. ``actor_loop_share`` splits each variant's wall time into blocked on
shield answers and the rollout thread's CPU. ``actor_core_us_per_env_step`` is
what an env step cost each variant in CPU (the actor process; ``host``: with
the router and, where asked, the shield process), and
``cpu_ratio_vs_local_qp`` the local QP's host cost over the shield service's:
the ratio the same cores would give if nothing waited, which time-sharing on a
loaded machine does not move (medians of the rounds)."""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from common import keys
from deploy.supervised_run import service_specs
from deploy.supervisor import ServiceSpec
from sage.bench.system.cpu import actor_step_cost, cpu_ratio, median_cost
from sage.bench.system.meter import StepMeter


def variants(path: Path, run: Path, cfg) -> dict[str, list[str]]:
    """The command line of each actor variant (the same run config, one setting changed)."""
    piped_path = replace(cfg, actor=replace(cfg.actor, pipeline=True)).save(run / "config-pipelined.json")
    full_path = replace(cfg, actor=replace(cfg.actor, prune_rows=False)).save(run / "config-full-rows.json")
    return {"local_qp": [sys.executable, "-m", "sage.bench.system", "local-actor",
                         "--config", str(path), "--actor-id", "0"],
            "shield_service": service_specs(path, roles=("actor",), actor_ids=[0])[0].argv,
            "shield_service_pipelined": service_specs(piped_path, roles=("actor",), actor_ids=[0])[0].argv,
            "shield_service_full_rows": service_specs(full_path, roles=("actor",), actor_ids=[0])[0].argv}


def one_actor(bench, cfg, path: Path, bus, learner) -> dict:
    """Each variant in turn, ``actor_rounds`` times, beside the running router and
    shield; ``learner`` publishes parameters (the actors wait for them)."""
    run = Path(cfg.run_dir)
    meter = StepMeter(cfg.run_id)
    bus.subscribe(keys.status_all(cfg.run_id), meter.on_status)
    feeder = bench.feed_params(learner)  # actors wait for parameters
    actor = variants(path, run, cfg)
    runs: dict[str, list] = {kind: [] for kind in actor}
    costs: dict[str, list] = {kind: [] for kind in actor}
    try:
        for r in range(bench.cfg.actor_rounds):
            for kind, argv in actor.items():
                bench.log(f"bench: one actor process ({bench.cfg.envs_per_actor} envs), "
                          f"{kind.replace('_', ' ')}, round {r + 1}/{bench.cfg.actor_rounds}")
                sub = bench.supervise([ServiceSpec("actor-0", argv)], run / f"{kind}-{r}")
                meter.reset()
                rate = meter.measure(1, bench.cfg.warmup_s, bench.cfg.measure_s,
                                     bench.cfg.start_timeout_s, bench.check, cpu=bench.cpu_probe)
                runs[kind].append((rate, {name: meter.window_rates.get(f"actor/0/{name}")
                                          for name in ("shield_wait_s", "loop_cpu_s")}))
                costs[kind].append(actor_step_cost(meter.window_cores, rate, kind != "local_qp"))
                bench.stop(sub)
    finally:
        feeder.stop()
    rates = {kind: float(np.median([rate for rate, _ in v])) for kind, v in runs.items()}
    # the loop shares of the round whose rate is the median (the lower middle one if even)
    loop = {kind: sorted(v, key=lambda x: x[0])[(len(v) - 1) // 2][1] for kind, v in runs.items()}
    return {"actor_steps_per_s": rates,
            "actor_steps_per_s_rounds": {kind: [rate for rate, _ in v] for kind, v in runs.items()},
            # per second of the actor's wall time: blocked on shield answers, and
            # its rollout thread's CPU time (1 - both: descheduled; the bench's actors never pace)
            "actor_loop_share": {kind: {"shield_wait": v["shield_wait_s"], "cpu": v["loop_cpu_s"]}
                                 for kind, v in loop.items()},
            "ratio_vs_local_qp": rates["shield_service"] / rates["local_qp"],
            # the same comparison in CPU: what an env step costs the host's cores (actor,
            # shield and router processes) with the shield service vs with the local QP;
            # medians of the rounds (time-sharing on a loaded machine does not enter it)
            "actor_core_us_per_env_step": {kind: median_cost(v) for kind, v in costs.items()},
            "cpu_ratio_vs_local_qp": cpu_ratio(costs["local_qp"], costs["shield_service"]),
            "pipelining_gain": rates["shield_service_pipelined"] / rates["shield_service"],
            "row_pruning_gain": rates["shield_service"] / rates["shield_service_full_rows"]}
