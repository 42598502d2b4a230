import sys, time, numpy as np
sys.path.insert(0, "tests")
from test_shield_prune import _env_rows
from common.shield.prune import drop_box_redundant_rows
from common.shield.qp import shield_actions
from common.shield import verify
for scen, hs in (("narrow_gate", None), ("maze", 1)):
    probs = []
    for a, rows in _env_rows(scen, K=16, steps=60, human_slot=hs):
        res = shield_actions(a, drop_box_redundant_rows(a, rows))
        probs.append((a, rows, res.a_exec, res.status.astype(np.int32)))
    for a, rows, x, s in probs[:2]:
        verify.verify_answer(a, rows, x, s)
    def run(f):
        t = time.thread_time()
        for _ in range(5):
            for a, rows, x, s in probs:
                f(a, rows, x, s)
        return (time.thread_time() - t) / (5 * len(probs)) * 1e6
    full = run(lambda a, r, x, s: verify.verify_answer(a, r, x, s))
    kkt = run(lambda a, r, x, s: verify._check_optimality(a, r, x, s, 1e-6))
    print(f"{scen} human={hs} K=16 M={probs[0][1].n_rows}: verify_answer {full:.1f} us/step thread CPU, of which KKT {kkt:.1f} us")
