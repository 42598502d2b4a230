import sys, threading, time
sys.path.insert(0, "tests")
import numpy as np
from common import keys, wire
from common.transport import Bus
from services.config import TrainConfig
from services.shield.service import ShieldService
cfg = TrainConfig(run_id="p", run_dir="/tmp/sage_probe_run", actors=2, envs_per_actor=32).validate()
bus = Bus.open(inprocess=True); stop = threading.Event()
sh = ShieldService(cfg, bus, stop=stop); threading.Thread(target=sh.run, daemon=True).start()
while sh.state != "running": time.sleep(0.05)
rng = np.random.default_rng(0)
def req(B, M, sender, seq):
    return wire.encode("shield_req", {"a_prop": rng.uniform(-1, 1, (B, 9)), "C": rng.normal(size=(B, M, 9)), "c": rng.normal(size=(B, M)),
        "row_mask": np.ones((B, M), bool), "fixed_mask": np.zeros((B, 9), bool)}, run_id="p", sender=sender, seq=seq)
atk = req(2, 4000, "actor/0", 0)
t0 = time.perf_counter(); errs = []
for i in range(20):
    r = bus.request(keys.shield("p"), atk, timeout=10.0); errs.append(r.err[:8] if r and r.err else r)
t_atk = time.perf_counter() - t0
good = req(32, 34, "actor/1", 0)
t0 = time.perf_counter(); r = bus.request(keys.shield("p"), good, timeout=10.0); t_good = time.perf_counter() - t0
print(f"attack B=2 M=4000 ({len(atk)/1e3:.0f} kB) x20: replies {set(errs)}, {t_atk/20*1e3:.1f} ms each; rejected limit={sh.rejected['limit']}; "
      f"then an actor-sized query (B=32, M=34) answered ok={r is not None and r.ok is not None} in {t_good*1e3:.1f} ms")
stop.set(); bus.close()
