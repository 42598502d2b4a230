"""``shards[k][n]``: ``k`` shield shard processes serving ``n`` unpaced actor
processes (no learner; the bench feeds parameters): the actors' steps/s, the
QPs/s each shard served and its busy share (QPs/s at 100% busy: a shard
core's capacity at the actors' batch)."""
from __future__ import annotations

from pathlib import Path

from common import keys
from common.transport import Bus
from deploy.supervised_run import router_spec, service_specs
from deploy.supervisor import free_tcp_port
from sage.bench.system.meter import StepMeter


def shards_phase(bench) -> dict:
    out: dict[str, dict] = {}
    for k in sorted(set(bench.cfg.shard_counts)):
        for n in sorted(set(bench.cfg.shard_actor_counts)):
            if k > n:
                continue
            port = free_tcp_port()
            connect = [f"tcp/127.0.0.1:{port}"]
            cfg, path = bench.train_config(n, connect, f"shard{k}", unpaced=True, shields=k)
            bench.log(f"bench: {k} shield shard(s), {n} actor process(es)")
            bench.supervise([router_spec(port), *service_specs(path, roles=("shield", "actor"),
                                                               actor_ids=range(n), shields=k)],
                            Path(cfg.run_dir))
            bus = Bus.open(connect=connect, mode="client")
            feeder = None
            try:
                meter = StepMeter(cfg.run_id)
                bus.subscribe(keys.status_all(cfg.run_id), meter.on_status)
                feeder = bench.feed_params(bench.params_publisher(cfg, bus))
                steps = meter.measure(n, bench.cfg.warmup_s, bench.cfg.measure_s, bench.cfg.start_timeout_s,
                                      bench.check)
                rates = meter.window_rates
                qps = {key.split("/")[1]: v for key, v in rates.items() if key.endswith("/rows")}
                busy = {key.split("/")[1]: v for key, v in rates.items() if key.endswith("/busy_s")}
            finally:
                if feeder is not None:
                    feeder.stop()
                bus.close()
                bench.stop_all()
            out.setdefault(str(k), {})[str(n)] = {
                "actor_env_steps_per_s": steps, "qps_served": sum(qps.values()), "qps_per_shard": qps,
                # seconds busy per second; QPs/s at 100% busy = a shard core's capacity at this batch
                "shield_busy_share": busy,
                "qps_per_busy_shard_s": {s_: qps[s_] / busy[s_] for s_ in qps if busy.get(s_)}}
    return out
