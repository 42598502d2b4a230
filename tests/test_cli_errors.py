"""Bad input to every `sage` command exits 2 with one line naming the bad value, never a traceback.

``sage.cli.main`` raises ``SystemExit(2)`` for it (as argparse does), or a
handler returns 2 after printing its line.

argparse's own errors (a number out of range, an unknown choice) print the
usage and one `error:` line; every other bad input (a value the config
dataclasses reject, a missing, truncated or corrupt file) prints exactly one
line, ``sage <command>: ...``. Nothing here trains: one tiny run (1 update)
provides a real run directory and checkpoint, and the training, supervisor,
suite and system-bench entry points are replaced by a failing stub.
"""
import json
import os
import shutil

import numpy as np
import pytest

import sage.bench.system.cli
import sage.suite
import sage.train
from sage.cli import main


@pytest.fixture(scope="module")
def files(tmp_path_factory, tiny_run):
    """Bad inputs, made once: truncated, corrupt and foreign files next to good ones."""
    import torch

    from common.audit.recording import record_episodes
    from common.audit.synthetic import random_team_params
    from common.env.config import EnvConfig
    from common.env.observations import OBS_DIM
    from services.config import TrainConfig

    d = tmp_path_factory.mktemp("bad")
    rng = np.random.default_rng(0)
    good = json.loads(TrainConfig(run_id="t", run_dir=str(d / "unused")).resolve().to_json())
    (d / "trunc.json").write_text('{"scenario": "narr')
    (d / "bad_scenario.json").write_text(json.dumps({**good, "scenario": "bogus"}))
    (d / "wrong_type.json").write_text(json.dumps({**good, "actors": "x"}))
    (d / "unknown_key.json").write_text(json.dumps({**good, "no_such_key": 1}))
    (d / "list.json").write_text("[1, 2]")
    (d / "corrupt.pt").write_bytes(rng.bytes(300))
    (d / "empty.pt").write_bytes(b"")
    ckpt = max((tiny_run / "checkpoints").glob("ckpt_*.pt"))
    (d / "half.pt").write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    torch.save({"a": torch.zeros(2)}, d / "foreign.pt")
    # run directories: truncated config.json (good checkpoints), no checkpoints, only corrupt ones
    shutil.copytree(tiny_run, d / "rd_trunc")
    (d / "rd_trunc" / "config.json").write_text((tiny_run / "config.json").read_text()[:40])
    (d / "rd_nockpt").mkdir()
    shutil.copy(tiny_run / "config.json", d / "rd_nockpt" / "config.json")
    (d / "rd_badckpt" / "checkpoints").mkdir(parents=True)
    shutil.copy(tiny_run / "config.json", d / "rd_badckpt" / "config.json")
    (d / "rd_badckpt" / "checkpoints" / "ckpt_00000001.pt").write_bytes(rng.bytes(500))
    for name, text in (("rd_listcfg", b"[1]"), ("rd_bincfg", rng.bytes(64))):
        (d / name).mkdir()
        (d / name / "config.json").write_bytes(text)
    (d / "empty_dir").mkdir()
    (d / "a_file").write_text("not a directory\n")
    # numpy: random bytes, an .npz that is not a recording, a truncated real recording
    (d / "corrupt.npz").write_bytes(rng.bytes(300))
    np.savez(d / "notrec.npz", x=np.zeros(3))
    rec = record_episodes(random_team_params(obs_dim=OBS_DIM, depth=2, seed=3),
                          EnvConfig(scenario="chicane", max_steps=5), episodes=1, seed=1)
    rec.save(d / "rec.npz")
    (d / "rec_half.npz").write_bytes((d / "rec.npz").read_bytes()[:500])
    (d / "params_wrong.json").write_text(json.dumps({"carrier_0/W": [[1.0, 0.0]]}))
    (d / "result_missing.json").write_text(json.dumps({"method": "sage"}))
    (d / "result_list.json").write_text("[]")
    return d


# (argv, kind, what the message must name). kind "argparse": argparse's own
# `error:` line; kind "usage": exactly one line `sage <command>: ...`.
# {T} = the folder of bad files, {RUN} = a real run directory.
BAD = [
    # sage train
    ("train --scenario bogus", "argparse", "bogus"),
    ("train --method bogus", "argparse", "bogus"),
    ("train --actors 0", "argparse", "--actors"),
    ("train --envs-per-actor -1", "argparse", "--envs-per-actor"),
    ("train --updates 0", "argparse", "--updates"),
    ("train --updates abc", "argparse", "--updates"),
    ("train --chunk-len 0", "argparse", "--chunk-len"),
    ("train --minutes -1", "argparse", "--minutes"),
    ("train --minutes 0", "argparse", "--minutes"),
    ("train --minutes nan", "argparse", "--minutes"),
    ("train --max-lag -1", "argparse", "--max-lag"),
    ("train --eval-episodes -1", "argparse", "--eval-episodes"),
    ("train --seed -3", "argparse", "--seed"),
    ("train --metrics-port 70000", "argparse", "--metrics-port"),
    ("train --human-slot 5", "argparse", "--human-slot"),
    ("train --set train.updates=abc --run-dir {T}/r", "usage", "train.updates=abc"),
    ("train --set algo.actor_lr=x --run-dir {T}/r", "usage", "algo.actor_lr=x"),
    ("train --set algo.epochs=1.5 --run-dir {T}/r", "usage", "algo.epochs=1.5"),
    ("train --set env.max_steps=-5 --run-dir {T}/r", "usage", "max_steps"),
    ("train --set env.grasp_solref=[1] --run-dir {T}/r", "usage", "env.grasp_solref"),
    ("train --set env.scenario=maze --run-dir {T}/r", "usage", "env.scenario"),
    ("train --set shield.no_such_field=1 --run-dir {T}/r", "usage", "shield.no_such_field"),
    ("train --set novalue --run-dir {T}/r", "usage", "novalue"),
    ("train --set train.checkpoint_every=0 --run-dir {T}/r", "usage", "checkpoint_every"),
    ("train --set train.minutes=-1 --run-dir {T}/r", "usage", "minutes"),
    ("train --set train.resume=3 --run-dir {T}/r", "usage", "train.resume=3"),
    ("train --set ports.learner=70000 --run-dir {T}/r", "usage", "ports.learner"),
    ("train --set actor.max_chunks_ahead=0 --run-dir {T}/r", "usage", "max_chunks_ahead"),
    ("train --run-id bad/id --run-dir {T}/r", "usage", "bad/id"),
    ("train --config {T}/missing.json", "usage", "missing.json"),
    ("train --config {T}/trunc.json", "usage", "trunc.json"),
    ("train --config {T}/bad_scenario.json", "usage", "bogus"),
    ("train --config {T}/wrong_type.json", "usage", "actors"),
    ("train --config {T}/unknown_key.json", "usage", "no_such_key"),
    ("train --config {T}/list.json", "usage", "list.json"),
    ("train --run-dir {T}/a_file", "usage", "a_file"),
    ("train --run-dir {T}/rd_trunc", "usage", "unreadable config.json"),
    ("train --run-dir {T}/rd_listcfg", "usage", "unreadable config.json"),
    ("train --run-dir {T}/rd_bincfg", "usage", "unreadable config.json"),
    # sage up
    ("up --roles bogus --run-dir {T}/up", "usage", "bogus"),
    ("up --roles , --run-dir {T}/up", "usage", "--roles"),
    ("up --actors 0", "argparse", "--actors"),
    ("up --scenario bogus", "argparse", "bogus"),
    ("up --minutes -1", "argparse", "--minutes"),
    ("up --metrics-base -1", "argparse", "--metrics-base"),
    ("up --actor-ids x --run-dir {T}/up", "usage", "'x'"),
    ("up --actors 2 --actor-ids 5 --run-dir {T}/up", "usage", "--actor-ids 5"),
    ("up --config {T}/missing.json", "usage", "missing.json"),
    ("up --config {T}/trunc.json", "usage", "trunc.json"),
    # sage eval
    ("eval {T}/missing", "usage", "missing"),
    ("eval {T}/corrupt.pt", "usage", "corrupt.pt"),
    ("eval {T}/empty.pt", "usage", "empty.pt"),
    ("eval {T}/half.pt", "usage", "half.pt"),
    ("eval {T}/foreign.pt", "usage", "foreign.pt"),
    ("eval {T}/trunc.json", "usage", "trunc.json"),
    ("eval {T}/rd_trunc", "usage", "config.json"),
    ("eval {T}/rd_nockpt", "usage", "no loadable checkpoint"),
    ("eval {T}/rd_badckpt", "usage", "no loadable checkpoint"),
    ("eval {T}/empty_dir", "usage", "empty_dir"),
    ("eval {RUN} --episodes 0", "argparse", "--episodes"),
    ("eval {RUN} --scenario bogus", "argparse", "bogus"),
    ("eval {RUN} --human-slot 7", "argparse", "--human-slot"),
    ("eval {RUN} --record {T}/rec.txt", "usage", "rec.txt"),
    # sage suite (nothing runs: the plan and the --set items are checked first)
    ("suite --methods bogus --out {T}/s", "usage", "bogus"),
    ("suite --scenarios bogus --out {T}/s", "usage", "bogus"),
    ("suite --seeds a,b --out {T}/s", "usage", "'a'"),
    ("suite --seeds -1 --out {T}/s", "usage", "-1"),
    ("suite --minutes-per-run -1", "argparse", "--minutes-per-run"),
    ("suite --updates-per-run 0", "argparse", "--updates-per-run"),
    ("suite --workers 0", "argparse", "--workers"),
    ("suite --set train.updates=abc --out {T}/s", "usage", "train.updates=abc"),
    ("suite --set env.nope=1 --out {T}/s", "usage", "env.nope"),
    ("suite --out {T}/a_file", "usage", "a_file"),
    # sage report
    ("report {T}/missing.json", "usage", "missing.json"),
    ("report {T}/trunc.json", "usage", "trunc.json"),
    ("report {T}/corrupt.pt", "usage", "corrupt.pt"),
    ("report {T}/result_missing.json", "usage", "result_missing.json"),
    ("report {T}/result_list.json", "usage", "result_list.json"),
    ("report {T}/empty_dir", "usage", "empty_dir"),
    # sage env render
    ("env render --scenario bogus", "argparse", "bogus"),
    ("env render --seed -1", "argparse", "--seed"),
    ("env render --out {T}/x.xyz", "usage", "x.xyz"),
    ("env render --out {T}/empty_dir", "usage", "empty_dir"),
    ("env render --out {T}/a_file/x.png", "usage", "a_file"),
    ("env render --layouts 0", "argparse", "--layouts"),
    # sage env calibrate
    ("env calibrate --episodes 0", "argparse", "--episodes"),
    ("env calibrate --layout-spread 3", "argparse", "--layout-spread"),
    ("env calibrate --aim-offset nan", "argparse", "--aim-offset"),
    ("env calibrate --scenario bogus", "argparse", "bogus"),
    # sage tree
    ("tree show {T}/missing.pt", "usage", "missing.pt"),
    ("tree show {T}/corrupt.pt", "usage", "corrupt.pt"),
    ("tree show {T}/half.pt", "usage", "half.pt"),
    ("tree show {T}/foreign.pt", "usage", "foreign.pt"),
    ("tree show {T}/trunc.json", "usage", "trunc.json"),
    ("tree show {T}/params_wrong.json", "usage", "params_wrong.json"),
    ("tree show {T}/corrupt.npz", "usage", "corrupt.npz"),
    ("tree show {T}/empty_dir", "usage", "empty_dir"),
    ("tree show {T}/rd_badckpt", "usage", "ckpt_00000001.pt"),
    ("tree show {RUN} --carrier 9", "usage", "--carrier 9"),
    ("tree show {RUN} --carrier -1", "argparse", "--carrier"),
    ("tree show {RUN} --top-terms 0", "argparse", "--top-terms"),
    ("tree show {RUN} --format bogus", "argparse", "bogus"),
    ("tree show {RUN} --eval-log {T}/missing.npz", "usage", "missing.npz"),
    ("tree show {RUN} --eval-log {T}/corrupt.npz", "usage", "corrupt.npz"),
    ("tree show {RUN} --eval-log {T}/notrec.npz", "usage", "notrec.npz"),
    ("tree bogus {RUN}", "argparse", "bogus"),
    # sage trace
    ("trace {T}/missing.npz", "usage", "missing.npz"),
    ("trace {T}/corrupt.npz", "usage", "corrupt.npz"),
    ("trace {T}/notrec.npz", "usage", "notrec.npz"),
    ("trace {T}/rec_half.npz", "usage", "rec_half.npz"),
    ("trace {T}/rec.npz --steps a,b", "usage", "--steps"),
    ("trace {T}/rec.npz --steps 0,99999", "usage", "--steps"),
    ("trace {T}/rec.npz --carrier 7 --out {T}/t.png", "usage", "--carrier 7"),
    ("trace {T}/rec.npz --out {T}/t.xyz", "usage", "t.xyz"),
    # sage audit
    ("audit {T}/missing.npz", "usage", "missing.npz"),
    ("audit {T}/corrupt.npz", "usage", "corrupt.npz"),
    ("audit {T}/rec.npz --bins 1", "usage", "progress_bins"),
    ("audit {T}/rec.npz --shuffles 1", "usage", "shuffles"),
    ("audit {T}/rec.npz --top-tuples 0", "argparse", "--top-tuples"),
    ("audit {T}/rec.npz --episode 9 --out {T}/audit", "usage", "--episode 9"),
    ("audit {T}/rec.npz --out {T}/a_file", "usage", "a_file"),
    # sage export-bundle
    ("export-bundle {T}/corrupt.pt {T}/bundle", "usage", "corrupt.pt"),
    ("export-bundle {T}/missing.pt {T}/bundle", "usage", "missing.pt"),
    ("export-bundle {RUN} {T}/a_file", "usage", "a_file"),
    # sage bench
    ("bench qp --batch 0", "argparse", "--batch"),
    ("bench qp --rows -1", "argparse", "--rows"),
    ("bench env --num-envs 0", "argparse", "--num-envs"),
    ("bench env --scenario bogus", "argparse", "bogus"),
    ("bench scripted --episodes 0", "argparse", "--episodes"),
    ("bench learner --T 0", "argparse", "--T"),
    ("bench learner --threads 0", "argparse", "--threads"),
    ("bench system --actors a", "usage", "'a'"),
    ("bench system --batch-sizes 0", "usage", "--batch-sizes"),
    ("bench system --scenario bogus", "argparse", "bogus"),
    ("bench system --seconds 0", "argparse", "--seconds"),
    ("bench system --work-dir {T}/a_file", "usage", "a_file"),
    ("bench bogus", "argparse", "bogus"),
]


@pytest.fixture
def nothing_runs(monkeypatch, tmp_path):
    """A bad invocation must fail before any work: these would train, supervise or benchmark."""
    def refuse(*args, **kwargs):
        raise AssertionError("a bad invocation reached the work it should have been refused before")

    monkeypatch.setattr(sage.train, "run_inprocess", refuse)
    monkeypatch.setattr(sage.train, "run_supervised", refuse)
    monkeypatch.setattr(sage.suite, "run_suite", refuse)
    monkeypatch.setattr(sage.bench.system.cli, "SystemBench", refuse)
    monkeypatch.chdir(tmp_path)   # nothing lands in the repository either
    monkeypatch.delenv("SAGE_TRACEBACK", raising=False)


@pytest.mark.parametrize("command, kind, names", BAD, ids=[c for c, _, _ in BAD])
def test_bad_invocation_exits_2_with_one_line(command, kind, names, files, tiny_run, nothing_runs, capsys):
    argv = [a.replace("{T}", str(files)).replace("{RUN}", str(tiny_run)) for a in command.split()]
    try:
        code = main(argv)   # a handler may also return 2 after its one line
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    captured = capsys.readouterr()
    err = captured.err
    assert "Traceback" not in err and "Traceback" not in captured.out
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines, "no message on stderr"
    if kind == "argparse":
        assert lines[0].startswith("usage: sage") and "error:" in lines[-1], err
    else:
        assert len(lines) == 1, err
        words = ["sage", *command.split()[:2]]
        prefix = " ".join(words[:3] if words[1] in ("bench", "env", "tree") else words[:2])
        assert lines[0].startswith(prefix + ": "), lines[0]
    assert names in lines[-1], lines[-1]


def test_enough_bad_invocations_over_every_command():
    assert len(BAD) >= 30
    commands = {c.split()[0] if c.split()[0] not in ("bench", "env", "tree") else " ".join(c.split()[:2])
                for c, _, _ in BAD}
    for name in ("train", "up", "eval", "suite", "report", "env render", "env calibrate", "tree show", "trace", "audit",
                 "export-bundle", "bench qp", "bench env", "bench scripted", "bench learner", "bench system"):
        assert name in commands, name


def test_an_unexpected_error_keeps_its_traceback(monkeypatch, tmp_path):
    """Only input errors become one line: a bug past the input checks still raises."""
    def boom(*args, **kwargs):
        raise ValueError("a bug in training")

    monkeypatch.setattr(sage.train, "run_inprocess", boom)
    with pytest.raises(ValueError, match="a bug in training"):
        main(["train", "--updates", "1", "--envs-per-actor", "2", "--chunk-len", "8", "--eval-episodes", "0",
              "--run-dir", str(tmp_path / "r"), "--quiet"])


def test_sage_traceback_shows_the_cause(monkeypatch, files):
    from sage.errors import UsageError

    monkeypatch.setenv("SAGE_TRACEBACK", "1")
    with pytest.raises(UsageError, match="corrupt.pt") as raised:
        main(["eval", str(files / "corrupt.pt")])
    assert raised.value.__cause__ is not None


def test_set_values_take_the_field_type():
    from sage.train import apply_override
    from services.config import TrainConfig

    cfg = TrainConfig()
    apply_override(cfg, "train.run_id=123")          # a string field keeps the text
    apply_override(cfg, "shield.window_s=1")         # an int is fine for a float field
    apply_override(cfg, "env.max_steps=null")        # int | None
    apply_override(cfg, "env.grasp_solref=[0.05, 1]")
    assert cfg.run_id == "123" and cfg.shield.window_s == 1.0 and isinstance(cfg.shield.window_s, float)
    assert cfg.env.max_steps is None and cfg.env.grasp_solref == (0.05, 1.0)
    for item in ("train.updates=abc", "train.updates=1.5", "train.resume=1", "algo.actor_lr=x",
                 "env.human_slot=x", "env.grasp_solref=3", "transport.connect=5"):
        with pytest.raises(SystemExit, match=r"must be (an integer|true or false|a number|a list)"):
            apply_override(cfg, item)


def test_validate_rejects_bad_config_values():
    from services.config import TrainConfig

    for bad in ({"scenario": "bogus"}, {"minutes": -1.0}, {"minutes": 0}, {"eval_episodes": -1},
                {"checkpoint_every": 0}, {"seed": -1}, {"actors": "2"}, {"resume": 1}, {"updates": True},
                {"status_period_s": 0}):
        with pytest.raises(ValueError):
            TrainConfig(run_id="t", **bad).validate()
    from services.config import UNLIMITED_UPDATES

    TrainConfig(run_id="t", minutes=2, updates=UNLIMITED_UPDATES).validate()   # a wall-clock budget alone
    for bad in ({"updates": 0}, {"minutes": float("nan")}, {"minutes": float("inf")}, {"envs_per_actor": 10**9},
                {"chunk_len": 10**9}, {"envs_per_actor": 4096, "chunk_len": 4096}):
        with pytest.raises(ValueError):
            TrainConfig(run_id="t", **bad).validate()


def test_python_dash_m_sage_prints_one_line(files):
    """The real entry point: exit status 2 and one line on stderr."""
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, "-m", "sage", "tree", "show", str(files / "corrupt.pt")],
                          check=False, capture_output=True, text=True, cwd=root, timeout=120)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("sage tree show: ") and "corrupt.pt" in lines[0], proc.stderr
