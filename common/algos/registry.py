"""The methods of Table I, plus the ablation arm, and what each one switches on;
torch-free, so actors, the CLI and the report read it without loading the learner.

| name        | executed action | proposal center            | actor update (``step``)                  |
|-------------|-----------------|----------------------------|------------------------------------------|
| happo       | a_prop          | a_ST (identity)            | sequential: HAPPO                        |
| happo_cbf   | QP(a_prop)      | a_ST (identity)            | sequential: HAPPO                        |
| talo_cbf    | QP(a_prop)      | a_ST (identity)            | joint: along g_TALO                      |
| sail_cbf    | QP(a_prop)      | Pi_kappa(x, a_ST) (SAIL)   | sequential: HAPPO                        |
| sage        | QP(a_prop)      | Pi_kappa(x, a_ST) (SAIL)   | joint: along g_TALO                      |
| joint_cbf   | QP(a_prop)      | a_ST (identity)            | joint: along g_ind (no TALO)             |

``step`` names the update step the learner runs: ``"sequential"``
(common/algos/sequential.py, HAPPO's per-carrier steps) or ``"joint"``
(common/algos/joint.py, all carriers in one step).

``joint_cbf`` (ablation, not in Table I) is TALO+CBF without the Lyapunov
projection: the same joint base scheme (all carriers stepped together, same
optimizer / ``AlgoConfig.talo_step``, same clipping), with ``g = g_ind``. Comparing
happo_cbf -> joint_cbf -> talo_cbf separates the change of base scheme
(sequential -> joint) from the TALO correction itself.

``METHODS`` is the paper's five (Table I order; the suite's default set and the
report's rows); ``ALL_METHODS`` adds the ablation arms. ``method_spec`` knows all.
"""
from __future__ import annotations

from dataclasses import dataclass

UPDATE_STEPS: tuple[str, ...] = ("sequential", "joint")


@dataclass(frozen=True)
class MethodSpec:
    name: str
    title: str          # as Table I prints it
    shielded: bool      # executed actions pass the exact joint CBF-QP (Eq. qpshield)
    uses_sail: bool     # proposal center is the SAIL map Pi_kappa (Eq. sail_projection)
    uses_talo: bool     # the joint step goes along g_TALO (Eq. talo_projection)
    step: str           # the update step: "sequential" (HAPPO, per carrier) or "joint" (all carriers at once)

    def __post_init__(self) -> None:
        if self.step not in UPDATE_STEPS:
            raise ValueError(f"{self.name}: step must be one of {UPDATE_STEPS}, got {self.step!r}")
        if self.uses_talo and not self.joint_step:
            raise ValueError(f"{self.name}: TALO is a joint step (uses_talo needs step='joint')")

    @property
    def joint_step(self) -> bool:
        return self.step == "joint"


METHOD_SPECS: dict[str, MethodSpec] = {s.name: s for s in (
    MethodSpec("happo", "HAPPO", shielded=False, uses_sail=False, uses_talo=False, step="sequential"),
    MethodSpec("happo_cbf", "HAPPO+CBF", shielded=True, uses_sail=False, uses_talo=False, step="sequential"),
    MethodSpec("talo_cbf", "TALO+CBF", shielded=True, uses_sail=False, uses_talo=True, step="joint"),
    MethodSpec("sail_cbf", "SAIL+CBF", shielded=True, uses_sail=True, uses_talo=False, step="sequential"),
    MethodSpec("sage", "SAGE+CBF", shielded=True, uses_sail=True, uses_talo=True, step="joint"),
    # ablation: TALO+CBF's base scheme without the correction
    MethodSpec("joint_cbf", "Joint+CBF", shielded=True, uses_sail=False, uses_talo=False, step="joint"),
)}
METHODS: tuple[str, ...] = ("happo", "happo_cbf", "talo_cbf", "sail_cbf", "sage")   # Table I
ABLATION_METHODS: tuple[str, ...] = ("joint_cbf",)
ALL_METHODS: tuple[str, ...] = METHODS + ABLATION_METHODS


def method_spec(name: str) -> MethodSpec:
    try:
        return METHOD_SPECS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(ALL_METHODS)}") from None
