"""Runs every ``benchmarks.bench_*`` module in turn, each in its own process.

Each script prints its own tables (see ``benchmarks/RESULTS.md`` for the recorded
numbers); this runner prints the machine once, runs the scripts one after the
other (never concurrently: they time things), and ends with a summary of exit
codes and wall times. It exits non-zero if any script failed.

Usage::

    python -m benchmarks.run_all                 # all of them
    python -m benchmarks.run_all env wrappers    # bench_env.py and bench_wrappers.py only
    python -m benchmarks.run_all --list
    python -m benchmarks.run_all -- --rounds 5   # arguments after -- go to every script
"""

from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys
import time

from benchmarks.machine import machine_line

HERE = os.path.dirname(os.path.abspath(__file__))


def discover() -> list[str]:
    return sorted(glob.glob(os.path.join(HERE, "bench_*.py")))


def short_name(path: str) -> str:
    return os.path.basename(path)[len("bench_") : -len(".py")]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    forwarded: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, forwarded = argv[:i], argv[i + 1 :]
    p = argparse.ArgumentParser(description="Run every benchmarks/bench_*.py in turn.")
    p.add_argument("names", nargs="*", help="only these (bench_<name>.py); default: all")
    p.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    args = p.parse_args(argv)

    scripts = discover()
    if args.list:
        for s in scripts:
            print(short_name(s))
        return 0
    if args.names:
        known = {short_name(s): s for s in scripts}
        unknown = [n for n in args.names if n not in known]
        if unknown:
            p.error(f"unknown benchmark(s) {unknown}; available: {sorted(known)}")
        scripts = [known[n] for n in args.names]
    if not scripts:
        print("no benchmarks/bench_*.py found")
        return 1

    print(machine_line())
    summary = []
    for script in scripts:
        cmd = [sys.executable, "-m", f"benchmarks.{os.path.basename(script)[:-3]}", *forwarded]
        print(f"\n{'=' * 78}\n$ python {' '.join(cmd[1:])}\n{'=' * 78}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd, cwd=os.path.dirname(HERE))
        summary.append((short_name(script), rc, time.perf_counter() - t0))

    print(f"\n{'=' * 78}\nsummary")
    for name, rc, dt in summary:
        print(f"  {name:<24} {'ok' if rc == 0 else f'FAILED (exit {rc})':<18} {dt:7.1f} s")
    return 0 if all(rc == 0 for _, rc, _ in summary) else 1


if __name__ == "__main__":
    sys.exit(main())
