"""MuJoCo three-carrier cooperative transport (docs/interfaces.md, common/env).

Names are resolved lazily so that importing a submodule (e.g. common.env.safety)
does not pull in MuJoCo.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "SCENARIOS": "common.env.scenarios", "FAMILIES": "common.env.scenarios",
    "SCENARIO_TITLES": "common.env.scenarios", "EnvConfig": "common.env.config",
    "OBS_FEATURE_NAMES": "common.env.observations", "BatchEnv": "common.env.batch_env",
    "TransportParallelEnv": "common.env.parallel_env", "aggregate": "common.env.metrics",
}
__all__ = list(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'common.env' has no attribute {name!r}")
