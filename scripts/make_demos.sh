#!/usr/bin/env bash
# ManiSkill motion-planning demonstrations, made offline, in the control and observation
# modes a policy trains on.
#
#   bash scripts/make_demos.sh ENV_ID NUM_DEMOS [CONTROL_MODE] [OUT_DIR]
#   e.g. bash scripts/make_demos.sh PickCube-v1 1000 pd_ee_delta_pos demos
#
# 1. ManiSkill's motion-planning solutions (mani_skill.examples.motionplanning.panda.run) write
#    NUM_DEMOS successful episodes in pd_joint_pos, on the CPU sim, seeds 0..NUM_DEMOS-1.
#    mplib 0.1.1 (which mani-skill pins) is built for numpy 1.x and crashes under the numpy 2
#    that opencv-python 5 needs, so the planner runs with numpy 1.26 first on PYTHONPATH, from
#    .venv/numpy1 (installed once, with pip --target). Nothing else sees that numpy.
# 2. ManiSkill's replay_trajectory converts them to CONTROL_MODE with state observations:
#    OUT_DIR/ENV_ID/motionplanning/trajectory.state.CONTROL_MODE.physx_cpu.h5 (+ .json), the
#    file examples/bc_torchrl.py reads. Episodes the conversion fails are dropped.
#
# Idempotent: a finished run of at least NUM_DEMOS demos (its stamp, .made-<count>) is kept; a
# reader takes the first NUM_DEMOS episodes (ManiSkillExperienceReplay(num_episodes=...)).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

ENV_ID="${1:?usage: make_demos.sh ENV_ID NUM_DEMOS [CONTROL_MODE] [OUT_DIR]}"
NUM="${2:?usage: make_demos.sh ENV_ID NUM_DEMOS [CONTROL_MODE] [OUT_DIR]}"
CONTROL="${3:-pd_ee_delta_pos}"
OUT="${4:-demos}"
VENV="${VENV:-.venv}"
PY="$VENV/bin/python"
NUMPY1="$VENV/numpy1"
PROCS="$(nproc)"

log() { echo "make_demos: $*"; }
[[ -x "$PY" ]] || { echo "make_demos: $PY not found: run 'make setup' first" >&2; exit 1; }

dir="$OUT/$ENV_ID/motionplanning"
converted="$dir/trajectory.state.$CONTROL.physx_cpu.h5"
count() { "$PY" -c 'import json,sys; print(len(json.load(open(sys.argv[1]))["episodes"]))' "$1" 2>/dev/null || echo 0; }
made="$( (find "$dir" -maxdepth 1 -name '.made-*' 2>/dev/null || true) | sed 's/.*\.made-//' | sort -n | tail -1)"
if [[ -f "$converted" && -n "$made" && "$made" -ge "$NUM" ]]; then
    log "$converted made already (from $made planned demos)"
    exit 0
fi

if [[ ! -f "$NUMPY1/numpy/__init__.py" ]]; then
    log "installing numpy<2 into $NUMPY1 (for mplib only)"
    "$PY" -m pip install -q --no-warn-conflicts --target "$NUMPY1" "numpy<2"
fi

rm -rf "$dir"
mkdir -p "$dir"
t0=$SECONDS
log "planning $NUM $ENV_ID demos on $PROCS processes"
# The planner's progress bars go to the log; its summary line is kept.
PYTHONPATH="$NUMPY1" "$PY" -m mani_skill.examples.motionplanning.panda.run -e "$ENV_ID" -n "$NUM" -b cpu \
    --only-count-success --record-dir "$OUT" --traj-name trajectory --num-procs "$PROCS" \
    >"$dir/planning.log" 2>&1 || { tail -20 "$dir/planning.log" >&2; exit 1; }
log "planned in $((SECONDS - t0)) s ($(count "$dir/trajectory.json") episodes)"

t1=$SECONDS
log "converting to $CONTROL, state observations"
"$PY" -m mani_skill.trajectory.replay_trajectory --traj-path "$dir/trajectory.h5" -c "$CONTROL" -o state \
    --save-traj -b physx_cpu --num-envs "$PROCS" >"$dir/conversion.log" 2>&1 ||
    { tail -20 "$dir/conversion.log" >&2; exit 1; }
log "converted in $((SECONDS - t1)) s: $converted ($(count "${converted%.h5}.json") episodes)"
touch "$dir/.made-$NUM"
