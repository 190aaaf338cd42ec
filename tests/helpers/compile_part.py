"""``python compile_part.py PART``: one step of the live harness's ``compile_kernels``
(``live_harness.compile_part``) in this interpreter; the harness runs the fit's here
while it compiles the rest (``tests/helpers`` on ``PYTHONPATH``)."""

from __future__ import annotations

import sys

from live_harness import compile_part

if __name__ == "__main__":
    compile_part(sys.argv[1])
