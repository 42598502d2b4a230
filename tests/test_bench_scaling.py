"""sage/bench/scaling.py: the capacity model behind docs/scaling.md, on
made-up measured inputs whose answers can be worked out by hand."""
import json

import pytest

from sage.bench.scaling import capacities, markdown, predict, table
from sage.cli import main


def inputs():
    system = {"config": {"envs_per_actor": 32, "chunk_len": 32},
              "actor_steps_per_s": {"shield_service": 4000.0, "local_qp": 5000.0},
              "shards": {"1": {"2": {"qps_per_busy_shard_s": {"0": 20000.0}}},
                         "2": {"4": {"qps_per_busy_shard_s": {"0": 25000.0, "1": 24000.0}}}},
              "router_msgs_per_s": {"small": {"msgs_per_s": 100000.0}, "shield_request": {"msgs_per_s": 5000.0}},
              "param_broadcast_ms": {"bytes": 30000}, "physics_bound_env_steps_per_s": 14000.0}
    learner = {"samples": 2048, "update_s": {"happo": 0.2, "sage": 0.5}, "update_cpu_s": {"happo": 0.1, "sage": 0.2}}
    return system, learner


def test_capacities_take_the_measured_figures():
    cap = capacities(*inputs())
    assert cap["shield_qps_per_core"] == 25000.0                 # the best-used shard
    assert cap["learner_samples_per_s"] == {"happo": 20480.0, "sage": 10240.0}   # thread CPU preferred
    assert cap["learner_time_source"] == "thread CPU"


def test_prediction_finds_the_first_bottleneck():
    cap = capacities(*inputs())
    small = predict(cap, 2, "sage")
    assert small["first_bottleneck"] == "actors" and small["env_steps_per_s"] == 8000.0
    big = predict(cap, 64, "sage")
    assert big["first_bottleneck"] == "learner (1)" and big["env_steps_per_s"] == 10240.0
    assert big["shield_shards_needed"] == 11            # 64 * 4000 / 25000 = 10.24 -> 11
    assert big["learners_needed"] == 25                 # 256000 / 10240
    # router load per actor: 2*4000/32 = 250 request-sized msgs/s of 5000, + small ones
    per_actor = 250 / 5000 + (2 * 4000 / 1024 + 2 + 2) / 100000
    assert big["routers_needed"] == pytest.approx(int(-(-64 * per_actor // 1)))
    assert len(table(cap)) == 6 and "| 512 | sage |" in markdown(table(cap))


def test_command_line_reads_files_and_rejects_bad_ones(tmp_path, capsys):
    system, learner = inputs()
    (tmp_path / "s.json").write_text(json.dumps(system))
    (tmp_path / "l.json").write_text(json.dumps(learner))
    assert main(["bench", "scaling", "--system", str(tmp_path / "s.json"), "--learner", str(tmp_path / "l.json"),
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["predicted"][0]["cores"] == 8
    (tmp_path / "bad.json").write_text(json.dumps({"config": {}}))
    with pytest.raises(SystemExit) as e:
        main(["bench", "scaling", "--system", str(tmp_path / "bad.json"), "--learner", str(tmp_path / "l.json")])
    assert e.value.code == 2
