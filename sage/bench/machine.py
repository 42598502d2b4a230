"""What a bench ran on: the CPU, the vector instructions numpy and torch dispatch to, the
CPUs this process may use and the versions of what does the arithmetic.

Figures in microseconds move with the hardware, not only with the code: the same commit
measured 2.2x apart on two hosts of this workplace (docs/scaling.md, "2026-12-08"), and
numpy's float32 tanh 17x apart. Every bench's JSON carries this block so that two figures
are compared only where it matches."""
from __future__ import annotations

import os
import platform

import numpy as np

# numpy's dispatch targets worth naming (its __cpu_features__ keys; x86, then Arm)
_SIMD_FEATURES = ("AVX512F", "AVX2", "FMA3", "SSE42", "ASIMD")


def cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``), else what ``platform`` says."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def host_cpus() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def numpy_simd() -> dict[str, bool]:
    """Which of the named vector extensions numpy found on this CPU at run time."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:   # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as features
    return {name: bool(features.get(name, False)) for name in _SIMD_FEATURES if name in features}


def machine() -> dict:
    """The block every bench's JSON carries (module docstring)."""
    import mujoco
    import torch

    return {
        "cpu_model": cpu_model(),
        "arch": platform.machine(),
        "cpus_available": host_cpus(),
        "numpy_simd": numpy_simd(),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "versions": {"python": platform.python_version(), "numpy": np.__version__, "torch": torch.__version__,
                     "mujoco": mujoco.__version__},
    }
