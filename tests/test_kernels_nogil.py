"""Every compiled kernel called from Python releases the interpreter lock: in
the in-process placement the actor's env step, its tree and SAIL forwards and
the shield's QP run beside the learner's thread instead of holding the GIL.
(Inlined helpers are compiled into their callers and have no lock of their own.)"""
import numba
import pytest

from common.env import kernels as env_kernels
from common.policy import proposal_kernels, sail_kernels, tree_kernels
from common.shield import qp_solver
from common.shield import row_kernels


@pytest.mark.parametrize("module", [env_kernels, qp_solver, row_kernels, proposal_kernels, sail_kernels, tree_kernels],
                         ids=lambda m: m.__name__)
def test_callable_kernels_are_nogil(module):
    kernels = {name: f for name, f in vars(module).items()
               if isinstance(f, numba.core.registry.CPUDispatcher) and f.__module__ == module.__name__}
    entry = {name: f for name, f in kernels.items() if f.targetoptions.get("inline") != "always"}
    assert entry, f"no kernels found in {module.__name__}"
    held = sorted(name for name, f in entry.items() if not f.targetoptions.get("nogil"))
    assert not held, f"{module.__name__}: kernels that hold the GIL: {held}"
