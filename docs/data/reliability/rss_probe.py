"""RSS of a router and a shield process before/after two 60 MiB messages.
usage: PYTHONPATH=<tree> python rss_probe.py <tree> <router_limit_bytes or 0>"""
import json, os, socket, subprocess, sys, time
from pathlib import Path
import numpy as np
tree, limit = sys.argv[1], int(sys.argv[2])
svc_limit = int(sys.argv[3]) if len(sys.argv) > 3 else 0
sys.path.insert(0, tree)
from common import keys, wire
from common.transport import Bus

def port():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p

def rss(pid):
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024

P = port(); run = Path("/tmp/sage_rss_run_" + str(os.getpid())); run.mkdir(parents=True, exist_ok=True)
env = dict(os.environ, PYTHONPATH=tree)
r_argv = [sys.executable, "-m", "deploy.router", "--listen", f"tcp/127.0.0.1:{P}"] + (["--max-message-bytes", str(limit)] if limit else [])
router = subprocess.Popen(r_argv, cwd=tree, env=env, stderr=subprocess.DEVNULL)
cfg = {"run_id": "rss", "run_dir": str(run), "transport": {"mode": "client", "connect": [f"tcp/127.0.0.1:{P}"], **({"max_message_bytes": svc_limit} if svc_limit else {})}}
(run / "cfg.json").write_text(json.dumps(cfg))
shield = subprocess.Popen([sys.executable, "-m", "services.shield", "--config", str(run / "cfg.json")], cwd=tree, env=env,
                          stderr=open(run / "shield.log", "w"))
time.sleep(2)
bus = Bus.open(connect=[f"tcp/127.0.0.1:{P}"], mode="client")
small = wire.encode("shield_req", {"a_prop": np.zeros((1, 9)), "C": np.zeros((1, 1, 9)), "c": np.zeros((1, 1)),
                                   "row_mask": np.ones((1, 1), bool), "fixed_mask": np.zeros((1, 9), bool)}, run_id="rss", sender="a", seq=0)
for _ in range(300):
    r = bus.request(keys.shield("rss"), small, timeout=1.0)
    if r is not None and r.ok is not None:
        break
    time.sleep(0.2)
time.sleep(3)
before = (rss(router.pid), rss(shield.pid))
M = (60 * 2**20) // (9 * 8)
big = wire.encode("shield_req", {"a_prop": np.zeros((1, 9)), "C": np.zeros((1, M, 9)), "c": np.zeros((1, 5)),
                                 "row_mask": np.ones((1, 5), bool), "fixed_mask": np.zeros((1, 9), bool)}, run_id="rss", sender="a", seq=1)
replies = []
for i in range(2):
    rep = bus.request(keys.shield("rss"), big, timeout=20.0)
    replies.append(None if rep is None else (rep.err or b"ok")[:60].decode(errors="replace"))
    peak = (rss(router.pid), rss(shield.pid))
time.sleep(7)   # a status tick or two: the shield may hand memory back
after = (rss(router.pid), rss(shield.pid))
ok = bus.request(keys.shield("rss"), small, timeout=5.0)
print(json.dumps({"message_MiB": round(len(big) / 2**20, 1), "router_limit": limit, "replies": replies,
                  "router_MB": [round(before[0]), round(after[0])], "shield_MB": [round(before[1]), round(after[1])],
                  "shield_still_answers": ok is not None and ok.ok is not None}))
bus.close()
for p in (shield, router):
    p.terminate()
    p.wait(10)
