"""The accelerator machine's check (device tool `run`; the calls: benchmarks/README.md, "GPU kit").

    python3 scripts/gpu_check.py --install-only [OUT]   # call 1: install the carried part (.gpu/kit2)
    python3 scripts/gpu_check.py [OUT]                  # call 2: install .gpu/kit, then the stages
    .venv/bin/python scripts/gpu_check.py --local       # dry run here: no kit, this Python as it is

Set-up: the Vulkan / GL loaders (one small shell step), the kit's wheels into a --target site,
byte-compiled there (a fresh process then reads .pyc instead of compiling every module), a probe
of versions, C extensions and one fresh process's import times. Stages, in this order, each under
its own limit and all inside --budget seconds from the start (a stage that would get under 30 s is
skipped and says so; one that fails does not stop the others):

    sweep  benchmarks/bench_collection.py, N = 1 8 15, repeat 2 (--sweep-pipelines): gym's
           AsyncVectorEnv of CPUGymWrapper against the README's pipeline and
           AsyncBatchedCollector, first, on a quiet machine; each child's start-up
           measured and bounded (--startup-limit)
    copy   benchmarks/bench_obs_copy.py --timing (device_copy.json)
    suite  pytest tests (without registry, docs, gpu), xdist -n cores --dist worksteal, JUnit
    gpu    pytest tests/gpu, only with SAPIEN's PhysX GPU library (it cannot be downloaded there)
    ceilings  benchmarks/bench_ceilings.py (only when named in --stages): topology, one raw env, N
           independent raw-env processes and N in lockstep, the CPU sim's ceilings (ceilings.json)

$OUT gets summary.json (written here, also when a stage fails), gpu_check.log, sweep.json,
device_copy.json, suite.xml, gpu.xml. Exit 0 when no stage failed, 2 when a kit part is missing.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
T0 = time.monotonic()
LOG = None

# The machine's loaders (the device README's recipe), printed back as KEY=VALUE for this process.
LOADERS_SH = r"""
if ! ldconfig -p | grep -q 'libvulkan\.so\.1 ' && [ -d .gpu/kit/gl ]; then
  for f in .gpu/kit/gl/*.deb; do dpkg -x "$f" /; done; ldconfig; echo "# unpacked .gpu/kit/gl to /" >&2
fi
if ! ldconfig -p | grep -q 'libX11\.so\.6 ' && [ -d .gpu/kit/x11 ]; then  # not to /: kept private
  for f in .gpu/kit/x11/*.deb; do dpkg -x "$f" /tmp/maniskill_torchrl-x11; done
  echo "LD_LIBRARY_PATH=/tmp/maniskill_torchrl-x11/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi
n=/usr/local/nvidia/share
if ! ls /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json >/dev/null 2>&1 \
   && [ -f $n/vulkan/icd.d/nvidia_icd.json ]; then
  echo "VK_ICD_FILENAMES=$n/vulkan/icd.d/nvidia_icd.json"; echo "VK_DRIVER_FILES=$n/vulkan/icd.d/nvidia_icd.json"
  echo "__EGL_VENDOR_LIBRARY_FILENAMES=$n/glvnd/egl_vendor.d/10_nvidia.json"
fi
"""

# The machine's own packages that the checks import and that have no .pyc.
UNCOMPILED = r"""
import importlib.util, os
for name in ("torch", "numpy", "scipy", "sympy", "networkx", "PIL", "h5py", "imageio", "matplotlib", "cv2"):
    spec = importlib.util.find_spec(name)
    if spec and spec.origin and spec.origin.endswith("__init__.py"):
        if not os.path.exists(importlib.util.cache_from_source(spec.origin)):
            print(os.path.dirname(spec.origin))
"""

# One fresh process: import times, versions, C extensions, what this torch supports.
PROBE = r"""
import json, os, sys, time
t = {"launch_to_main_s": round(time.time() - float(sys.argv[1]), 2)}
out = {"import_s": t}
for mod in ("torch", "gymnasium", "sapien", "mani_skill.envs", "tensordict", "torchrl", "maniskill_torchrl"):
    s = time.perf_counter()
    try:
        __import__(mod)
        t[mod] = round(time.perf_counter() - s, 2)
    except Exception as e:
        t[mod] = f"IMPORT FAILED: {type(e).__name__}: {e}"
import torch
out["torch"], out["cuda"] = torch.__version__, torch.cuda.is_available()
for mod in ("tensordict", "torchrl", "gymnasium", "sapien", "mani_skill", "numpy", "maniskill_torchrl"):
    m = sys.modules.get(mod)
    out[mod] = f"{getattr(m, '__version__', '?')} ({os.path.dirname(m.__file__)})" if m else "missing"
for name, mod in (("tensordict_C", "tensordict._C"), ("torchrl_C", "torchrl._torchrl")):
    try:
        __import__(mod)
        out[name] = "ok"
    except Exception as e:
        out[name] = f"{type(e).__name__}: {str(e)[:300]}"
try:
    from torchrl.data import LazyTensorStorage, PrioritizedReplayBuffer
    PrioritizedReplayBuffer(alpha=0.6, beta=0.4, storage=LazyTensorStorage(10))
    out["prioritized_replay"] = "ok"
except Exception as e:
    out["prioritized_replay"] = (
        f"unavailable with torch {torch.__version__}: torchrl's C extension is built for torch 2.14 and does "
        f"not load here ({type(e).__name__}: {str(e)[:120]}); everything else (ManiSkillEnv, transforms, "
        "Collector, PPO, SAC with uniform replay) works"
    )
out["pythondontwritebytecode"] = os.environ.get("PYTHONDONTWRITEBYTECODE")
print("@@probe " + json.dumps(out))
"""


def log(msg: str) -> None:
    line = f"gpu-check [{time.monotonic() - T0:5.0f}s]: {msg}"
    print(line, flush=True)
    if LOG:
        LOG.write(line + "\n")
        LOG.flush()


def run(cmd: list[str], limit: float, env: dict | None = None, echo: bool = True) -> tuple[str, int | None, float]:
    """Runs cmd in its own session, its output to the log; at the limit SIGINT (pytest then writes its
    JUnit file), SIGKILL 20 s later. Returns (status, exit code, wall s)."""
    t = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)  # fmt: skip
    import threading

    lines: list[str] = []

    def read() -> None:
        for line in proc.stdout:
            lines.append(line)
            if echo:
                sys.stdout.write(line)
            if LOG:
                LOG.write(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    status = None
    try:
        proc.wait(timeout=max(1.0, limit))
    except subprocess.TimeoutExpired:
        status = "timed_out"
        for sig, grace in ((signal.SIGINT, 20), (signal.SIGKILL, 5)):
            try:
                os.killpg(proc.pid, sig)
                proc.wait(timeout=grace)
                break
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)  # whatever the command left running
    except (ProcessLookupError, PermissionError):
        pass
    reader.join(timeout=5)
    run.output = "".join(lines)
    rc = proc.returncode
    return status or ("passed" if rc == 0 else "failed"), rc, round(time.monotonic() - t, 1)


def install(args, env: dict) -> tuple[list[str], float, str | None]:
    """Loaders, then every carried part's wheels into the site (byte-compiled); the project's wheel into
    the machine's Python (its console script). Returns (parts, seconds, error)."""
    t = time.monotonic()
    parts = sorted(str(p.parent.relative_to(ROOT)) for p in ROOT.glob(".gpu/kit*/wheels"))
    if not parts:
        return [], 0.0, "no kit carried (.gpu/kit*/wheels): build it with `make gpu-kit` and carry .gpu/kit2, .gpu/kit"
    res = subprocess.run(["bash", "-c", LOADERS_SH], cwd=ROOT, capture_output=True, text=True)
    for line in res.stdout.splitlines():
        key, _, value = line.partition("=")
        env[key] = os.environ[key] = value
        log(f"loader: {line}")
    log(res.stderr.strip() or "loaders: the machine has libvulkan.so.1 and libX11.so.6")
    site = Path(args.site)
    site.mkdir(parents=True, exist_ok=True)
    for part in parts:
        wheels = sorted((ROOT / part / "wheels").glob("*.whl"))
        stamp = site / f".installed-{Path(part).name}-{_digest(ROOT / part)}"
        if stamp.exists():
            log(f"{part} already installed in {site} (warm machine)")
            continue
        deps = [str(w) for w in wheels if not w.name.startswith("maniskill_torchrl-")]
        own = [str(w) for w in wheels if w.name.startswith("maniskill_torchrl-")]
        pip = [args.python, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile", "--no-cache-dir"]
        st, rc, s = run(pip + ["--upgrade", "--target", str(site)] + deps, 180, echo=False)
        log(f"{part}: {len(deps)} wheels into {site}: {st} in {s}s")
        if st != "passed":
            print(run.output[-3000:])
            return parts, time.monotonic() - t, f"pip install of {part} failed"
        if own:  # its console script beside python3; the checks import the repository's copy
            st, _, _ = run(pip + ["--force-reinstall"] + own, 60, echo=False)
            log(f"{part}: the project's wheel into {args.python}'s environment: {st}")
        stamp.touch()
    # Byte-compile the site, the repository and the machine's own packages that the checks import if
    # they have no .pyc: each fresh process (suite workers, benchmark children) then loads .pyc instead
    # of compiling torch, mani_skill, torchrl, tensordict, sapien from source (PYTHONDONTWRITEBYTECODE).
    res = subprocess.run([args.python, "-c", UNCOMPILED], capture_output=True, text=True)
    own = res.stdout.split()
    dirs = [str(site), "maniskill_torchrl", "tests", "benchmarks", "examples", *own]
    st, _, s = run([args.python, "-m", "compileall", "-q", "-j", "0", *dirs], 150, echo=False)
    log(f"compileall of {site}, the repository and the machine's {own or 'nothing (all compiled)'}: {st} in {s}s")
    return parts, time.monotonic() - t, None


def _digest(part: Path) -> str:
    return hashlib.sha256("".join(sorted(p.name + "\n" for p in (part / "wheels").iterdir())).encode()).hexdigest()[:16]


def missing_parts(parts: list[str], site: Path) -> list[str]:
    """The kit's parts (PARTS.txt names all of them) that no call installed on this machine."""
    listed = (ROOT / parts[0] / "PARTS.txt").read_text().split("\n") if parts else []
    names = [line.split()[0] for line in listed if line.strip()]
    return [f".gpu/{n}" for n in names if not list(site.glob(f".installed-{n}-*"))]


def junit(path: Path) -> dict:
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        return {"junit": f"unreadable: {e}"}
    res = {k: 0 for k in ("passed", "failed", "errors", "skipped")}
    failed, skips, times = {}, {}, []
    for case in root.iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        times.append((float(case.get("time") or 0), name))
        tags = {child.tag: child for child in case}
        for tag, key in (("failure", "failed"), ("error", "errors")):
            if tag in tags:
                res[key] += 1
                failed[name] = f"{tag}: {(tags[tag].get('message') or '').strip()[:300]}"
        if "skipped" in tags:
            res["skipped"] += 1
            reason = (tags["skipped"].get("message") or "").strip()[:200]
            skips[reason] = skips.get(reason, 0) + 1
        elif not {"failure", "error"} & tags.keys():
            res["passed"] += 1
    return {**res, "failed_tests": failed, "skip_reasons": skips,
            "slowest_s": {n: round(t, 1) for t, n in sorted(times, reverse=True)[:10]}}  # fmt: skip


def sweep_summary(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        return {"json": f"missing: {e}"}
    fps, startup, failed = {}, {}, {}
    for run_ in d.get("runs", []):
        spec, n = run_["name"].split(" N=")[0], int(run_["name"].split("N=")[1].split()[0])
        r = run_.get("result")
        if not r or r.get("skipped") or r.get("failed"):
            failed.setdefault(spec, {})[n] = (r or {}).get("skipped") or (r or {}).get("failed") or "failed"
            continue
        fps.setdefault(spec, {})[n] = round(r["units"] / r["wall_s"], 1)
        startup[f"{spec} N={n}"] = {k: r.get(k) for k in ("startup_s", "interpreter_s", "imports_s")}
    out = {"complete": d.get("complete", False), "frames_per_s": fps, "child_startup_s": startup}
    if failed:
        out["not_measured"] = failed
    gym = next((v for s, v in fps.items() if s.split(":")[0] == "gym"), {})
    out["ratio_to_gym"] = {
        s: {n: round(v[n] / gym[n], 2) for n in gym if n in v} for s, v in fps.items() if s.split(":")[0] != "gym"
    }
    out["scaling_vs_n_times_n1"] = {
        s: {n: round(v[n] / (n * v[1]), 2) for n in v if n > 1} for s, v in fps.items() if 1 in v
    }
    return out


def main(argv: list[str] | None = None) -> int:
    global LOG
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", nargs="?", default=os.environ.get("OUT") or "outputs/gpu-check")
    p.add_argument("--install-only", action="store_true", help="install the carried part(s), then stop")
    p.add_argument("--local", action="store_true", help="dry run here: no kit, 2 workers, a short sweep")
    p.add_argument("--budget", type=float, default=430, help="seconds for this call, set-up included (430)")
    p.add_argument("--stages", nargs="*", default=["sweep", "copy", "suite", "gpu"])
    p.add_argument("--python", default=sys.executable)
    p.add_argument("--site", default="/tmp/maniskill_torchrl-gpu-site")
    p.add_argument("--sweep-n", type=int, nargs="+", default=[1, 8, 15])
    p.add_argument("--sweep-seconds", type=float, default=2.0, help="timed collection per run (2)")
    p.add_argument("--sweep-rounds", type=int, default=1, help="alternating rounds of the sweep (1)")
    p.add_argument(
        "--sweep-pipelines",
        nargs="+",
        default=["batched:t1,rp,dev,em", "async:auto"],
        help="bench_collection.py contenders besides gym, repeat 2 (the README's pipeline, past lockstep)",
    )
    p.add_argument("--startup-limit", type=float, default=40, help="start-up limit of one benchmark child (40 s)")
    p.add_argument("--sweep-s", type=float, default=165, help="sweep limit (165 s)")
    p.add_argument("--copy-s", type=float, default=90, help="bench_obs_copy --timing limit (90 s)")
    p.add_argument("--gpu-s", type=float, default=120, help="tests/gpu limit (120 s)")
    p.add_argument("--ceilings-s", type=float, default=150, help="bench_ceilings limit (150 s)")
    p.add_argument("--workers", type=int, default=os.cpu_count(), help="suite workers (cores)")
    p.add_argument("--per-test-s", type=float, default=240, help="one test's limit (pytest-timeout, if there)")
    p.add_argument("--suite", nargs="+", default=["tests"], help="what the suite stage runs (tests)")
    args = p.parse_args(argv)
    if args.local:  # a dry run here: what the command line leaves at its default
        local = {"workers": min(args.workers, 2), "sweep_n": [1, 2], "sweep_seconds": 1.0, "budget": 3600,
                 "sweep_s": 600, "startup_limit": 120, "copy_s": 300}  # fmt: skip
        for k, v in local.items():
            if getattr(args, k) == p.get_default(k):
                setattr(args, k, v)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    for f in ("summary.json", "gpu_check.log", "sweep.json", "device_copy.json", "suite.xml", "gpu.xml"):
        (out / f).unlink(missing_ok=True)
    for f in ("ceilings.json",):
        (out / f).unlink(missing_ok=True)
    LOG = open(out / "gpu_check.log", "w")
    env = dict(os.environ, PYTHONUNBUFFERED="1", RL_WARNINGS="0")
    summary: dict = {"date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                     "budget_s": args.budget, "machine": machine()}  # fmt: skip
    log(f"{ROOT} -> {out}; {summary['machine']}; budget {args.budget:.0f}s; stages {args.stages}")

    def finish(code: int, error: str | None = None) -> int:
        summary["wall_s"] = round(time.monotonic() - T0, 1)
        stages = summary.get("stages", {})
        summary["failed_stages"] = [k for k, v in stages.items() if v["status"] in ("failed", "timed_out")]
        summary["skipped_stages"] = {k: v.get("note", "") for k, v in stages.items() if v["status"] == "skipped"}
        if error:
            summary["error"] = error
        summary["ok"] = code == 0 and not summary["failed_stages"]
        (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        for k, v in stages.items():  # the end of the output is what the device tool's reply shows
            counts = {c: v[c] for c in ("passed", "failed", "errors", "skipped") if c in v}
            wall, limit = v.get("wall_s", 0), v.get("limit_s", 0)
            print(f"  {k:6s} {v['status']:9s} {wall:6.1f}s / {limit}s {counts} {v.get('note', '')}")
            for t, msg in list(v.get("failed_tests", {}).items())[:30]:
                print(f"         FAILED {t}: {msg[:200]}")
            for key in ("frames_per_s", "ratio_to_gym", "scaling_vs_n_times_n1", "child_startup_s",
                        "not_measured", "result"):  # fmt: skip
                if v.get(key):
                    print(f"         {key}: {json.dumps(v[key])}")
        log(f"summary.json: ok={summary['ok']}, {summary['wall_s']}s; failed {summary['failed_stages']}, "
            f"skipped {list(summary['skipped_stages'])}")  # fmt: skip
        return code if code else (0 if summary["ok"] else 1)

    if not args.local:
        parts, install_s, error = install(args, env)
        summary.update(kit_parts=parts, install_s=round(install_s, 1))
        if error:
            log(f"ERROR: {error}")
            return finish(2 if not parts else 1, error)
        # the repository first: torchrl's wheel ships top-level `benchmarks` and `scripts` packages
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), args.site, env.get("PYTHONPATH")]))
        if args.install_only:
            return finish(0)
        missing = missing_parts(parts, Path(args.site))
        if missing:
            error = f"{missing} not installed: the machine went back between the calls; make both calls again"
            log(f"ERROR: {error}")
            return finish(2, error)
    else:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    st, _, s = run([args.python, "-c", PROBE, repr(time.time())], 120, env, echo=False)
    probe = next((json.loads(line[8:]) for line in run.output.splitlines() if line.startswith("@@probe ")), None)
    summary["environment"] = probe or {"probe": f"{st}: {run.output[-1000:]}"}
    log(f"probe ({s}s): {json.dumps(summary['environment'])}")
    physx = physx_library(args, env)
    summary["physx_gpu_library"] = physx or "ok"

    stages = summary["stages"] = {}
    py = args.python
    for name in args.stages:
        left = args.budget - (time.monotonic() - T0) - 30  # a stage stopped at its limit gets 20 s to end
        if name == "gpu" and physx:
            stages[name] = {"status": "skipped", "note": physx}
            continue
        limit = {"sweep": args.sweep_s, "copy": args.copy_s, "gpu": args.gpu_s, "ceilings": args.ceilings_s}.get(
            name, left
        )
        limit = min(limit, left)
        if limit < 30:
            stages[name] = {"status": "skipped", "note": f"{left:.0f}s left of the {args.budget:.0f}s budget"}
            log(f"stage {name}: skipped, {left:.0f}s left")
            continue
        pytest = [py, "-m", "pytest", "-q", "-rfEs", "--durations=15", "-p", "no:cacheprovider",
                  "-o", "junit_family=xunit1"]  # fmt: skip
        if _has(py, env, "pytest_timeout"):
            pytest += ["--timeout", str(args.per_test_s)]
        cmd = {
            "sweep": [py, "benchmarks/bench_collection.py", "--n", *map(str, args.sweep_n), "--repeat", "2",
                      "--rounds", str(args.sweep_rounds), "--seconds", str(args.sweep_seconds),
                      "--pipelines", *args.sweep_pipelines,
                      "--max-wait", "3", "--retries", "0", "--startup-limit", str(args.startup_limit),
                      "--timeout", str(args.startup_limit + args.sweep_seconds + 20), "--out", str(out / "sweep.json")],
            "copy": [py, "benchmarks/bench_obs_copy.py", "--timing", "--out", str(out / "device_copy.json")],
            "suite": pytest + [*args.suite, "--ignore=tests/registry", "--ignore=tests/docs", "--ignore=tests/gpu",
                               f"--junitxml={out / 'suite.xml'}"]
            + (["-n", str(args.workers), "--dist", "worksteal"] if args.workers > 1 and _has(py, env, "xdist") else []),
            "gpu": pytest + ["tests/gpu", f"--junitxml={out / 'gpu.xml'}"],
            "ceilings": [py, "benchmarks/bench_ceilings.py", "--n", *map(str, args.sweep_n), "--seconds", "3",
                         "--rounds", "2", "--budget", str(max(limit - 45, 10)), "--out", str(out / "ceilings.json")],
        }.get(name)  # fmt: skip
        if cmd is None:
            stages[name] = {"status": "failed", "note": "unknown stage (sweep copy suite gpu ceilings)"}
            continue
        log(f"stage {name} (limit {limit:.0f}s): {' '.join(cmd)}")
        st, rc, s = run(cmd, limit, env)
        stages[name] = {"status": st, "exit_code": rc, "wall_s": s, "limit_s": round(limit)}
        if name == "sweep":
            stages[name].update(sweep_summary(out / "sweep.json"))
            if st == "passed" and stages[name].get("not_measured"):
                stages[name].update(status="failed", note="runs without a result (not_measured)")
        elif name == "copy" and st != "passed" and "--timing" in run.output and "unrecognized" in run.output:
            stages[name].update(status="skipped", note="bench_obs_copy.py has no --timing mode yet")
        elif name == "copy" and (out / "device_copy.json").exists():
            stages[name]["result"] = json.loads((out / "device_copy.json").read_text())
        elif name == "ceilings" and (out / "ceilings.json").exists():
            ceilings = json.loads((out / "ceilings.json").read_text())
            stages[name]["result"] = {k: ceilings.get(k) for k in ("topology", "summary", "stopped")}
        elif name in ("suite", "gpu"):
            stages[name].update(junit(out / f"{name}.xml"))
        log(f"stage {name}: {stages[name]['status']} (exit {rc}) in {s}s")
    return finish(0)


def _has(py: str, env: dict, module: str) -> bool:
    return subprocess.run([py, "-c", f"import {module}"], env=env, capture_output=True).returncode == 0


def physx_library(args, env: dict) -> str | None:
    """None when SAPIEN's PhysX GPU library is there (or carried in .gpu/physx), else why not."""
    res = subprocess.run([args.python, "-c", "import sapien.physx as p; print(p.version())"], env=env,
                         capture_output=True, text=True)  # fmt: skip
    target = Path.home() / ".sapien" / "physx" / res.stdout.strip() / "libPhysXGpu_64.so"
    if not target.exists() and (ROOT / ".gpu/physx/libPhysXGpu_64.so").exists() and res.stdout.strip():
        shutil.copytree(ROOT / ".gpu/physx", target.parent, dirs_exist_ok=True)
    if target.exists():
        return None
    return f"no PhysX GPU library ({target}); SAPIEN cannot download it without internet: GPU-sim stages skipped"


def machine() -> dict:
    m = {"host": platform.node(), "cores": os.cpu_count(), "python": sys.version.split()[0]}
    try:
        m["cpu"] = next(x.split(":", 1)[1].strip() for x in open("/proc/cpuinfo") if x.startswith("model name"))
    except (OSError, StopIteration):
        pass
    if shutil.which("nvidia-smi"):
        q = ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"]
        m["gpu"] = subprocess.run(q, capture_output=True, text=True).stdout.strip()
    return m


if __name__ == "__main__":
    sys.exit(main())
