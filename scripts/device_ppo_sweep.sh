#!/usr/bin/env bash
# PPO configurations side by side on the accelerator machine's CPU cores, each pinned to 2 cores
# (taskset) to stand in for the 2-core development machine; CPU sim, CPU policy. Used to choose
# the CPU training configuration before the timed run on the 2-core machine (benchmarks/RESULTS.md).
#
#   [CORES=2] bash scripts/device_ppo_sweep.sh SECONDS NAME:"ARGS" [NAME:"ARGS" ...]   (device tool, carry .gpu/kit)
# Each NAME gets $OUT/NAME/{metrics.jsonl,log.txt}.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
secs=$1; shift
OUT_DIR="${OUT:-outputs/ppo-sweep}"
python3 scripts/gpu_check.py --install-only "$OUT_DIR/.install" >/dev/null 2>&1 || { cat "$OUT_DIR/.install/gpu_check.log"; exit 1; }
rm -rf "$OUT_DIR/.install"
export PYTHONPATH="${GPU_CHECK_SITE:-/tmp/maniskill_torchrl-gpu-site}:$(pwd)" PYTHONUNBUFFERED=1 RL_WARNINGS=0
core=0
per=${CORES:-2}
for spec in "$@"; do
    name=${spec%%:*}; args=${spec#*:}
    mkdir -p "$OUT_DIR/$name"
    # shellcheck disable=SC2086
    taskset -c "$core-$((core + per - 1))" timeout -k 5 "$secs" python3 examples/ppo_torchrl.py --device cpu \
        --out "$OUT_DIR/$name" $args >"$OUT_DIR/$name/log.txt" 2>&1 &
    core=$((core + per))
done
wait
for spec in "$@"; do
    name=${spec%%:*}
    echo "== $name: ${spec#*:}"
    grep '^eval\|Error\|error' "$OUT_DIR/$name/log.txt" | tail -6
    grep '^iter' "$OUT_DIR/$name/log.txt" | tail -1
done
