"""The library's benchmarks: one timing harness (``common``, ``alternate``, ``machine``) and a
``bench_*`` module per claim, whose current figures are in ``benchmarks/RESULTS.md``.

Run one from the repository root as a module, e.g. ``python -m benchmarks.bench_env``, or all of
them with ``python -m benchmarks.run_all`` (``make bench``). The modules import each other as
``benchmarks.*``; run by file path they cannot, and stop saying so (``benchmarks.py``).
(torchrl's wheel also installs a ``benchmarks`` folder, a namespace package: this regular
package, first on the path from the repository root, wins over it.)
"""
