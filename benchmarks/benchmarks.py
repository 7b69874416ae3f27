"""Not a benchmark: what a benchmark run by file path says.

``python benchmarks/bench_env.py`` puts ``benchmarks/`` first on ``sys.path``, so the script's
``from benchmarks.common import ...`` finds this module as ``benchmarks`` (before torchrl's
``benchmarks`` namespace package in site-packages, whose error would not say what to do), and it
stops with the command that works. Run as ``python -m benchmarks.bench_env`` from the repository
root, ``benchmarks`` is the package and this module is never imported (if it is, as
``benchmarks.benchmarks``, it does nothing).
"""

import os
import sys

if __name__ == "benchmarks":
    _script = sys.argv[0] or "the script"
    _name = os.path.splitext(os.path.basename(_script))[0] or "bench_env"
    raise SystemExit(
        f"{_script} imports its siblings from the package `benchmarks`: run it from the repository root "
        f"as a module, `python -m benchmarks.{_name}` (benchmarks/README.md)."
    )
