"""The five methods of Table I and what each one switches on; torch-free, so
actors, the CLI and the report read it without loading the learner.

| name        | executed action | proposal center            | actor update               |
|-------------|-----------------|----------------------------|----------------------------|
| happo       | a_prop          | a_ST (identity)            | HAPPO sequential           |
| happo_cbf   | QP(a_prop)      | a_ST (identity)            | HAPPO sequential           |
| talo_cbf    | QP(a_prop)      | a_ST (identity)            | TALO joint step            |
| sail_cbf    | QP(a_prop)      | Pi_kappa(x, a_ST) (SAIL)   | HAPPO sequential           |
| sage        | QP(a_prop)      | Pi_kappa(x, a_ST) (SAIL)   | TALO joint step            |
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MethodSpec:
    name: str
    title: str          # as Table I prints it
    shielded: bool      # executed actions pass the exact joint CBF-QP (Eq. qpshield)
    uses_sail: bool     # proposal center is the SAIL map Pi_kappa (Eq. sail_projection)
    uses_talo: bool     # joint TALO step (Eq. talo_projection) instead of HAPPO's sequential one


METHOD_SPECS: dict[str, MethodSpec] = {s.name: s for s in (
    MethodSpec("happo", "HAPPO", shielded=False, uses_sail=False, uses_talo=False),
    MethodSpec("happo_cbf", "HAPPO+CBF", shielded=True, uses_sail=False, uses_talo=False),
    MethodSpec("talo_cbf", "TALO+CBF", shielded=True, uses_sail=False, uses_talo=True),
    MethodSpec("sail_cbf", "SAIL+CBF", shielded=True, uses_sail=True, uses_talo=False),
    MethodSpec("sage", "SAGE+CBF", shielded=True, uses_sail=True, uses_talo=True),
)}
METHODS: tuple[str, ...] = tuple(METHOD_SPECS)


def method_spec(name: str) -> MethodSpec:
    try:
        return METHOD_SPECS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}") from None
