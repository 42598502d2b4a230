import sys
sys.path.insert(0, "tests")
import numpy as np
from test_shield_prune import _env_rows
from common.shield.prune import drop_box_redundant_rows
from common.shield.qp import shield_actions
from common.shield.verify import verify_answer
from collections import Counter
for scen, hs in (("narrow_gate", None), ("maze", 1), ("narrow_gate", 0)):
    real, forged = Counter(), Counter(); steps = 0
    for a, rows in _env_rows(scen, K=16, steps=80, human_slot=hs):
        steps += 1
        res = shield_actions(a, drop_box_redundant_rows(a, rows))
        real[verify_answer(a, rows, res.a_exec, res.status.astype(np.int32))] += 1
        zeros = np.where(np.broadcast_to(rows.fixed_mask, a.shape), a, 0.0)
        forged[verify_answer(a, rows, zeros, np.zeros(len(a), np.int32))] += 1
    print(f"{scen} human_slot={hs}: {steps} steps x 16 envs; real answers {dict(real)}; 'all zeros, optimal' forgeries {dict(forged)}")
