#!/usr/bin/env bash
# The one check to run on the accelerator machine (device tool `run`): installs the GPU kit and
# runs, as stages, the whole CPU suite, tests/gpu, the demo, the example smoke runs and a
# collection sweep; writes logs and $OUT/summary.json. The exact calls: benchmarks/README.md, "GPU kit".
#
#   bash scripts/gpu_check.sh [OUT_DIR]       # OUT_DIR defaults to $OUT, else outputs/gpu-check
#   bash scripts/gpu_check.sh --install-only  # install the carried part(s) of the kit, stop
#   GPU_CHECK_LOCAL=1 bash scripts/gpu_check.sh   # a dry run here, without the kit (below)
#
# Run from the repository root (the device tool does), as root. The kit (`make gpu-kit`) has two
# parts: carry .gpu/kit2 in a first call with --install-only, then .gpu/kit in the call that runs
# the check, back to back while the machine is warm (it stays so for about 30 s). The check stops
# at once, before any stage, if a part of the kit is not installed (a machine that went back
# between the calls): run both calls again.
#
# Set-up (logged; a failed install stops the run):
#   1. Vulkan: unpacks .gpu/kit/gl/*.deb to / if the machine has no libvulkan.so.1 (the device
#      README's recipe), libX11 into a private folder if it lacks one, and points the Vulkan /
#      EGL loaders at the NVIDIA driver's ICD files if they are not found;
#   2. installs every carried part: its wheels with pip install --no-index --no-deps --target
#      $SITE, and this project's wheel (maniskill_torchrl-*.whl) into the machine's Python itself,
#      so that the maniskill-torchrl console script lies beside python3 as the suite expects;
#   3. the GPU sim's PhysX library: installs .gpu/physx if carried; without it (SAPIEN's download
#      needs internet) the stages gpu and bench are skipped and summary.json says why;
#   4. versions and the tensordict / torchrl C++ extensions against this torch.
# Stages (GPU_CHECK_STAGES, in this order; each has its own time limit, and all of them end
# before GPU_CHECK_DEADLINE_S seconds from the start, so that the summary is written inside the
# device tool's 600 s per command: a stage that would start too late is skipped and says so;
# a stage that fails does not stop the others):
#   suite  the CPU suite, pytest-xdist on the machine's cores (-n cores-2): tests/ without
#          tests/registry, tests/docs and tests/gpu (GPU_CHECK_SUITE_S, 330 s; 196 s with 14
#          workers on a 16-core H200 machine, 2026-11-26);
#   gpu    pytest tests/gpu (GPU_CHECK_TEST_S, 240 s), skipped without the PhysX GPU library;
#   demo   the maniskill-torchrl console script's demo, 400 frames with a video (GPU_CHECK_DEMO_S, 90 s);
#   smoke  examples/ppo_torchrl.py and sac_torchrl.py --smoke, and both again with
#          --sim-backend cpu --device cuda (the CPU sim feeding a GPU learner; skipped without
#          CUDA), the four side by side (GPU_CHECK_SMOKE_S, 150 s);
#   sweep  benchmarks/bench_collection.py: the batched CPU env against gymnasium's AsyncVectorEnv
#          of ManiSkill's CPUGymWrapper, PickCube-v1 state, N = 1 4 8 15, one round of 3 s each
#          (GPU_CHECK_SWEEP_S, 150 s);
#   bench  benchmarks/bench_gpu.py (GPU_CHECK_BENCH_S, 170 s), only when named in GPU_CHECK_STAGES,
#          and skipped without the PhysX GPU library.
# Expected on a 16-core machine without the PhysX library: about 30 s of set-up, then suite ~200 s,
# demo ~30 s, smoke ~45 s, sweep ~100 s: about 7 minutes.
#
# Files in OUT_DIR (at most 8 come back from the device tool): summary.json (per stage: status,
# exit code, wall time, limit; the suite's and tests/gpu's pass / fail / skip counts, failed tests
# and skip reasons; the smoke runs; the sweep's frames/s, ratios and scaling; the machine),
# gpu_check.log (everything printed), suite.xml and gpu.xml (junit), sweep.json, bench.json.
# Exit status: 0 when no stage failed (skipped stages do not count), 1 otherwise, 2 without a kit
# (or a part of it not installed); summary.json is written in every case.
#
# Knobs: GPU_CHECK_STAGES ("suite gpu demo smoke sweep"), GPU_CHECK_DEADLINE_S (560),
#        GPU_CHECK_SITE (/tmp/maniskill_torchrl-gpu-site), PYTHON (python3),
#        GPU_CHECK_SUITE_S, GPU_CHECK_SUITE_WORKERS (cores - 2), GPU_CHECK_SUITE_ARGS (extra pytest
#        arguments), GPU_CHECK_PER_TEST_S (300) and GPU_CHECK_GPU_PER_TEST_S (150, tests/gpu): per test,
#        with pytest-timeout,
#        GPU_CHECK_TEST_S,
#        GPU_CHECK_PYTEST_ARGS (tests/gpu), GPU_CHECK_DEMO_S, GPU_CHECK_SMOKE_S, GPU_CHECK_SWEEP_S,
#        GPU_CHECK_SWEEP_N ("1 4 8 15"), GPU_CHECK_SWEEP_SECONDS (3), GPU_CHECK_BENCH_S,
#        GPU_CHECK_BENCH_ARGS, GPU_CHECK_INSTALL (1; 0: no kit, the current Python as it is).
#        GPU_CHECK_LOCAL=1: a dry run of the script on a machine without the kit (this one):
#        GPU_CHECK_INSTALL=0, PYTHON=.venv/bin/python, 2 suite workers, the sweep at N = 1 2 for
#        1 s, no deadline (3600 s); any knob set explicitly wins.
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
if [[ "${GPU_CHECK_LOCAL:-0}" == 1 ]]; then
    : "${GPU_CHECK_INSTALL:=0}" "${GPU_CHECK_SUITE_WORKERS:=2}" "${GPU_CHECK_SWEEP_N:=1 2}"
    : "${GPU_CHECK_SWEEP_SECONDS:=1}" "${GPU_CHECK_DEADLINE_S:=3600}" "${GPU_CHECK_SUITE_S:=2400}"
    : "${GPU_CHECK_SWEEP_S:=600}" "${GPU_CHECK_SMOKE_S:=300}" "${GPU_CHECK_DEMO_S:=180}"
    [[ -z "${PYTHON:-}" && -x .venv/bin/python ]] && PYTHON=.venv/bin/python
fi
OUT_DIR="${OUT_DIR:-${OUT:-outputs/gpu-check}}"
mkdir -p "$OUT_DIR"
OUT_DIR="$(cd "$OUT_DIR" && pwd)"
PY="${PYTHON:-python3}"
SITE="${GPU_CHECK_SITE:-/tmp/maniskill_torchrl-gpu-site}"
INSTALL="${GPU_CHECK_INSTALL:-1}"
STAGES="${GPU_CHECK_STAGES-suite gpu demo smoke sweep}"  # set but empty: set-up only
DEADLINE_S="${GPU_CHECK_DEADLINE_S:-560}"
WORK="$(mktemp -d /tmp/maniskill_torchrl-gpu-check.XXXXXX)"  # the demo's and smoke runs' outputs
export PYTHONUNBUFFERED=1 RL_WARNINGS=0
STAGES_TSV="$OUT_DIR/.stages.tsv"
: >"$STAGES_TSV"

log() { echo "gpu-check [$(($(date +%s) - T0))s]: $*"; }
# record NAME STATUS RC WALL_S LIMIT_S NOTE: one line of the summary's stages
record() { printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$1" "$2" "$3" "$4" "$5" "${6:-}" >>"$STAGES_TSV"; }
# early_summary MESSAGE: summary.json of a run that stopped before its stages
early_summary() {
    "$PY" - "$OUT_DIR/summary.json" "$1" "$(($(date +%s) - T0))" <<'PYEOF' || true
import datetime, json, sys
json.dump({"date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "ok": False, "error": sys.argv[2], "failed_stages": ["setup"], "wall_s": {"total": int(sys.argv[3])}},
          open(sys.argv[1], "w"), indent=2)
PYEOF
}

# run_stage NAME LIMIT_S COMMAND...: runs COMMAND under `timeout` (its whole process group), its
# limit cut to what is left before the deadline; records passed / failed / timed_out, or skipped
# when less than a minute would be left.
run_stage() {
    local name="$1" limit="$2"; shift 2
    local left=$((DEADLINE_S - ($(date +%s) - T0) - 15))
    if ((left < 60)); then
        log "stage $name: SKIPPED, ${left}s left before the ${DEADLINE_S}s deadline"
        record "$name" skipped "" 0 "$limit" "not started: ${left}s left before the ${DEADLINE_S}s deadline"
        return 0
    fi
    ((limit > left)) && limit=$left
    log "stage $name (limit ${limit}s): $*"
    local t rc status
    t=$(date +%s)
    timeout -k 10 "$limit" "$@"
    rc=$?
    t=$(($(date +%s) - t))
    case $rc in
        0) status=passed ;;
        124|137) status=timed_out ;;
        *) status=failed ;;
    esac
    log "stage $name: $status (exit $rc) in ${t}s"
    record "$name" "$status" "$rc" "$t" "$limit" "${STAGE_NOTE:-}"
    STAGE_NOTE=""
}

# ------------------------------------------------------------------- stage bodies
# Run under `timeout` through `bash -c` (exported below).
stage_demo() {
    local bin
    bin="$(dirname "$("$PY" -c 'import sys; print(sys.executable)')")/maniskill-torchrl"
    if [[ ! -x "$bin" ]]; then
        echo "gpu-check: demo: no console script at $bin (the project's wheel is not installed in $PY's environment)"
        return 1
    fi
    "$bin" demo --frames 400 --workers 2 --video-steps 8 --video-size 64 --out "$WORK/demo" --no-progress || return
    local f
    for f in rollout.mp4 returns.png summary.json; do
        [[ -s "$WORK/demo/$f" ]] || { echo "gpu-check: demo: $f missing or empty"; return 1; }
    done
    echo "gpu-check: demo: rollout.mp4 ($(stat -c %s "$WORK/demo/rollout.mp4") bytes), returns.png, summary.json written"
}

stage_smoke() {  # the example smoke runs side by side; one line per run in $OUT_DIR/.smoke.tsv
    local names=(ppo sac)
    local cmds=(
        "$PY examples/ppo_torchrl.py --smoke --out $WORK/ppo"
        "$PY examples/sac_torchrl.py --smoke --out $WORK/sac"
    )
    : >"$OUT_DIR/.smoke.tsv"
    if [[ "$CUDA" == 1 ]]; then
        names+=(ppo_cpu_sim_cuda_learner sac_cpu_sim_cuda_learner)
        cmds+=(
            "$PY examples/ppo_torchrl.py --smoke --sim-backend cpu --device cuda --out $WORK/ppo-cuda"
            "$PY examples/sac_torchrl.py --smoke --sim-backend cpu --device cuda --out $WORK/sac-cuda"
        )
    else
        local n
        for n in ppo_cpu_sim_cuda_learner sac_cpu_sim_cuda_learner; do
            printf '%s\tskipped\t\t0\t\tno CUDA on this machine\n' "$n" >>"$OUT_DIR/.smoke.tsv"
        done
    fi
    local i pids=() fail=0
    for i in "${!names[@]}"; do
        (
            s=$(date +%s)
            bash -c "${cmds[$i]}" >"$WORK/smoke-${names[$i]}.log" 2>&1
            rc=$?
            st=passed
            ((rc == 0)) || st=failed
            printf '%s\t%s\t%s\t%s\t%s\n' "${names[$i]}" "$st" "$rc" "$(($(date +%s) - s))" "${cmds[$i]}" \
                >>"$OUT_DIR/.smoke.tsv"
            exit "$rc"
        ) &
        pids+=($!)
    done
    for i in "${!pids[@]}"; do wait "${pids[$i]}" || fail=1; done
    return "$fail"
}

main() {

log "repo $(pwd) at $(git rev-parse --short HEAD 2>/dev/null || echo '?'), out $OUT_DIR, stages: $STAGES"
log "python $PY, $(nproc) cores, deadline ${DEADLINE_S}s"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null |
    sed 's/^/gpu-check: GPU: /' || log "nvidia-smi not found"

parts=()
install_s=0
if [[ "$INSTALL" == 1 ]]; then
    for p in .gpu/kit .gpu/kit[0-9]*; do [[ -d "$p/wheels" ]] && parts+=("$p"); done
    if ((${#parts[@]} == 0)); then
        log "ERROR: no kit carried: build it with 'make gpu-kit' and name .gpu/kit (or .gpu/kit2) in the run's carry"
        early_summary "no kit carried (.gpu/kit*/wheels)"
        return 2
    fi

    # -------------------------------------------------------- 1. Vulkan / X11
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

    # -------------------------------------------------------------- 2. install
    t=$(date +%s)
    mkdir -p "$SITE"
    for part in "${parts[@]}"; do
        stamp="$SITE/.installed-$(basename "$part")-$(ls "$part"/wheels | sha256sum | cut -c1-16)"
        if [[ -f "$stamp" ]]; then
            log "$part already installed in $SITE (warm machine)"
            continue
        fi
        deps=() project=()
        for w in "$part"/wheels/*.whl; do
            case "$(basename "$w")" in maniskill_torchrl-*) project+=("$w") ;; *) deps+=("$w") ;; esac
        done
        log "installing $part (${#deps[@]} wheels) into $SITE"
        if ((${#deps[@]})) && ! "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
                --target "$SITE" "${deps[@]}" >"$OUT_DIR/.pip.log" 2>&1; then
            cat "$OUT_DIR/.pip.log"
            log "ERROR: pip install of $part failed"
            early_summary "pip install of $part failed (gpu_check.log)"
            return 1
        fi
        grep -v "WARNING: Target directory" "$OUT_DIR/.pip.log" 2>/dev/null || true
        if ((${#project[@]})); then
            # Into the Python's own environment: its console script then lies beside python3. The suite
            # imports the repository's copy (PYTHONPATH), so a wheel built from an older tree is harmless.
            log "installing ${project[*]##*/} into $PY's environment (the maniskill-torchrl console script)"
            "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --force-reinstall \
                "${project[@]}" >"$OUT_DIR/.pip.log" 2>&1 ||
                { cat "$OUT_DIR/.pip.log"; log "WARNING: the project's wheel did not install: the demo stage will fail"; }
        fi
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
    # Every part of the kit must be installed by now (.gpu/kit*/PARTS.txt names them all).
    missing=()
    while read -r name hash; do
        [[ -f "$SITE/.installed-$name-$hash" ]] || missing+=(".gpu/$name")
    done < <(cat "${parts[0]}/PARTS.txt" 2>/dev/null)
    if ((${#missing[@]})); then
        log "ERROR: ${missing[*]} not installed on this machine: it was given back between the calls (they must"
        log "       follow each other within ~30 s). Run the calls of benchmarks/README.md, 'GPU kit', again."
        early_summary "kit parts not installed: ${missing[*]} (the machine was given back between the calls)"
        return 2
    fi
else
    export PYTHONPATH="$(pwd)${PYTHONPATH:+:$PYTHONPATH}"
    log "GPU_CHECK_INSTALL=0: no kit, $PY as it is; PYTHONPATH=$PYTHONPATH"
    [[ $INSTALL_ONLY == 1 ]] && return 0
fi

# ------------------------------------------------------- 3. PhysX GPU library
# SAPIEN downloads it on the GPU sim's first use, which fails on a machine without internet:
# install the kit's copy (.gpu/physx, made by gpu_kit.sh when the building machine has it),
# else skip the GPU-sim stages with the reason instead of failing every test on the download.
physx_ver="$("$PY" -c 'import sapien.physx as p; print(p.version())' 2>/dev/null)"
physx_dir="$HOME/.sapien/physx/$physx_ver"
if [[ ! -f "$physx_dir/libPhysXGpu_64.so" && -f .gpu/physx/libPhysXGpu_64.so ]]; then
    mkdir -p "$physx_dir" && cp .gpu/physx/* "$physx_dir/" && log "PhysX GPU library installed from .gpu/physx"
fi
physx_ok=1
physx_reason=""
if [[ ! -f "$physx_dir/libPhysXGpu_64.so" ]] &&
        ! timeout 60 "$PY" -c 'from maniskill_torchrl._maniskill import enable_physx_gpu; enable_physx_gpu()' \
            >"$OUT_DIR/.physx.log" 2>&1; then
    physx_ok=0
    physx_reason="no PhysX GPU library ($physx_dir/libPhysXGpu_64.so), and SAPIEN cannot download it here: $(tail -1 "$OUT_DIR/.physx.log" | cut -c1-300)"
    tail -3 "$OUT_DIR/.physx.log"
    log "no PhysX GPU library ($physx_dir/libPhysXGpu_64.so) and it cannot be downloaded here:"
    log "       the stages gpu and bench are skipped. Put it on the kit-building machine and rerun"
    log "       make gpu-kit (scripts/gpu_kit.sh says where), then carry .gpu/physx as well."
fi
rm -f "$OUT_DIR/.physx.log"

# ---------------------------------------------------------------- 4. extensions
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
CUDA="$("$PY" -c 'import torch; print(int(torch.cuda.is_available()))' 2>/dev/null || echo 0)"
setup_s=$(($(date +%s) - T0))
export PY WORK OUT_DIR CUDA
export -f stage_demo stage_smoke

# ---------------------------------------------------------------------- stages
for stage in $STAGES; do
    case "$stage" in
    suite)
        workers="${GPU_CHECK_SUITE_WORKERS:-$(($(nproc) - 2))}"
        ((workers < 1)) && workers=1
        xdist=() per_test=()
        if "$PY" -c "import xdist" 2>/dev/null; then
            xdist=(-n "$workers")
        else
            STAGE_NOTE="pytest-xdist missing: one process"
            log "pytest-xdist is not installed: the suite runs in one process"
        fi
        # pytest-timeout (there on the machine) stops one hung test and keeps the junit report.
        "$PY" -c "import pytest_timeout" 2>/dev/null && per_test=(--timeout "${GPU_CHECK_PER_TEST_S:-300}")
        # shellcheck disable=SC2086
        run_stage suite "${GPU_CHECK_SUITE_S:-330}" "$PY" -m pytest tests --ignore=tests/registry \
            --ignore=tests/docs --ignore=tests/gpu -q -rfEs --durations=15 -p no:cacheprovider "${xdist[@]}" \
            "${per_test[@]}" -o junit_family=xunit1 --junitxml="$OUT_DIR/suite.xml" ${GPU_CHECK_SUITE_ARGS:-}
        ;;
    gpu)
        if ((physx_ok)); then
            per_test=()
            "$PY" -c "import pytest_timeout" 2>/dev/null && per_test=(--timeout "${GPU_CHECK_GPU_PER_TEST_S:-150}")
            # shellcheck disable=SC2086
            run_stage gpu "${GPU_CHECK_TEST_S:-240}" "$PY" -m pytest tests/gpu -q -rA -p no:cacheprovider \
                "${per_test[@]}" -o junit_family=xunit1 --junitxml="$OUT_DIR/gpu.xml" ${GPU_CHECK_PYTEST_ARGS:-}
        else
            log "stage gpu: SKIPPED: $physx_reason"
            record gpu skipped "" 0 0 "$physx_reason"
        fi
        ;;
    demo)
        run_stage demo "${GPU_CHECK_DEMO_S:-90}" bash -c stage_demo
        ;;
    smoke)
        run_stage smoke "${GPU_CHECK_SMOKE_S:-150}" bash -c stage_smoke
        for f in "$WORK"/smoke-*.log; do
            [[ -f "$f" ]] || continue
            echo "----- $(basename "$f" .log) (last 25 lines)"
            tail -n 25 "$f"
        done
        ;;
    sweep)
        # shellcheck disable=SC2086
        run_stage sweep "${GPU_CHECK_SWEEP_S:-150}" "$PY" benchmarks/bench_collection.py \
            --n ${GPU_CHECK_SWEEP_N:-1 4 8 15} --repeat 1 --rounds 1 --seconds "${GPU_CHECK_SWEEP_SECONDS:-3}" \
            --pipelines gym batched --max-wait 3 --retries 0 --timeout 90 --out "$OUT_DIR/sweep.json"
        ;;
    bench)
        if ((physx_ok)); then
            # shellcheck disable=SC2086
            run_stage bench "${GPU_CHECK_BENCH_S:-170}" "$PY" benchmarks/bench_gpu.py --out "$OUT_DIR/bench.json" \
                ${GPU_CHECK_BENCH_ARGS:-}
        else
            log "stage bench: SKIPPED: $physx_reason"
            record bench skipped "" 0 0 "$physx_reason"
        fi
        ;;
    *)
        log "unknown stage $stage (known: suite gpu demo smoke sweep bench)"
        record "$stage" failed "" 0 0 "unknown stage"
        ;;
    esac
done

# --------------------------------------------------------------------- summary
"$PY" - "$OUT_DIR" "$setup_s" "$install_s" "$(($(date +%s) - T0))" "${parts[*]:-}" "$physx_ok" "$physx_reason" \
    "$DEADLINE_S" <<'PYEOF'
import datetime, json, os, platform, re, subprocess, sys
import xml.etree.ElementTree as ET

out_dir, setup_s, install_s, total_s, parts, physx_ok, physx_reason, deadline_s = sys.argv[1:9]


def read_tsv(name, fields):
    rows = []
    try:
        with open(os.path.join(out_dir, name)) as f:
            for line in f:
                cells = line.rstrip("\n").split("\t")
                rows.append(dict(zip(fields, cells + [""] * (len(fields) - len(cells)))))
    except OSError:
        pass
    return rows


def junit(path):
    """Counts, failed tests (with the first line of their message) and skip reasons of a junit file."""
    res = {}
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        return {"junit": f"unreadable: {e}"}
    suites = [root] if root.tag == "testsuite" else root.findall("testsuite")
    for k in ("tests", "failures", "errors", "skipped"):
        res[k] = sum(int(s.get(k, 0)) for s in suites)
    res["passed"] = res["tests"] - res["failures"] - res["errors"] - res["skipped"]
    failed, skips, slowest = {}, {}, []
    for case in root.iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        slowest.append((float(case.get("time", 0) or 0), name))
        for tag in ("failure", "error"):
            el = case.find(tag)
            if el is not None:
                message = (el.get("message") or "").strip().splitlines()
                failed[name] = f"{tag}: {message[0][:300] if message else ''}"
        el = case.find("skipped")
        if el is not None:
            reason = (el.get("message") or "").strip()[:200]
            skips[reason] = skips.get(reason, 0) + 1
    res["failed_tests"] = failed
    res["skip_reasons"] = skips
    res["slowest_s"] = {n: round(t, 1) for t, n in sorted(slowest, reverse=True)[:10]}
    return res


def sweep(path):
    try:
        d = json.load(open(path))
    except (OSError, ValueError) as e:
        return {"json": f"missing: {e}"}
    fps, ok = {}, {}
    for name, r in d.get("results", {}).items():
        m = re.match(r"(\S+) N=(\d+) r=(\d+)", name)
        if not m:
            continue
        spec, n = m.group(1), int(m.group(2))
        if r.get("median_s"):
            fps.setdefault(spec, {})[n] = round(1.0 / r["median_s"], 1)
        elif r.get("note") or r.get("failures"):
            ok.setdefault(spec, {})[n] = r.get("note") or f"{r.get('failures')} failures"
    out = {"settings": d.get("settings"), "frames_per_s": fps, "benchmark_s": round(d.get("wall_s", 0), 1)}
    if ok:
        out["not_measured"] = ok
    gym, batched = fps.get("gym", {}), fps.get("batched", {})
    out["ratio_batched_to_gym"] = {n: round(batched[n] / gym[n], 2) for n in sorted(gym) if n in batched}
    # frames/s at N against N times the same pipeline at N = 1 (1.0: linear scaling)
    out["scaling_vs_n_times_n1"] = {
        spec: {n: round(v[n] / (n * v[1]), 2) for n in sorted(v) if n > 1} for spec, v in fps.items() if 1 in v
    }
    out["machine"] = d.get("machine")
    return out


stages = {}
for row in read_tsv(".stages.tsv", ["name", "status", "exit_code", "wall_s", "limit_s", "note"]):
    st = {"status": row["status"], "exit_code": int(row["exit_code"]) if row["exit_code"] else None,
          "wall_s": int(row["wall_s"] or 0), "limit_s": int(row["limit_s"] or 0)}
    if row["note"]:
        st["note"] = row["note"]
    stages[row["name"]] = st
if "suite" in stages:
    stages["suite"].update(junit(os.path.join(out_dir, "suite.xml")))
if "gpu" in stages and stages["gpu"]["status"] != "skipped":
    stages["gpu"].update(junit(os.path.join(out_dir, "gpu.xml")))
if "smoke" in stages:
    runs = {}
    for r in read_tsv(".smoke.tsv", ["name", "status", "exit_code", "wall_s", "command", "note"]):
        runs[r["name"]] = {"status": r["status"], "exit_code": int(r["exit_code"]) if r["exit_code"] else None,
                           "wall_s": int(r["wall_s"] or 0)}
        runs[r["name"]].update({k: r[k] for k in ("command", "note") if r[k]})
    for name in ("ppo", "sac", "ppo_cpu_sim_cuda_learner", "sac_cpu_sim_cuda_learner"):
        runs.setdefault(name, {"status": "killed: the stage's time limit"})
    stages["smoke"]["runs"] = runs
if "sweep" in stages:
    stages["sweep"].update(sweep(os.path.join(out_dir, "sweep.json")))
    # bench_collection.py exits 0 when a run fails: a sweep with a cell left unmeasured failed
    if stages["sweep"]["status"] == "passed" and (stages["sweep"].get("not_measured") or not stages["sweep"].get("frames_per_s")):
        stages["sweep"]["status"] = "failed"
        stages["sweep"]["note"] = "runs without a result (not_measured)"
if "bench" in stages and stages["bench"]["status"] != "skipped":
    try:
        b = json.load(open(os.path.join(out_dir, "bench.json")))
        stages["bench"].update({k: b[k] for k in ("gpu", "summary", "skipped", "targets", "complete") if k in b})
    except (OSError, ValueError):
        stages["bench"]["json"] = "missing"

machine = {"host": platform.node(), "cores": os.cpu_count(), "python": sys.version.split()[0]}
try:
    machine["cpu"] = next(l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name"))
    machine["memory_gib"] = round(int(next(l.split()[1] for l in open("/proc/meminfo") if l.startswith("MemTotal"))) / 2**20, 1)
except (OSError, StopIteration):
    pass
try:
    machine["gpu"] = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total",
                                     "--format=csv,noheader"], capture_output=True, text=True).stdout.strip() or None
except OSError:
    machine["gpu"] = None
summary = {
    "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    "commit": subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip() or None,
    "machine": machine,
    "kit_parts": parts.split(),
    "physx_gpu_library": "ok" if physx_ok == "1" else physx_reason,
    "deadline_s": int(deadline_s),
    "wall_s": {"setup": int(setup_s), "install": int(install_s), "total": int(total_s),
               **{k: v["wall_s"] for k, v in stages.items()}},
}
try:
    summary["environment"] = json.load(open(os.path.join(out_dir, ".ext.json")))
except (OSError, ValueError):
    summary["environment"] = None
summary["stages"] = stages
summary["failed_stages"] = [k for k, v in stages.items() if v["status"] in ("failed", "timed_out")]
summary["skipped_stages"] = {k: v.get("note", "") for k, v in stages.items() if v["status"] == "skipped"}
summary["ok"] = not summary["failed_stages"]
json.dump(summary, open(os.path.join(out_dir, "summary.json"), "w"), indent=2)

print(f"\nsummary ({out_dir}/summary.json): ok={summary['ok']}, wall_s={summary['wall_s']}")
for k, v in stages.items():
    counts = ", ".join(f"{c} {v[c]}" for c in ("passed", "failures", "errors", "skipped") if c in v)
    print(f"  {k:6s} {v['status']:9s} {v['wall_s']:4d}s / {v['limit_s']}s  {counts}  {v.get('note', '')}")
    for t, msg in list(v.get("failed_tests", {}).items())[:40]:
        print(f"           FAILED {t}: {msg[:160]}")
    for name, r in v.get("runs", {}).items():
        print(f"           {name}: {r['status']} {r.get('wall_s', '')}")
    if "frames_per_s" in v:
        print(f"           frames/s {v['frames_per_s']}; batched/gym {v['ratio_batched_to_gym']}; "
              f"scaling {v['scaling_vs_n_times_n1']}")
PYEOF
rm -f "$OUT_DIR/.ext.json" "$OUT_DIR/.stages.tsv" "$OUT_DIR/.smoke.tsv"
rm -rf "$WORK"
failed="$("$PY" -c 'import json, sys; print(" ".join(json.load(open(sys.argv[1]))["failed_stages"]))' "$OUT_DIR/summary.json" 2>/dev/null || echo "summary")"
log "done in $(($(date +%s) - T0))s; failed stages: ${failed:-none}; files in $OUT_DIR"
[[ -z "$failed" ]]
}

# A fresh log and no stale results (a local OUT_DIR is reused: the summary must read this run's files).
rm -f "$OUT_DIR"/{summary.json,suite.xml,gpu.xml,sweep.json,bench.json,gpu_check.log}
main 2>&1 | tee "$OUT_DIR/gpu_check.log"
exit "${PIPESTATUS[0]}"
