"""The actor's shield query carries only the rows the action box does not
satisfy everywhere (actor.prune_rows); the answer is still checked against all
of the step's rows, and executed only if it meets them."""
from dataclasses import replace

import numpy as np

from common import wire
from common.safety_rows import SafetyRows
from common.shield.qp import solve_cbf_qp
from common.spec import JOINT_ACT_DIM
from common.transport import Bus
from services.actor.service import ActorService
from services.config import TrainConfig


class SpyBus:
    """Records what the actor asks; answers nothing."""

    def __init__(self):
        self.payloads = []

    def replies(self, key, payload, timeout):
        self.payloads.append(payload)
        return iter(())


def _rows(rng, B=6, M=12):
    C = rng.normal(size=(B, M, JOINT_ACT_DIM))
    c = rng.normal(size=(B, M))
    c[:, ::2] = -20.0            # far from binding anywhere in the box: droppable
    mask = np.ones((B, M), bool)
    mask[:, 1] = False
    return SafetyRows(C, c, mask, np.zeros((B, JOINT_ACT_DIM), bool))


def _asked(prune: bool):
    cfg = TrainConfig(run_id="r", method="sage")
    cfg = replace(cfg, actor=replace(cfg.actor, prune_rows=prune))
    actor = ActorService(cfg, Bus.open(inprocess=True), 0)
    actor.bus = SpyBus()
    rng = np.random.default_rng(3)
    rows = _rows(rng)
    a_prop = rng.uniform(-1, 1, size=(rows.batch, JOINT_ACT_DIM))
    actor.ask_shield(a_prop, rows)
    return a_prop, rows, wire.decode(actor.bus.payloads[0], run_id="r", expect="shield_req").body


def test_query_carries_the_needed_rows_only_and_the_same_qp():
    a_prop, rows, body = _asked(prune=True)
    full = _asked(prune=False)[2]
    assert full["C"].shape == rows.C.shape
    assert body["C"].shape[1] < rows.C.shape[1] and (body["c"][body["row_mask"]] > -20.0).all()
    sent = solve_cbf_qp(a_prop, body["C"], body["c"], body["row_mask"], body["fixed_mask"])
    ref = solve_cbf_qp(a_prop, rows.C, rows.c, rows.row_mask, rows.fixed_mask)
    np.testing.assert_allclose(sent.a_exec, ref.a_exec, atol=1e-9)
    assert (sent.status == ref.status).all()
