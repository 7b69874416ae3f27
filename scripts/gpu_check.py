"""The accelerator machine's check, the device tool's `run` (the calls and the budget: benchmarks/README.md, "GPU kit").

    python3 scripts/gpu_check.py --install-only [OUT]   # call 1: install the carried part (.gpu/kit2)
    python3 scripts/gpu_check.py [OUT]                  # call 2: install .gpu/kit, then the --stages within --budget
    .venv/bin/python scripts/gpu_check.py --local       # dry run here (make gpu-check): no kit, this Python as it is

Into $OUT: summary.json, gpu_check.log, sweep.json, device_copy.json, suite.xml, gpu.xml. Exit 0 when no stage
failed, 2 when a kit part is missing."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT, SITE, T0 = Path(__file__).resolve().parents[1], "/tmp/maniskill_torchrl-gpu-site", time.monotonic()
OUTPUTS = ("summary.json", "gpu_check.log", "sweep.json", "device_copy.json", "suite.xml", "gpu.xml", "ceilings.json")
LOG, STAGES = None, ("sweep", "copy", "suite", "gpu", "ceilings")
# The machine's loaders (the device README's recipe), printed back as KEY=VALUE for this process.
LOADERS_SH = r"""X=/tmp/maniskill_torchrl-x11 N=/usr/local/nvidia/share
if ! ldconfig -p | grep -q 'libvulkan\.so\.1 ' && [ -d .gpu/kit/gl ]; then
  for f in .gpu/kit/gl/*.deb; do dpkg -x "$f" /; done; ldconfig; echo "# unpacked .gpu/kit/gl to /" >&2; fi
if ! ldconfig -p | grep -q 'libX11\.so\.6 ' && [ -d .gpu/kit/x11 ]; then  # not to /: kept private
  for f in .gpu/kit/x11/*.deb; do dpkg -x "$f" $X; done
  echo "LD_LIBRARY_PATH=$X/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"; fi
if ! ls /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json >/dev/null 2>&1 \
   && [ -f $N/vulkan/icd.d/nvidia_icd.json ]; then
  echo "VK_ICD_FILENAMES=$N/vulkan/icd.d/nvidia_icd.json"; echo "VK_DRIVER_FILES=$N/vulkan/icd.d/nvidia_icd.json"
  echo "__EGL_VENDOR_LIBRARY_FILENAMES=$N/glvnd/egl_vendor.d/10_nvidia.json"; fi"""
# Byte-compiles the folders given and the machine's packages without .pyc (PYTHONDONTWRITEBYTECODE there).
COMPILE = r"""import compileall, importlib.util as u, os, sys
dirs = sys.argv[1:] + ["maniskill_torchrl", "tests", "benchmarks", "examples"]  # the site, the repository
for name in ("torch", "numpy", "scipy", "sympy", "networkx", "PIL", "h5py", "imageio", "matplotlib", "cv2"):
    s = u.find_spec(name)
    if s and s.origin and s.origin.endswith("__init__.py") and not os.path.exists(u.cache_from_source(s.origin)):
        dirs.append(os.path.dirname(s.origin)); print("and the machine's", dirs[-1])
sys.exit(not all([compileall.compile_dir(d, quiet=2, workers=0) for d in dirs]))"""
# One fresh process: import times, versions, C extensions (torchrl's is built for torch 2.14: on another torch no
# prioritized replay), the GPU, pytest plugins, SAPIEN's PhysX GPU library (copied from .gpu/physx when carried).
PROBE = r"""import importlib, json, os, shutil, subprocess, sys, time
out = {"import_s": {"launch_to_main_s": round(time.time() - float(sys.argv[1]), 2)}}
for mod in ("torch", "gymnasium", "sapien", "mani_skill.envs", "tensordict", "tensordict._C", "torchrl",
            "torchrl._torchrl", "maniskill_torchrl", "numpy"):
    try:
        t = time.perf_counter(); m = importlib.import_module(mod); t = round(time.perf_counter() - t, 2)
        out["import_s"][mod], out[mod] = t, f"{getattr(m, '__version__', 'ok')} ({os.path.dirname(m.__file__)})"
    except Exception as e:
        out[mod] = f"IMPORT FAILED: {type(e).__name__}: {str(e)[:300]}"
out["cuda"] = "torch" in sys.modules and sys.modules["torch"].cuda.is_available()
smi = "nvidia-smi --format=csv,noheader --query-gpu=name,driver_version,memory.total"
out["gpu"] = shutil.which("nvidia-smi") and subprocess.getoutput(smi)
out["plugins"] = {m: bool(importlib.util.find_spec(m)) for m in ("pytest_timeout", "xdist")}
out["pythondontwritebytecode"] = os.environ.get("PYTHONDONTWRITEBYTECODE")
out["cpu"] = next((x.split(":")[1].strip() for x in open("/proc/cpuinfo") if x.startswith("model name")), "")
lib = os.path.expanduser(f"~/.sapien/physx/{sys.modules['sapien'].physx.version()}") if "sapien" in sys.modules else "?"
if not os.path.exists(f"{lib}/libPhysXGpu_64.so") and os.path.exists(".gpu/physx/libPhysXGpu_64.so") and lib != "?":
    shutil.copytree(".gpu/physx", lib, dirs_exist_ok=True)
out["physx_gpu_library"] = "ok" if os.path.exists(f"{lib}/libPhysXGpu_64.so") else f"no {lib}/libPhysXGpu_64.so"
json.dump(out, open(sys.argv[2], "w"))"""


def log(msg: str) -> None:
    for file in (sys.stdout, LOG):
        print(f"gpu-check [{time.monotonic() - T0:5.0f}s]: {msg}", file=file, flush=True)


def run(cmd: list[str], limit: float, env: dict | None = None) -> tuple[str, int | None, float]:
    """cmd in its own session, its output to the log; at the limit SIGINT (pytest then writes its JUnit file),
    SIGKILL 20 s later, and to whatever it left. Returns (status, exit code, wall s)."""
    t, status = time.monotonic(), None
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=LOG, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        proc.wait(timeout=max(1.0, limit))
    except subprocess.TimeoutExpired:
        status = "timed_out"
        with contextlib.suppress(ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(proc.pid, signal.SIGINT)
            proc.wait(timeout=20)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)  # the command if SIGINT did not end it, and whatever it left
    proc.wait()
    return status or ("passed" if proc.returncode == 0 else "failed"), proc.returncode, round(time.monotonic() - t, 1)


def install(env: dict) -> tuple[list[str], str | None]:
    """Loaders; each carried part's wheels into the site, stamped (the project's wheel into this Python too)."""
    parts = sorted(p.parent.name for p in ROOT.glob(".gpu/kit*/wheels"))
    if not parts:
        return [], "no kit carried (.gpu/kit*/wheels): build it with `make gpu-kit` and carry .gpu/kit2, .gpu/kit"
    res = subprocess.run(["bash", "-c", LOADERS_SH], cwd=ROOT, capture_output=True, text=True)
    env.update(line.split("=", 1) for line in res.stdout.splitlines())
    log(f"loaders: {res.stdout.split() or 'the machine has libvulkan.so.1, libX11.so.6, the ICD'} {res.stderr.strip()}")
    pip = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile", "--force-reinstall"]
    for part in parts:
        wheels = sorted(str(w) for w in (ROOT / ".gpu" / part / "wheels").glob("*.whl"))
        stamp, names = Path(SITE, f".installed-{part}"), "".join(Path(w).name + "\n" for w in wheels)
        if stamp.exists() and stamp.read_text() == names:
            log(f".gpu/{part} already installed in {SITE} (warm machine)")
            continue
        own = [w for w in wheels if Path(w).name.startswith("maniskill_torchrl-")]
        st, _, s = run(pip + ["--upgrade", "--target", SITE, *sorted(set(wheels) - set(own))], 180, env)
        log(f".gpu/{part}: {len(wheels) - len(own)} wheels into {SITE}: {st} in {s}s")
        if st != "passed":
            return parts, f"pip install of .gpu/{part} failed"
        if own:  # the checks import the repository's copy
            log(f".gpu/{part}: the project's wheel into {sys.executable}: {run(pip + own, 60, env)[0]}")
        stamp.write_text(names)
    st, _, s = run([sys.executable, "-c", COMPILE, SITE], 150, env)
    log(f"compileall of {SITE} and the repository: {st} in {s}s")
    return parts, None


def junit(path: Path) -> dict:
    try:
        cases = sorted(ET.parse(path).getroot().iter("testcase"), key=lambda c: -float(c.get("time") or 0))
    except (OSError, ET.ParseError) as e:
        return {"junit": f"unreadable: {e}"}
    res = {"passed": 0, "failed": 0, "errors": 0, "skipped": 0, "failed_tests": {}, "skip_reasons": {}}
    for case in cases:
        tags = {child.tag: (child.get("message") or "").strip() for child in case}
        tag = next((t for t in ("failure", "error", "skipped") if t in tags), None)
        res[{"failure": "failed", "error": "errors", "skipped": "skipped", None: "passed"}[tag]] += 1
        if tag == "skipped":
            res["skip_reasons"][tags[tag][:200]] = res["skip_reasons"].get(tags[tag][:200], 0) + 1
        elif tag:
            res["failed_tests"][f"{case.get('classname')}::{case.get('name')}"] = f"{tag}: {tags[tag][:300]}"
    res["slowest_s"] = {f"{c.get('classname')}::{c.get('name')}": float(c.get("time") or 0) for c in cases[:10]}
    return res


def sweep_summary(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        return {"json": f"missing: {e}"}
    rates, startup, failed, ran = {}, {}, {}, {}
    for one in d.get("runs", []):
        spec, n, r = one["name"].split(" N=")[0], int(one["name"].split("N=")[1].split()[0]), one.get("result") or {}
        if not r or r.get("skipped") or r.get("failed"):
            failed.setdefault(spec, {})[n] = r.get("skipped") or r.get("failed") or "failed"
            continue
        rates.setdefault(spec, {}).setdefault(n, []).append(r["units"] / r["wall_s"])  # frames: agent steps
        startup.setdefault(f"{spec} N={n}", []).append({k: r.get(k) for k in ("startup_s", "imports_s")})
        ran.setdefault(spec, {k: r[k] for k in ("main_threads", "worker_threads", "sims") if k in r})
    fps = {s: {n: round(statistics.median(v), 1) for n, v in sorted(by_n.items())} for s, by_n in rates.items()}
    gym = fps.get("gym") or next((v for s, v in fps.items() if s.split(":")[0] == "gym"), {})
    out = {"complete": d.get("complete"), "frames_per_s": fps, "child_startup_s": startup, "not_measured": failed}
    out["rounds"] = {s: {n: len(v) for n, v in by_n.items()} for s, by_n in rates.items()}
    out["ran"] = ran  # torch threads main / workers, the sims' mode (benchmarks/bench_collection.py)
    out["ratio_to_gym"] = {s: {n: round(v[n] / gym[n], 2) for n in gym if n in v} for s, v in fps.items() if v != gym}
    best = {n: max(fps[g][n] for g in ("gym", "gym:t1") if n in fps.get(g, {})) for n in gym}  # the faster gym
    out["ratio_to_best_gym"] = {s: {n: round(v[n] / best[n], 2) for n in best if n in v} for s, v in fps.items()
                                if s.split(":")[0] != "gym"}  # fmt: skip
    out["scaling_vs_n_times_n1"] = {s: {n: round(v[n] / n / v[1], 2) for n in v if n > 1} for s, v in fps.items()
                                    if 1 in v}  # fmt: skip
    return out


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    arg = p.add_argument
    arg("out", nargs="?", default=os.environ.get("OUT") or "outputs/gpu-check")
    arg("--install-only", action="store_true", help="install the carried part(s), then stop")
    arg("--local", action="store_true", help="dry run here (make gpu-check): no kit, this Python as it is")
    arg("--budget", type=float, default=450, help="seconds for this call, set-up included (450)")
    arg("--stages", nargs="*", default=["sweep", "copy", "suite", "gpu"], choices=STAGES)
    # The sweep (benchmarks/README.md, "GPU kit": ~17 min in all, so it runs by N in calls of its own): all
    # rounds of one N before the next, the largest N first; it starts no child that would end past its limit.
    arg("--sweep-n", type=int, nargs="+", default=[15, 8, 4, 1], help="sub-envs, in the order run (15 8 4 1)")
    arg("--sweep-seconds", type=float, default=2.0, help="timed collection per run (2)")
    arg("--sweep-rounds", type=int, default=3, help="alternating rounds of the sweep (3)")
    # The library's asynchronous path, async:lib, makes it ~22 min in all (benchmarks/README.md).
    sweep = ["gym:t1", "batched:t1,rp,dev,em", "async:auto", "async:lib"]
    arg("--sweep-pipelines", nargs="+", default=sweep, help=f"besides gym ({' '.join(sweep)})")
    arg("--startup-limit", type=float, default=40, help="start-up limit of one benchmark child (40 s)")
    arg("--sweep-s", type=float, default=150, help="sweep limit (150 s)")
    arg("--copy-s", type=float, default=75, help="bench_obs_copy --timing limit (75 s)")
    arg("--suite-s", type=float, default=210, help="kept for the suite by the stages before it (210 s)")
    arg("--gpu-s", type=float, default=120, help="tests/gpu limit, kept for it by the stages before it (120 s)")
    arg("--ceilings-s", type=float, default=150, help="bench_ceilings limit (150 s)")
    arg("--workers", type=int, default=os.cpu_count(), help="suite workers (cores)")
    arg("--suite", nargs="+", default=["tests"], help="what the suite stage runs (tests)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    global LOG
    args = parse(argv)
    out, env = Path(args.out).resolve(), dict(os.environ, PYTHONUNBUFFERED="1", RL_WARNINGS="0")
    out.mkdir(parents=True, exist_ok=True)
    for f in OUTPUTS:
        (out / f).unlink(missing_ok=True)
    LOG = open(out / "gpu_check.log", "a")  # the commands' output appended too
    machine = {"host": os.uname().nodename, "cores": os.cpu_count(), "python": sys.version.split()[0]}
    summary = {"date_utc": time.strftime("%FT%T+00:00", time.gmtime()), "budget_s": args.budget, "machine": machine}
    stages = summary["stages"] = {}
    log(f"{ROOT} -> {out}; {machine}; budget {args.budget:.0f}s; stages {args.stages}")

    def finish(code: int, error: str | None = None) -> int:
        summary.update(wall_s=round(time.monotonic() - T0, 1), **({"error": error} if error else {}))
        summary["failed_stages"] = [k for k, v in stages.items() if v["status"] in ("failed", "timed_out")]
        summary["skipped_stages"] = {k: v.get("note", "") for k, v in stages.items() if v["status"] == "skipped"}
        summary["ok"] = code == 0 and not summary["failed_stages"]
        (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        for k, v in stages.items():  # the end of the output is what the device tool's reply shows
            print(f"  {k:8s} {json.dumps({x: y for x, y in v.items() if x not in ('slowest_s', 'child_startup_s')})}")
        log(f"summary.json: ok={summary['ok']}, {summary['wall_s']}s; failed {summary['failed_stages']}, "
            f"skipped {list(summary['skipped_stages'])}{'; ERROR: ' + error if error else ''}")  # fmt: skip
        return code or (0 if summary["ok"] else 1)

    path = [str(ROOT)] + ([] if args.local else [SITE])  # the repository first: torchrl ships a `benchmarks` folder
    if not args.local:
        Path(SITE).mkdir(parents=True, exist_ok=True)
        t, (parts, error) = time.monotonic(), install(env)
        summary.update(kit_parts=parts, install_s=round(time.monotonic() - t, 1))
        if error or args.install_only:
            return finish(1 if parts and error else 2 if error else 0, error)
        names = (ROOT / ".gpu" / parts[0] / "PARTS.txt").read_text().split()  # every part of the kit
        if missing := [f".gpu/{n}" for n in names if not Path(SITE, f".installed-{n}").exists()]:
            return finish(2, f"{missing} not installed: the machine went back between the calls; make both again")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [*path, env.get("PYTHONPATH")]))
    st, _, s = run([sys.executable, "-c", PROBE, repr(time.time()), str(out / "summary.json")], 120, env)
    probe = json.loads((out / "summary.json").read_text()) if st == "passed" else {"probe": f"{st}: see the log"}
    summary["environment"] = probe  # the probe wrote it to summary.json, which finish() then rewrites whole
    log(f"probe ({s}s): {json.dumps(probe)}")

    py, n, plugins = sys.executable, [str(k) for k in args.sweep_n], probe.get("plugins", {})
    pytest = [py, "-m", "pytest", "-q", "-rfEs", "--durations=15", "-p", "no:cacheprovider", "-o",
              "junit_family=xunit1", *(["--timeout", "240"] if plugins.get("pytest_timeout") else [])]  # fmt: skip
    workers = ["-n", str(args.workers), "--dist", "worksteal"] if plugins.get("xdist") and args.workers > 1 else []
    commands = {
        "sweep": [py, "-m", "benchmarks.bench_collection", "--n", *n, "--repeat", "2", "--rounds",
                  str(args.sweep_rounds), "--seconds", str(args.sweep_seconds), "--pipelines", *args.sweep_pipelines,
                  "--order", "n", "--max-wait", "3", "--retries", "0", "--startup-limit", str(args.startup_limit),
                  "--timeout", str(args.startup_limit + args.sweep_seconds + 20), "--out", str(out / "sweep.json")],
        "copy": [py, "-m", "benchmarks.bench_obs_copy", "--timing", "--out", str(out / "device_copy.json")],
        # tests/gpu also holds the CUDA double's test, which runs in the suite as it always did.
        "suite": pytest + [*args.suite, "--ignore=tests/registry", "--ignore=tests/docs",
                           "--ignore-glob=tests/gpu/test_gpu_*.py", f"--junitxml={out / 'suite.xml'}", *workers],
        "gpu": pytest + ["tests/gpu", "--ignore=tests/gpu/test_cuda_machine.py", f"--junitxml={out / 'gpu.xml'}"],
        "ceilings": [py, "-m", "benchmarks.bench_ceilings", "--n", *n, "--seconds", "3", "--rounds", "2",
                     "--out", str(out / "ceilings.json"), "--budget"],  # + the stage's limit less 45 s
        # (the sweep: + --budget, the stage's limit less 30 s: it starts no child that would end later)
    }  # fmt: skip
    physx = probe.get("physx_gpu_library", "no probe")
    limits = {"sweep": args.sweep_s, "copy": args.copy_s, "suite": 1e9, "gpu": args.gpu_s, "ceilings": args.ceilings_s}
    kept = {"suite": args.suite_s, "gpu": args.gpu_s if physx == "ok" else 0}  # what the stages before these leave
    for i, name in enumerate(args.stages):
        left = args.budget - (time.monotonic() - T0) - 30  # a stage stopped at its limit gets 20 s to end
        limit = min(limits.get(name, 0), left - sum(kept.get(later, 0) for later in args.stages[i + 1 :]))
        gpu_off = name == "gpu" and physx != "ok"
        if gpu_off or limit < 30:
            stages[name] = {"status": "skipped", "note": f"{physx}: no GPU sim" if gpu_off else f"{limit:.0f}s left"}
            log(f"stage {name}: {stages[name]}")
            continue
        budget = {"ceilings": [str(max(limit - 45, 10))], "sweep": ["--budget", str(max(limit - 30, 10))]}
        cmd = commands[name] + budget.get(name, [])
        log(f"stage {name} (limit {limit:.0f}s): {' '.join(cmd)}")
        st, rc, s = run(cmd, limit, env)
        stage = stages[name] = {"status": st, "exit_code": rc, "wall_s": s, "limit_s": round(limit)}
        if name == "sweep":
            stage.update(sweep_summary(out / "sweep.json"))
            if st == "passed" and stage.get("not_measured"):
                stage.update(status="failed", note="runs without a result (not_measured)")
        elif name in ("suite", "gpu"):
            stage.update(junit(out / f"{name}.xml"))
        elif (result := out / ("device_copy.json" if name == "copy" else "ceilings.json")).exists():
            result, keys = json.loads(result.read_text()), ("topology", "summary", "stopped")  # ceilings': the gist
            stage["result"] = {k: result.get(k) for k in keys} if name == "ceilings" else result
        log(f"stage {name}: {stage['status']} (exit {rc}) in {s}s")
    return finish(0)


if __name__ == "__main__":
    sys.exit(main())
