#!/usr/bin/env bash
# The one command to run on the accelerator machine (device tool `run`, carry [".gpu/kit"]):
# installs the GPU kit, checks the torchrl / tensordict C++ extensions against the machine's
# torch, runs tests/gpu and benchmarks/bench_gpu.py, and writes logs and a JSON summary.
#
#   bash scripts/gpu_check.sh [OUT_DIR]       # OUT_DIR defaults to $OUT, else outputs/gpu-check
#   bash scripts/gpu_check.sh --install-only  # a multi-part kit: install the carried part, stop
#
# Run from the repository root (the device tool does), as root, with the kit built by
# `make gpu-kit` carried (.gpu/kit, plus .gpu/kit2... if the kit ever needs several parts:
# carry and install those first, one `run` each, with --install-only, back to back while
# the machine is warm). Exact `run` invocation: benchmarks/README.md, "GPU kit".
#
# Steps (each logged; the run goes on after a failed step and reports it):
#   1. Vulkan: unpacks .gpu/kit/gl/*.deb to / if the machine has no libvulkan.so.1 (the
#      device README's recipe), libX11 into a private folder if it lacks one, and points
#      the Vulkan / EGL loaders at the NVIDIA driver's ICD files if they are not found;
#   2. installs every carried part: pip install --no-index --no-deps --target $SITE;
#   2b. the GPU sim's PhysX library: installs .gpu/physx if carried; without it (SAPIEN's
#      download needs internet) steps 4 and 5 are skipped and summary.json says why;
#   3. extensions: tensordict._C and torchrl._torchrl against this torch (what to do if not);
#   4. python -m pytest tests/gpu   (time limit GPU_CHECK_TEST_S, default 240 s);
#   5. python benchmarks/bench_gpu.py (time limit GPU_CHECK_BENCH_S, default 170 s);
#   6. summary.json: machine, versions, install and extension results, test counts,
#      benchmark medians and ratios, wall times.
# Files in OUT_DIR (at most 8, as the device tool brings back): gpu_check.log, tests.log,
# tests.xml, bench.log, bench.json, summary.json.
#
# Knobs: GPU_CHECK_SITE (default /tmp/maniskill_torchrl-gpu-site), GPU_CHECK_TEST_S,
#        GPU_CHECK_BENCH_S, GPU_CHECK_PER_TEST_S (150, with pytest-timeout),
#        GPU_CHECK_PYTEST_ARGS (extra pytest arguments),
#        GPU_CHECK_BENCH_ARGS (extra bench_gpu.py arguments), PYTHON (default python3).
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
T0=$(date +%s)

INSTALL_ONLY=0
OUT_DIR=""
for arg in "$@"; do
    case "$arg" in
        --install-only) INSTALL_ONLY=1 ;;
        -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit 0 ;;
        *) OUT_DIR="$arg" ;;
    esac
done
OUT_DIR="${OUT_DIR:-${OUT:-outputs/gpu-check}}"
mkdir -p "$OUT_DIR"
OUT_DIR="$(cd "$OUT_DIR" && pwd)"
PY="${PYTHON:-python3}"
SITE="${GPU_CHECK_SITE:-/tmp/maniskill_torchrl-gpu-site}"
export PYTHONUNBUFFERED=1 RL_WARNINGS=0

log() { echo "gpu-check [$(($(date +%s) - T0))s]: $*"; }

main() {

log "repo $(pwd) at $(git rev-parse --short HEAD 2>/dev/null || echo '?'), out $OUT_DIR, site $SITE"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null |
    sed 's/^/gpu-check: GPU: /' || log "nvidia-smi not found"

parts=()
for p in .gpu/kit .gpu/kit[0-9]*; do [[ -d "$p/wheels" ]] && parts+=("$p"); done
if ((${#parts[@]} == 0)); then
    log "ERROR: no kit carried: build it with 'make gpu-kit' and name .gpu/kit in the run's carry"
    return 2
fi

# ------------------------------------------------------------ 1. Vulkan / X11
if [[ -d .gpu/kit/gl ]] && ! ldconfig -p 2>/dev/null | grep -q 'libvulkan\.so\.1 '; then
    if [[ $(id -u) == 0 ]]; then
        log "no libvulkan.so.1: unpacking .gpu/kit/gl/*.deb to /"
        for f in .gpu/kit/gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
    else
        log "no libvulkan.so.1 and not root: unpacking .gpu/kit/gl/*.deb to /tmp/maniskill_torchrl-gl"
        for f in .gpu/kit/gl/*.deb; do dpkg -x "$f" /tmp/maniskill_torchrl-gl; done
        export LD_LIBRARY_PATH="/tmp/maniskill_torchrl-gl/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    fi
fi
if [[ -d .gpu/kit/x11 ]] && ! ldconfig -p 2>/dev/null | grep -q 'libX11\.so\.6 '; then
    # Not to /: the device README warns that other packages unpacked there can break it.
    log "no libX11.so.6 (SAPIEN's renderer links it): unpacking .gpu/kit/x11/*.deb to /tmp/maniskill_torchrl-x11"
    for f in .gpu/kit/x11/*.deb; do dpkg -x "$f" /tmp/maniskill_torchrl-x11; done
    export LD_LIBRARY_PATH="/tmp/maniskill_torchrl-x11/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi
icd=""
for f in /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json; do [[ -f "$f" ]] && icd="$f"; done
if [[ -z "$icd" && -z "${VK_ICD_FILENAMES:-}" && -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]]; then
    log "NVIDIA Vulkan ICD from /usr/local/nvidia (device README)"
    export VK_ICD_FILENAMES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    export VK_DRIVER_FILES=$VK_ICD_FILENAMES
    [[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ]] &&
        export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
fi

# ------------------------------------------------------------------ 2. install
install_s=0
t=$(date +%s)
for part in "${parts[@]}"; do
    stamp="$SITE/.installed-$(basename "$part")-$(ls "$part"/wheels | sha256sum | cut -c1-16)"
    if [[ -f "$stamp" ]]; then
        log "$part already installed in $SITE (warm machine)"
        continue
    fi
    log "installing $part ($(ls "$part"/wheels/*.whl | wc -l) wheels) into $SITE"
    if ! "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target "$SITE" "$part"/wheels/*.whl >"$OUT_DIR/.pip.log" 2>&1; then
        cat "$OUT_DIR/.pip.log"
        log "ERROR: pip install of $part failed"
        return 1
    fi
    grep -v "WARNING: Target directory" "$OUT_DIR/.pip.log" || true
    rm -f "$OUT_DIR/.pip.log"
    touch "$stamp"
done
install_s=$(($(date +%s) - t))
export PYTHONPATH="$SITE:$(pwd)${PYTHONPATH:+:$PYTHONPATH}"
log "installed in ${install_s}s; PYTHONPATH=$PYTHONPATH"
if [[ $INSTALL_ONLY == 1 ]]; then
    log "--install-only: done"
    return 0
fi

# ------------------------------------------------------- 2b. PhysX GPU library
# SAPIEN downloads it on the GPU sim's first use, which fails on a machine without internet:
# install the kit's copy (.gpu/physx, made by gpu_kit.sh when the building machine has it),
# else skip the GPU-sim steps with the reason instead of failing every test on the download.
physx_ver="$("$PY" -c 'import sapien.physx as p; print(p.version())' 2>/dev/null)"
physx_dir="$HOME/.sapien/physx/$physx_ver"
if [[ ! -f "$physx_dir/libPhysXGpu_64.so" && -f .gpu/physx/libPhysXGpu_64.so ]]; then
    mkdir -p "$physx_dir" && cp .gpu/physx/* "$physx_dir/" && log "PhysX GPU library installed from .gpu/physx"
fi
physx_ok=1
if [[ ! -f "$physx_dir/libPhysXGpu_64.so" ]] &&
        ! timeout 60 "$PY" -c 'from maniskill_torchrl._maniskill import enable_physx_gpu; enable_physx_gpu()' \
            >"$OUT_DIR/.physx.log" 2>&1; then
    physx_ok=0
    tail -3 "$OUT_DIR/.physx.log"
    log "ERROR: no PhysX GPU library ($physx_dir/libPhysXGpu_64.so) and it cannot be downloaded here:"
    log "       the GPU-sim tests and benchmark are skipped. Put it on the kit-building machine and rerun"
    log "       make gpu-kit (scripts/gpu_kit.sh says where), then carry .gpu/physx as well."
fi
rm -f "$OUT_DIR/.physx.log"

# ---------------------------------------------------------------- 3. extensions
log "versions and C++ extensions"
"$PY" - "$OUT_DIR/.ext.json" <<'EOF'
import json, sys, warnings
warnings.filterwarnings("ignore")
out = {}
import torch
out["torch"] = torch.__version__
out["cuda_available"] = torch.cuda.is_available()
out["gpu"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
for mod in ("tensordict", "torchrl", "gymnasium", "sapien", "mani_skill", "numpy"):
    try:
        m = __import__(mod)
        out[mod] = getattr(m, "__version__", "?")
        out[mod + "_from"] = m.__file__
    except Exception as e:  # noqa: BLE001
        out[mod] = f"IMPORT FAILED: {type(e).__name__}: {e}"
try:
    import tensordict._C  # noqa: F401  (pybind11, links no libtorch: should always load)
    out["tensordict_C"] = "ok"
except Exception as e:  # noqa: BLE001
    out["tensordict_C"] = f"{type(e).__name__}: {e}"
try:
    import torchrl._torchrl  # noqa: F401  (links libtorch: needs the torch it was built against)
    out["torchrl_C"] = "ok"
except Exception as e:  # noqa: BLE001
    out["torchrl_C"] = f"{type(e).__name__}: {str(e)[:400]}"
# What needs torchrl's C++ extension: the segment trees of prioritized sampling.
try:
    from torchrl.data import LazyTensorStorage, PrioritizedReplayBuffer
    PrioritizedReplayBuffer(alpha=0.7, beta=0.5, storage=LazyTensorStorage(8))
    out["prioritized_replay_buffer"] = "ok"
except Exception as e:  # noqa: BLE001
    out["prioritized_replay_buffer"] = f"{type(e).__name__}: {str(e)[:200]}"
# What the library and its PPO example use works without it.
try:
    from tensordict import TensorDict
    from torchrl.data import ReplayBuffer
    from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
    rb = ReplayBuffer(storage=LazyTensorStorage(8), sampler=SamplerWithoutReplacement(), batch_size=4)
    rb.extend(TensorDict(x=torch.arange(8.0), batch_size=[8]))
    rb.sample()
    out["sampler_without_replacement"] = "ok"
except Exception as e:  # noqa: BLE001
    out["sampler_without_replacement"] = f"{type(e).__name__}: {e}"
try:
    import sapien
    out["sapien_render_device"] = str(sapien.render.get_device_summary())[:600]
except Exception as e:  # noqa: BLE001
    out["sapien_render_device"] = f"{type(e).__name__}: {e}"
json.dump(out, open(sys.argv[1], "w"), indent=2)
for k, v in out.items():
    print(f"  {k:30s} {v}")
if out["torchrl_C"] != "ok":
    print(
        "\n  torchrl's C++ extension does not load against torch " + out["torch"] + ".\n"
        "  Only prioritized replay (PrioritizedReplayBuffer / PrioritizedSampler: its segment trees) needs it;\n"
        "  ManiSkillEnv, the transforms, Collector, GAE, ClipPPOLoss and SamplerWithoutReplacement work without it,\n"
        "  so the GPU checks go on. To get it: carry a torchrl wheel built against this torch (build it on this\n"
        "  machine from the torchrl 0.14.1 sdist with `pip wheel --no-build-isolation --no-deps`: it has nvcc,\n"
        "  cmake and ninja), or pair torchrl with the torch it was built for."
    )
if out["tensordict_C"] != "ok":
    print("\n  tensordict's C++ extension does not load: tensordict cannot work; check the cp312 wheel in .gpu/kit.")
EOF
ext_rc=$?
((ext_rc == 0)) || log "the version / extension probe failed (exit $ext_rc)"

test_rc=3 test_s=0 bench_rc=3 bench_s=0  # 3: not run (no PhysX GPU library)
if ((physx_ok)); then
# ---------------------------------------------------------------------- 4. tests
log "pytest tests/gpu (limit ${GPU_CHECK_TEST_S:-240}s)"
t=$(date +%s)
per_test=()
# pytest-timeout (there on the machine) stops one hung test and keeps the junit report.
"$PY" -c "import pytest_timeout" 2>/dev/null && per_test=(--timeout "${GPU_CHECK_PER_TEST_S:-150}")
# shellcheck disable=SC2086
timeout -k 10 "${GPU_CHECK_TEST_S:-240}" "$PY" -m pytest tests/gpu -q -rA -p no:cacheprovider "${per_test[@]}" \
    -o junit_family=xunit1 --junitxml="$OUT_DIR/tests.xml" ${GPU_CHECK_PYTEST_ARGS:-} 2>&1 | tee "$OUT_DIR/tests.log"
test_rc=${PIPESTATUS[0]}
test_s=$(($(date +%s) - t))
log "tests: exit $test_rc in ${test_s}s"

# ---------------------------------------------------------------------- 5. bench
log "benchmarks/bench_gpu.py (limit ${GPU_CHECK_BENCH_S:-170}s)"
t=$(date +%s)
# shellcheck disable=SC2086
timeout -k 10 "${GPU_CHECK_BENCH_S:-170}" "$PY" benchmarks/bench_gpu.py --out "$OUT_DIR/bench.json" \
    ${GPU_CHECK_BENCH_ARGS:-} 2>&1 | tee "$OUT_DIR/bench.log"
bench_rc=${PIPESTATUS[0]}
bench_s=$(($(date +%s) - t))
log "bench: exit $bench_rc in ${bench_s}s"

fi
# -------------------------------------------------------------------- 6. summary
"$PY" - "$OUT_DIR" "$install_s" "$test_rc" "$test_s" "$bench_rc" "$bench_s" "$(($(date +%s) - T0))" "${parts[*]}" "$physx_ok" <<'EOF'
import datetime, json, os, subprocess, sys
import xml.etree.ElementTree as ET

out_dir, install_s, test_rc, test_s, bench_rc, bench_s, total_s, parts, physx_ok = sys.argv[1:10]
summary = {
    "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    "kit_parts": parts.split(),
    "physx_gpu_library": "ok" if physx_ok == "1" else "missing: the GPU-sim tests and benchmark did not run",
    "wall_s": {"install": int(install_s), "tests": int(test_s), "bench": int(bench_s), "total": int(total_s)},
}
try:
    summary["commit"] = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    summary["nvidia_smi"] = subprocess.run(
        ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
        capture_output=True, text=True).stdout.strip()
except OSError:
    pass
try:
    summary["environment"] = json.load(open(os.path.join(out_dir, ".ext.json")))
except (OSError, ValueError):
    summary["environment"] = None
tests = {"exit_code": int(test_rc)}
try:
    root = ET.parse(os.path.join(out_dir, "tests.xml")).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    for k in ("tests", "failures", "errors", "skipped"):
        tests[k] = int(suite.get(k, 0))
    tests["passed"] = tests["tests"] - tests["failures"] - tests["errors"] - tests["skipped"]
    cases = {}
    for case in suite.iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        state = "passed"
        for tag in ("failure", "error", "skipped"):
            if case.find(tag) is not None:
                state = tag
        props = {p.get("name"): p.get("value") for p in case.iter("property")}
        cases[name] = {"state": state, "time_s": float(case.get("time", 0)), **({"properties": props} if props else {})}
    tests["cases"] = cases
except (OSError, ET.ParseError, AttributeError) as e:
    tests["junit"] = f"unreadable: {e}"
summary["tests"] = tests
bench = {"exit_code": int(bench_rc)}
try:
    b = json.load(open(os.path.join(out_dir, "bench.json")))
    bench.update({k: b[k] for k in ("gpu", "summary", "skipped", "targets", "complete") if k in b})
except (OSError, ValueError):
    bench["json"] = "missing"
summary["bench"] = bench
summary["ok"] = tests["exit_code"] == 0 and bench["exit_code"] == 0
json.dump(summary, open(os.path.join(out_dir, "summary.json"), "w"), indent=2)
print(json.dumps({k: summary[k] for k in ("ok", "wall_s")}, indent=None))
print("tests:", {k: v for k, v in tests.items() if k != "cases"})
print("bench:", json.dumps(bench.get("summary", bench), indent=1)[:3000])
EOF
rm -f "$OUT_DIR/.ext.json"
log "done in $(($(date +%s) - T0))s: tests exit $test_rc, bench exit $bench_rc; files in $OUT_DIR"
[[ $test_rc == 0 && $bench_rc == 0 ]]
}

main 2>&1 | tee -a "$OUT_DIR/gpu_check.log"
exit "${PIPESTATUS[0]}"
