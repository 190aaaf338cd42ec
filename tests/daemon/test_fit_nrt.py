"""The fit compiles without numba's reference counting (``kernel_fit.fit_one_t`` and
``fit_many`` with ``_nrt=False``, inherited by their callees): safe only while no
kernel of the fit returns an array. numba refuses to compile a returned view without
counting, but not a returned argument, and it keys a compiled signature without its
flags, so a callee compiled without counting and returning an array would be handed
to a counting caller that takes a reference it was never given (freed early)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

#: A fresh interpreter compiles (or loads) only the fit's kernels, then lists every
#: signature of the package whose return type holds an array.
_SCAN = """
import json, sys
from numba.core import types
from numba.core.registry import CPUDispatcher
from retargetd.daemon.body.solve_fit import warm_up_solver
warm_up_solver()
def holds_array(t):
    if isinstance(t, types.Array):
        return True
    return isinstance(t, types.BaseTuple) and any(holds_array(x) for x in t.types)
found = set()
for name, mod in list(sys.modules.items()):
    if name.startswith("retargetd"):
        for attr, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher):
                for cres in obj.overloads.values():
                    if holds_array(cres.signature.return_type):
                        found.add(name + "." + attr)
print(json.dumps(sorted(found)))
"""

#: The construction's views, returned by its kernels to ``_seed_from_construction``,
#: which compiles with counting (``_nrt=True``).
CONSTRUCTION_VIEWS = {
    "retargetd.daemon.body.kernel.plan_views",
    "retargetd.daemon.body.kernel.state_views",
    "retargetd.daemon.body.kernel.out_views",
}


@pytest.mark.timeout(600)
def test_no_fit_kernel_returns_an_array() -> None:
    done = subprocess.run(
        [sys.executable, "-c", _SCAN], capture_output=True, text=True, timeout=580
    )
    assert done.returncode == 0, done.stderr[-4000:]
    found = set(json.loads(done.stdout.strip().splitlines()[-1]))
    # the scan sees a returned array (the construction's, counted) ...
    assert found >= CONSTRUCTION_VIEWS, found
    # ... and none elsewhere in what the fit compiles
    assert found == CONSTRUCTION_VIEWS, found - CONSTRUCTION_VIEWS
