#!/usr/bin/env bash
# Idempotent developer set-up for maniskill_torchrl.
#
#   bash scripts/setup.sh        (or: make setup)
#
# 1. Creates .venv at the repo root (python3 -m venv) if missing.
# 2. Installs torch==2.14.1 (pinned: torchrl 0.14.1's C extension, which prioritized replay
#    needs, is built against torch 2.14 and does not load on another torch; on Linux that is
#    PyPI's CUDA build with its nvidia-* wheels, found in a local pip index where there is one)
#    and `pip install -e ".[test,demo,distributed,docs,hydra,maniskill]"`
#    (the `maniskill` extra: the ManiSkill 3.0.x release) in one resolve (and numpy<2 into
#    .venv/numpy1, ManiSkill's motion planner's: maniskill_torchrl.data.motion_planning), then
#    writes the bytecode of what the library, its examples and its tests import (by importing it
#    once; the make targets let Python write the rest's on first use).
#    The install itself is uv's `uv pip install` (uv installed into the venv by pip first), with
#    pip's index settings (`pip config list`: index URLs, find-links, constraints, cert) passed on
#    by scripts/uv_args.py,
#    and pip's resolution semantics (--index-strategy unsafe-best-match): the same versions as
#    pip, in about a quarter of the time (pip resolves and unpacks ~7 GB on one core). Where uv
#    cannot be installed or fails, pip installs as before (MANISKILL_TORCHRL_NO_UV=1: always).
#    The torch pin (or the torch already installed) is passed to pip as a constraint,
#    so pip can never swap it for an unpinned (multi-GB CUDA) torch.
#    MANISKILL=nightly (make test MANISKILL=nightly) builds .venv-nightly instead,
#    with `mani-skill-nightly` in place of the extra (the same `mani_skill` package).
# 3. Checks that SAPIEN finds a Vulkan device (ManiSkill 3 needs one even for
#    state observations). On Debian bookworm as root it installs Mesa
#    lavapipe from bookworm-backports when none is found.
#
# A stamp (.venv/.setup-stamp, sha256 of pyproject.toml + this script + uv_args.py) skips
# pip entirely when nothing changed; a successful Vulkan probe is cached in
# .venv/.vulkan-ok.
#
# Environment knobs:
#   MANISKILL_TORCHRL_SKIP_TORCH=1     don't install torch (bring your own 2.14.x, e.g.
#                                      a CUDA build, installed into .venv first)
#   MANISKILL_TORCHRL_NO_APT=1         never touch apt; just print instructions
#   MANISKILL_TORCHRL_NO_UV=1          install with pip alone (no uv)
#   MANISKILL_TORCHRL_FORCE_VULKAN_PROBE=1   ignore the cached Vulkan probe
#   PYTHON=python3.X                   interpreter used to create .venv
#   MANISKILL=release|nightly          which ManiSkill: the release (.venv, default) or
#                                      mani-skill-nightly (.venv-nightly)
#   MANISKILL_NIGHTLY_SPEC=...         the nightly requirement (default below)
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."

TORCH_PIN="torch==2.14.1"
# torchrl's C extension loads on this torch minor only (the pin above, or a user's own build of it).
TORCH_ABI="2.14"
# Both are part of the stamp (this script's hash): changing them reinstalls.
EXTRAS="test,demo,distributed,docs,hydra"
NIGHTLY_SPEC="${MANISKILL_NIGHTLY_SPEC:-mani-skill-nightly>=2026.8,<2026.9}"
# The installer (pinned: a new uv must not change what CI installs unseen).
UV_PIN="uv==0.13.9"

log() { echo "setup: $*"; }
# pip, minus the noise about file:// index locations that don't exist here.
pip_q() {
    "$PY" -m pip -q "$@" 2>&1 |
        { grep -v "^WARNING: Location 'file://.*' is ignored: it is neither a file nor a directory" || true; }
}
die() { echo "setup: ERROR: $*" >&2; exit 1; }

case "${MANISKILL:-release}" in
    release) VENV=.venv; EXTRAS="$EXTRAS,maniskill"; MANISKILL_REQ=() ;;
    nightly) VENV=.venv-nightly; MANISKILL_REQ=("$NIGHTLY_SPEC") ;;
    *) die "MANISKILL=${MANISKILL} is neither 'release' nor 'nightly'" ;;
esac
PY="$VENV/bin/python"
STAMP="$VENV/.setup-stamp"
VULKAN_STAMP="$VENV/.vulkan-ok"

# Installs its arguments (pip install's) with uv; returns non-zero where uv is not there or fails.
uv_install() {
    [[ "${MANISKILL_TORCHRL_NO_UV:-0}" != 1 ]] || return 1
    "$VENV/bin/uv" --version >/dev/null 2>&1 || pip_q install "$UV_PIN" >/dev/null 2>&1 || return 1
    local opts=() envs=() line
    while IFS= read -r line; do
        if [[ "$line" == SSL_CERT_FILE=* ]]; then envs+=("$line"); else opts+=("$line"); fi
    done < <("$PY" -m pip config list 2>/dev/null | "$PY" scripts/uv_args.py)
    env ${envs[@]+"${envs[@]}"} "$VENV/bin/uv" pip install --quiet --python "$PY" \
        --index-strategy unsafe-best-match ${opts[@]+"${opts[@]}"} "$@"
}

torch_version() { "$PY" -c 'import importlib.metadata as m; print(m.version("torch"))'; }

# ---------------------------------------------------------------- venv + pip
if [[ ! -x "$PY" ]]; then
    log "creating $VENV"
    "${PYTHON:-python3}" -m venv "$VENV"
fi

want_hash="$( (sha256sum pyproject.toml scripts/setup.sh scripts/uv_args.py; echo "${MANISKILL_REQ[*]:-}") | sha256sum | cut -d' ' -f1)"
have_hash="$(cat "$STAMP" 2>/dev/null || true)"

if [[ "$want_hash" == "$have_hash" ]]; then
    pip_done=0
else
    rm -f "$STAMP" "$VULKAN_STAMP"
    # The torch the resolver must keep: the one installed (a user's own build), else TORCH_PIN,
    # installed in the same pip call as the package (one resolve).
    constraints="$(mktemp)"
    trap 'rm -f "$constraints"' EXIT
    torch_req=()
    if "$PY" -c "import torch" >/dev/null 2>&1 && [[ "$(torch_version)" == "$TORCH_ABI".* ]]; then
        log "torch $(torch_version) already in $VENV, not reinstalling"
        echo "torch==$(torch_version)" >"$constraints"
    elif [[ "${MANISKILL_TORCHRL_SKIP_TORCH:-0}" == 1 ]]; then
        have="$("$PY" -c "import torch; print(torch.__version__)" 2>/dev/null || echo "not importable")"
        die "MANISKILL_TORCHRL_SKIP_TORCH=1 but torch in $VENV is $have; torchrl 0.14's C extension" \
            "needs torch $TORCH_ABI.x: install your build of it first ($PY -m pip install 'torch==$TORCH_ABI.*' ...)," \
            "or unset the variable"
    else
        if "$PY" -c "import torch" >/dev/null 2>&1; then
            log "torch $(torch_version) in $VENV is not $TORCH_ABI.x, which torchrl's C extension needs: replacing it"
        fi
        torch_req=("$TORCH_PIN")
        echo "$TORCH_PIN" >"$constraints"
    fi

    log "installing ${torch_req[*]:+${torch_req[*]} and }maniskill_torchrl (editable, extras: $EXTRAS) ${MANISKILL_REQ[*]:-}"
    reqs=(-c "$constraints" ${torch_req[@]+"${torch_req[@]}"} -e ".[$EXTRAS]" ${MANISKILL_REQ[@]+"${MANISKILL_REQ[@]}"})
    if ! uv_install "${reqs[@]}"; then
        [[ "${MANISKILL_TORCHRL_NO_UV:-0}" == 1 ]] || log "uv unavailable or failed (see above): installing with pip"
        # --no-compile: pip byte-compiles all ~15,000 installed files (torch alone: ~20 s), of which
        # the library's processes import about a third; those are compiled below.
        pip_q install --no-compile "${reqs[@]}"
    fi
    log "compiling the bytecode of what the library imports"
    # Importing writes the .pyc of each module imported (PYTHONDONTWRITEBYTECODE, which some machines
    # set, would stop it), on one core: ~25 s for ~4,600 files, where compileall of the whole
    # site-packages took ~43 s on 2 cores. A process that imports a module without its .pyc
    # compiles it (with PYTHONDONTWRITEBYTECODE set, every time: ~22 s for this import instead of ~9 s).
    env -u PYTHONDONTWRITEBYTECODE "$PY" - <<'EOF' || log "warning: an import failed (above): its bytecode is compiled on first use"
import importlib, pkgutil

import maniskill_torchrl

names = ["torch", "tensordict", "tensordict.nn", "torchrl.envs", "torchrl.collectors", "torchrl.data",
         "torchrl.modules", "torchrl.objectives", "torchrl.objectives.value", "mani_skill.envs",
         "mani_skill.trajectory.replay_trajectory", "gymnasium", "matplotlib.pyplot", "imageio", "h5py",
         "pytest", "xdist", "hypothesis"]
names += [m.name for m in pkgutil.walk_packages(maniskill_torchrl.__path__, "maniskill_torchrl.")]
for name in names:
    try:
        importlib.import_module(name)
    except ImportError:
        pass  # an optional dependency that is not installed: nothing to compile
EOF
    # Exactly one ManiSkill distribution: the release and the nightly install the same files.
    "$PY" - <<'EOF' || die "expected exactly one of mani-skill / mani-skill-nightly in $VENV (see above); remove $VENV and re-run"
import importlib.metadata as m, sys
have = [f"{d} {m.version(d)}" for d in ("mani-skill", "mani-skill-nightly") if list(m.distributions(name=d))]
print("setup: ManiSkill:", ", ".join(have) or "none")
sys.exit(len(have) != 1)
EOF
    echo "$want_hash" >"$STAMP"
    pip_done=1
fi

# ------------------------------------------------------ the motion planner's numpy 1
# ManiSkill's motion planner (mplib 0.1.1, which mani-skill pins) crashes under numpy 2: its process runs
# with a numpy 1 first on PYTHONPATH, from $VENV/numpy1 (maniskill_torchrl.data.motion_planning finds it at
# <sys.prefix>/numpy1). Made here, once, so that nothing is installed at run time. Nothing else sees it.
if [[ ! -f "$VENV/numpy1/numpy/__init__.py" ]]; then
    log "installing numpy<2 into $VENV/numpy1 (for ManiSkill's motion planner only)"
    pip_q install --no-warn-conflicts --no-compile --target "$VENV/numpy1" "numpy<2" ||
        log "warning: numpy<2 could not be installed into $VENV/numpy1: the motion-planning demos need it"
    pip_done=1
fi

# -------------------------------------------------------------------- Vulkan
# Exit codes: 0 = device found, 2 = no rendering device, 3 = sapien broken.
vulkan_probe() {
    local out rc=0
    out="$(timeout 120 "$PY" - 2>&1 <<'EOF'
import sys
try:
    import sapien
except Exception as e:
    print(f"cannot import sapien: {e!r}")
    sys.exit(3)
try:
    sapien.render.RenderSystem()
except Exception as e:
    print(f"{type(e).__name__}: {e}")
    sys.exit(2)
EOF
)" || rc=$?
    if [[ $rc -ne 0 && -n "$out" ]]; then
        printf '%s\n' "$out" | tail -n 5 | sed 's/^/setup:   probe: /' >&2
    fi
    return "$rc"
}

if [[ "${MANISKILL_TORCHRL_FORCE_VULKAN_PROBE:-0}" == 1 ]]; then
    rm -f "$VULKAN_STAMP"
fi

if [[ -f "$VULKAN_STAMP" ]]; then
    [[ $pip_done == 1 ]] || log "up to date"
    exit 0
fi

log "probing for a Vulkan device"
rc=0
vulkan_probe || rc=$?
if [[ $rc -eq 3 ]]; then
    die "sapien is not importable in $VENV (see above); try 'make clean setup'"
elif [[ $rc -ne 0 && $rc -ne 2 ]]; then
    die "Vulkan probe crashed or timed out (exit $rc)"
fi

if [[ $rc -eq 2 ]]; then
    log "no usable Vulkan device (ManiSkill needs one, even for state observations)"
    codename="$(. /etc/os-release 2>/dev/null && echo "${VERSION_CODENAME:-}")" || codename=""
    if [[ "$(id -u)" -eq 0 && "$codename" == bookworm && "${MANISKILL_TORCHRL_NO_APT:-0}" != 1 ]]; then
        if grep -rqsE '^[^#]*bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
            log "bookworm-backports already in apt sources"
        else
            log "adding bookworm-backports to /etc/apt/sources.list.d/backports.sources"
            cat >/etc/apt/sources.list.d/backports.sources <<'EOF'
Types: deb
URIs: http://deb.debian.org/debian
Suites: bookworm-backports
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
        fi
        log "installing Mesa lavapipe from bookworm-backports (apt-get)"
        apt-get update -q
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
            -t bookworm-backports mesa-vulkan-drivers libvulkan1
        log "re-probing for a Vulkan device"
        rc=0
        vulkan_probe || rc=$?
        [[ $rc -eq 0 ]] || die "still no usable Vulkan device after installing" \
            "bookworm-backports mesa-vulkan-drivers (probe exit $rc, see above)"
    else
        die "no usable Vulkan device. Install Mesa >= 24.3 lavapipe" \
            "(Debian/Ubuntu: 'apt-get install mesa-vulkan-drivers libvulkan1';" \
            "on Debian bookworm use '-t bookworm-backports', its own Mesa 22.3 is too old)" \
            "or a GPU driver with Vulkan support, then re-run 'make setup'."
    fi
fi

date -u +%FT%TZ >"$VULKAN_STAMP"
log "Vulkan device OK"
[[ $pip_done == 0 ]] || log "done"
