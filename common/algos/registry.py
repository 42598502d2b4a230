"""The methods of Table I, plus the ablation arm, and what each one switches on;
torch-free, so actors, the CLI and the report read it without loading the learner.

| name        | executed action | proposal center            | actor update                         |
|-------------|-----------------|----------------------------|--------------------------------------|
| happo       | a_prop          | a_ST (identity)            | HAPPO sequential                     |
| happo_cbf   | QP(a_prop)      | a_ST (identity)            | HAPPO sequential                     |
| talo_cbf    | QP(a_prop)      | a_ST (identity)            | joint step along g_TALO              |
| sail_cbf    | QP(a_prop)      | Pi_kappa(x, a_ST) (SAIL)   | HAPPO sequential                     |
| sage        | QP(a_prop)      | Pi_kappa(x, a_ST) (SAIL)   | joint step along g_TALO              |
| joint_cbf   | QP(a_prop)      | a_ST (identity)            | joint step along g_ind (no TALO)     |

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


@dataclass(frozen=True)
class MethodSpec:
    name: str
    title: str          # as Table I prints it
    shielded: bool      # executed actions pass the exact joint CBF-QP (Eq. qpshield)
    uses_sail: bool     # proposal center is the SAIL map Pi_kappa (Eq. sail_projection)
    uses_talo: bool     # the joint step goes along g_TALO (Eq. talo_projection)
    joint_step: bool    # joint base scheme (all carriers in one step) instead of HAPPO's sequential one

    def __post_init__(self) -> None:
        if self.uses_talo and not self.joint_step:
            raise ValueError(f"{self.name}: TALO is a joint step (uses_talo needs joint_step)")


METHOD_SPECS: dict[str, MethodSpec] = {s.name: s for s in (
    MethodSpec("happo", "HAPPO", shielded=False, uses_sail=False, uses_talo=False, joint_step=False),
    MethodSpec("happo_cbf", "HAPPO+CBF", shielded=True, uses_sail=False, uses_talo=False, joint_step=False),
    MethodSpec("talo_cbf", "TALO+CBF", shielded=True, uses_sail=False, uses_talo=True, joint_step=True),
    MethodSpec("sail_cbf", "SAIL+CBF", shielded=True, uses_sail=True, uses_talo=False, joint_step=False),
    MethodSpec("sage", "SAGE+CBF", shielded=True, uses_sail=True, uses_talo=True, joint_step=True),
    # ablation: TALO+CBF's base scheme without the correction
    MethodSpec("joint_cbf", "Joint+CBF", shielded=True, uses_sail=False, uses_talo=False, joint_step=True),
)}
METHODS: tuple[str, ...] = ("happo", "happo_cbf", "talo_cbf", "sail_cbf", "sage")   # Table I
ABLATION_METHODS: tuple[str, ...] = ("joint_cbf",)
ALL_METHODS: tuple[str, ...] = METHODS + ABLATION_METHODS


def method_spec(name: str) -> MethodSpec:
    try:
        return METHOD_SPECS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(ALL_METHODS)}") from None
