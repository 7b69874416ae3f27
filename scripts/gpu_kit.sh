#!/usr/bin/env bash
# Builds the GPU kit: everything the accelerator machine lacks to run the checks of
# scripts/gpu_check.py (the collection sweep, the obs-copy timing, the whole CPU suite, tests/gpu)
# as carries for the device tool (`make gpu-kit`).
#
#   bash scripts/gpu_kit.sh            # fill .gpu/ (idempotent: downloads are cached)
#   bash scripts/gpu_kit.sh --verify   # then check the slimmed wheels on the CPU sim here
#
# The accelerator machine (see benchmarks/README.md, "GPU kit") has Python 3.12 and
# torch 2.11.0+cu130 with numpy, scipy, h5py, pyyaml, tqdm, tabulate, imageio, lxml,
# networkx, requests, huggingface-hub, nvidia-ml-py, opencv-python-headless, pytest...
# and reaches no package registry. This script puts under .gpu/ (git-ignored):
#
#   .gpu/kit/wheels/  cp312 manylinux x86_64 wheels of what that machine lacks
#                     (torchrl, tensordict, gymnasium, sapien, mani_skill, imageio-ffmpeg
#                     and their missing dependencies, pinned below), mani_skill and sapien
#                     slimmed by scripts/gpu_kit_slim.py (every asset the CPU suite opens
#                     stays); no torch, no nvidia-* wheels; and this project's own wheel,
#                     built here (maniskill_torchrl-*.whl: gpu_check.py installs it into
#                     the machine's Python, so that the maniskill-torchrl console script
#                     exists beside python3, as the suite expects)
#   .gpu/kit/gl/      Debian's Vulkan loader and GL/EGL dispatch .debs (libvulkan1 ...),
#                     unpacked to / there when the machine has no libvulkan.so.1
#   .gpu/kit/x11/     libX11 and its libraries (SAPIEN's renderer links libX11.so.6),
#                     unpacked to a private folder there only if the machine lacks it
#   .gpu/kit/MANIFEST.txt   what is in the kit, what was left out and why, sizes
#
# Each direct subfolder of .gpu/ is one carry of the device tool. One command carries
# at most 64 MiB, the repository included, so a part holds at most 60 MiB (and at most
# 64 MiB minus the repository's size). The kit takes two parts: .gpu/kit (the .debs and
# what the wheels do not spill) and .gpu/kit2 (first fit, biggest wheel first). Carry and
# install .gpu/kit2 first (`python3 scripts/gpu_check.py --install-only`), then run the
# check with .gpu/kit, back to back while the machine is warm (benchmarks/README.md).
#
# Downloads are cached in $GPU_KIT_CACHE (default ~/.cache/maniskill_torchrl/gpu-kit);
# a second run downloads nothing and rebuilds .gpu/ from the cache in seconds.
#
# Knobs: PYTHON (default python3; needs pip), GPU_KIT_CACHE, GPU_KIT_PART_MIB (60),
#        GPU_KIT_SLACK_MIB (4: kept free in each command for the repository's growth),
#        GPU_KIT_NO_DEBS=1 (skip the .debs: apt-get is needed to fetch them).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

PY="${PYTHON:-python3}"
CACHE="${GPU_KIT_CACHE:-$HOME/.cache/maniskill_torchrl/gpu-kit}"
PART_MIB="${GPU_KIT_PART_MIB:-60}"
SLACK_MIB="${GPU_KIT_SLACK_MIB:-4}"
KIT=.gpu
VERIFY=0
for arg in "$@"; do
    case "$arg" in
        --verify) VERIFY=1 ;;
        -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit 0 ;;
        *) echo "gpu_kit: unknown argument $arg" >&2; exit 2 ;;
    esac
done
log() { echo "gpu-kit: $*"; }
die() { echo "gpu-kit: ERROR: $*" >&2; exit 1; }

# What the accelerator machine lacks, pinned (resolved for cp312 from the project's pins:
# torchrl 0.14.1, tensordict 0.14.3, mani_skill 3.0.1, sapien 3.0.3, gymnasium 1.4.0).
PINS=(
    torchrl==0.14.1 tensordict==0.14.3 pyvers==0.2.3 hoptorch==0.1.4 orjson==3.13.0
    importlib-metadata==10.2.0 lazy-importer==0.1.0
    gymnasium==1.4.0 farama-notifications==0.0.6
    sapien==3.0.3 pyperclip==1.11.0 importlib-resources==7.1.0 transforms3d==0.4.2
    mani-skill==3.0.1 dacite==1.9.2 gitpython==3.2.1 gitdb==4.0.12 smmap==5.0.3
    trimesh==5.2.0 defusedxml==0.7.1 tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.0
    pytorch-kinematics==0.7.6 arm-pytorch-utilities==0.5.0 pytorch-seed==0.2.0
    ipython==9.18.1 ipython-pygments-lexers==1.1.1 traitlets==5.16.1 matplotlib-inline==0.2.2
    prompt-toolkit==3.0.53 wcwidth==0.9.4 stack-data==0.6.3 executing==2.3.0 asttokens==3.0.2
    pure-eval==0.2.4 pexpect==4.9.0 ptyprocess==0.7.0
    imageio-ffmpeg==0.7.0
)
# Declared dependencies deliberately left out (wheels are installed with --no-deps).
EXCLUDED=(
    "mplib==0.1.1 + toppra: mani_skill's motion-planning examples only (11.5 + 0.9 MiB)"
    "jedi + parso: IPython's tab completion only (4.8 MiB)"
    "opencv-python: the machine has opencv-python-headless (same cv2 module)"
    "httpx2, httpcore2, truststore: huggingface_hub 2.x needs; the machine's huggingface-hub 1.x has its own"
    "torch, triton, nvidia-*, cuda-*: preinstalled there (torch 2.11.0+cu130)"
)
GL_DEBS=(libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
X11_DEBS=(libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0)
PLATFORMS=(manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64)

norm() { echo "$1" | tr 'A-Z' 'a-z' | sed -E 's/[-_.]+/_/g'; }

# ------------------------------------------------------------------ wheels
# imageio-ffmpeg 0.7.0 (29.5 MiB, manylinux2014; ffmpeg 7.0.2): the newest, 0.8.x, is 65 MiB, more
# than one carry. The CPU suite and the demo write .mp4 through it (imageio's ffmpeg plugin).
mkdir -p "$CACHE/wheels" "$CACHE/slim" "$CACHE/gl" "$CACHE/x11" "$CACHE/project"
missing=()
for pin in "${PINS[@]}"; do
    name="$(norm "${pin%%==*}")" ver="${pin##*==}"
    found=0
    for f in "$CACHE"/wheels/*.whl; do
        [[ -e "$f" ]] || continue
        base="$(basename "$f")"
        if [[ "$(norm "${base%%-*}")" == "$name" && "$(echo "$base" | cut -d- -f2)" == "$ver" ]]; then found=1; break; fi
    done
    [[ $found == 1 ]] || missing+=("$pin")
done
if ((${#missing[@]})); then
    log "downloading ${#missing[@]} cp312 wheels into $CACHE/wheels"
    plat=()
    for p in "${PLATFORMS[@]}"; do plat+=(--platform "$p"); done
    "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        "${plat[@]}" -d "$CACHE/wheels" "${missing[@]}" 2>&1 |
        { grep -v "^WARNING: Location 'file://.*' is ignored" || true; }
else
    log "all ${#PINS[@]} wheels cached in $CACHE/wheels"
fi

# Slim mani_skill and sapien (again only when the wheel or the slimming rules changed).
for dist in mani_skill sapien; do
    src="$(ls "$CACHE"/wheels/${dist}-*.whl | head -1)"
    dst="$CACHE/slim/$(basename "$src")"
    if [[ ! -f "$dst" || "$dst" -ot "$src" || "$dst" -ot scripts/gpu_kit_slim.py ]]; then
        "$PY" scripts/gpu_kit_slim.py "$src" "$CACHE/slim"
    fi
done

# This project as a wheel (pure Python), built from the working tree each time: gpu_check.py
# installs it into the machine's Python (the console script), while the suite imports the
# repository's copy (PYTHONPATH). Needs setuptools in the building Python (.venv has it).
BUILD_PY="$PY"
[[ -x .venv/bin/python ]] && BUILD_PY=.venv/bin/python
rm -f "$CACHE"/project/*.whl
had_build=0
[[ -e build ]] && had_build=1
"$BUILD_PY" -m pip wheel -q --no-deps --no-build-isolation --no-index -w "$CACHE/project" . 2>&1 |
    { grep -v "^WARNING: Location 'file://.*' is ignored" || true; }
ls "$CACHE"/project/maniskill_torchrl-*-py3-none-any.whl >/dev/null 2>&1 || die "building this project's wheel failed"
((had_build)) || rm -rf build  # setuptools' build folder, where this build made it

# -------------------------------------------------------------------- debs
fetch_debs() {  # dir pkgs... (the device README's recipe: amd64 lists of our own, no system change)
    local dir="$1"; shift
    local want=() p
    for p in "$@"; do ls "$dir"/"${p}"_*.deb >/dev/null 2>&1 || want+=("$p"); done
    ((${#want[@]})) || return 0
    command -v apt-get >/dev/null || die "apt-get is needed to fetch ${want[*]} (or set GPU_KIT_NO_DEBS=1)"
    local o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists="$CACHE/apt-lists"
             -oAPT::Sandbox::User=root -qq)
    mkdir -p "$CACHE/apt-lists/partial"
    if [[ ! -f "$CACHE/apt-lists/.updated" ]]; then
        apt-get "${o[@]}" update && touch "$CACHE/apt-lists/.updated"
    fi
    log "downloading ${want[*]}"
    (cd "$dir" && apt-get "${o[@]}" download "${want[@]}")
    # Epochs are url-escaped in .deb names (2%3a1.8.4), versions may hold '+': keep names of
    # letters, digits, '.', '_' and '-' for the carry (dpkg -x does not read the name).
    local f b
    for f in "$dir"/*.deb; do
        b="$(basename "$f")"; b="${b//%3a/_}"; b="${b//[^A-Za-z0-9._-]/_}"
        [[ "$dir/$b" == "$f" ]] || mv "$f" "$dir/$b"
    done
    return 0
}
if [[ "${GPU_KIT_NO_DEBS:-0}" != 1 ]]; then
    fetch_debs "$CACHE/gl" "${GL_DEBS[@]}"
    fetch_debs "$CACHE/x11" "${X11_DEBS[@]}"
fi

# ---------------------------------------------------------------- assemble
# The repository travels with every command: a part gets what is left of 64 MiB.
repo_bytes="$( { { git ls-files -z; git ls-files -z --others --exclude-standard; } 2>/dev/null |
    xargs -0 -r stat -c %s 2>/dev/null || true; } | awk '{ s += $1 } END { print s + 0 }')"

rm -rf "$KIT.tmp" && mkdir -p "$KIT.tmp"
"$PY" - "$CACHE" "$KIT.tmp" "$PART_MIB" "$repo_bytes" "$SLACK_MIB" "${PINS[@]}" <<'EOF'
import os, re, shutil, sys

cache, out, part_mib, repo_bytes, slack_mib = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
pins = sys.argv[6:]
norm = lambda s: re.sub(r"[-_.]+", "_", s).lower()
want = {norm(p.split("==")[0]): p.split("==")[1] for p in pins}
wheels = []
for f in sorted(os.listdir(os.path.join(cache, "wheels"))):
    name, ver = norm(f.split("-")[0]), f.split("-")[1]
    if want.get(name) != ver:
        continue  # an older pin left in the cache
    slim = os.path.join(cache, "slim", f)
    wheels.append(slim if os.path.exists(slim) else os.path.join(cache, "wheels", f))
missing = set(want) - {norm(os.path.basename(w).split("-")[0]) for w in wheels}
if missing:
    sys.exit(f"gpu-kit: ERROR: wheels missing from the cache: {sorted(missing)}")
wheels += sorted(os.path.join(cache, "project", f) for f in os.listdir(os.path.join(cache, "project")) if f.endswith(".whl"))
debs = {d: sorted(os.path.join(cache, d, f) for f in os.listdir(os.path.join(cache, d)) if f.endswith(".deb"))
        for d in ("gl", "x11") if os.path.isdir(os.path.join(cache, d))}

MiB = 2**20
# The repository may grow between this build and the run: keep slack_mib free in every command.
limit = min(part_mib * MiB, 64 * MiB - repo_bytes - slack_mib * MiB)
size = os.path.getsize
deb_bytes = sum(size(f) for fs in debs.values() for f in fs)
for w in wheels:
    if size(w) > limit:
        sys.exit(f"gpu-kit: ERROR: {os.path.basename(w)} alone ({size(w) / MiB:.1f} MiB) exceeds a part ({limit / MiB:.1f} MiB)")


def assign(k):
    """k parts, balanced: each wheel, biggest first, into the part with the fewest bytes so far
    (the .debs in the first, .gpu/kit); None if a part would exceed the limit."""
    parts = [{"wheels": [], "debs": debs if i == 0 else {}, "bytes": deb_bytes if i == 0 else 0} for i in range(k)]
    for w in sorted(wheels, key=size, reverse=True):
        part = min(parts, key=lambda p: p["bytes"])
        part["wheels"].append(w)
        part["bytes"] += size(w)
    return parts if all(p["bytes"] <= limit for p in parts) else None


k = 1
while (parts := assign(k)) is None:
    k += 1

for i, part in enumerate(parts):
    name = "kit" if i == 0 else f"kit{i + 1}"
    os.makedirs(os.path.join(out, name, "wheels"))
    for w in part["wheels"]:
        dst = os.path.join(out, name, "wheels", os.path.basename(w))
        try:
            os.link(w, dst)
        except OSError:
            shutil.copy2(w, dst)
    for d, fs in part["debs"].items():
        os.makedirs(os.path.join(out, name, d))
        for f in fs:
            shutil.copy2(f, os.path.join(out, name, d, os.path.basename(f)))

EOF

{
    echo "maniskill_torchrl GPU kit, built $(date -u +%Y-%m-%dT%H:%M:%SZ) by scripts/gpu_kit.sh"
    echo "For: python3.12 (cp312) manylinux x86_64 with torch 2.11 preinstalled; install with"
    echo "  python3 scripts/gpu_check.py  (pip install --no-index --no-deps --target ... .gpu/kit*/wheels/*.whl;"
    echo "  maniskill_torchrl-*.whl into the machine's Python itself, for its console script)"
    echo
    echo "Left out on purpose (declared dependencies; the wheels are installed with --no-deps):"
    for e in "${EXCLUDED[@]}"; do echo "  - $e"; done
    echo
    echo "Slimmed: mani_skill and sapien, see */SLIMMED.txt inside their .dist-info and scripts/gpu_kit_slim.py"
} >"$KIT.tmp/MANIFEST.head"

rm -rf "$KIT" && mkdir -p "$KIT"
for part in "$KIT.tmp"/kit*; do
    name="$(basename "$part")"
    {
        cat "$KIT.tmp/MANIFEST.head"
        echo
        echo "Part $name:"
        (cd "$part" && find . -type f ! -name MANIFEST.txt | sort | while read -r f; do
            awk -v b="$(stat -c %s "$f")" -v f="${f#./}" 'BEGIN { printf "  %8.2f MiB  %s\n", b / 1048576, f }'; done)
    } >"$part/MANIFEST.txt"
    mv "$part" "$KIT/$name"
done
rm -rf "$KIT.tmp"
# Every part names all parts and their wheel lists' hashes (what gpu_check.py stamps an installed
# part with): the check then knows whether a part installed by an earlier call is missing.
for part in "$KIT"/kit*; do
    for p in "$KIT"/kit*; do echo "$(basename "$p") $(ls "$p"/wheels | sha256sum | cut -c1-16)"; done >"$part/PARTS.txt"
done

# --------------------------------------------------------- PhysX GPU library
# SAPIEN downloads libPhysXGpu_64.so from GitHub on the GPU sim's first use; the accelerator
# machine cannot. When this machine has it (the GPU sim ran here once, or it was unzipped into
# the folder by hand), it travels as its own part, .gpu/physx, which gpu_check.py installs.
physx_ver="$(.venv/bin/python -c 'import sapien.physx as p; print(p.version())' 2>/dev/null || echo 105.1-physx-5.3.1.patch0)"
physx_src="${GPU_KIT_PHYSX_DIR:-$HOME/.sapien/physx/$physx_ver}"
if [[ -f "$physx_src/libPhysXGpu_64.so" ]]; then
    mkdir -p "$KIT/physx" && cp "$physx_src"/* "$KIT/physx/" && echo "$physx_ver" >"$KIT/physx/VERSION"
    log "PhysX GPU library $physx_ver from $physx_src: carry .gpu/physx in the first run, after .gpu/kit was installed"
else
    log "NOTE: no PhysX GPU library in $physx_src: the GPU sim cannot start on a machine without internet"
    log "      access (SAPIEN downloads it from its physx-precompiled GitHub release $physx_ver on first use);"
    log "      unzip that release's linux-so.zip there (or set GPU_KIT_PHYSX_DIR) and rerun to carry it"
fi

# ------------------------------------------------------------------- sizes
log "parts (each is one carry of the device tool; limit ${PART_MIB} MiB per part, 64 MiB per command with the repo):"
status=0
for part in "$KIT"/*/; do
    bytes="$(du -sb "$part" | cut -f1)"
    awk -v p="${part%/}" -v b="$bytes" -v r="$repo_bytes" -v w="$(ls "$part"/wheels/*.whl 2>/dev/null | wc -l)" \
        -v d="$(ls "$part"/*/*.deb 2>/dev/null | wc -l)" 'BEGIN {
        printf "gpu-kit:   %-10s %6.1f MiB (%d wheels, %d .debs) + repo %.1f MiB = %.1f MiB per run\n",
               p, b / 1048576, w, d, r / 1048576, (b + r) / 1048576 }' 
    if (( bytes > PART_MIB * 1048576 || bytes + repo_bytes > 64 * 1048576 )); then status=1; fi
    if (( bytes + repo_bytes > (64 - SLACK_MIB) * 1048576 )); then
        log "WARNING: ${part%/} leaves less than ${SLACK_MIB} MiB for the repository's growth"
    fi
done
((status == 0)) || die "a part exceeds its limit"
log "the largest wheels:"
ls -S "$KIT"/*/wheels/*.whl | head -5 | while read -r f; do
    awk -v b="$(stat -c %s "$f")" -v f="$(basename "$f")" 'BEGIN { printf "gpu-kit:   %6.1f MiB  %s\n", b / 1048576, f }'; done

# ------------------------------------------------------------------ verify
if [[ $VERIFY == 1 ]]; then
    # The slimmed mani_skill (pure Python) with a slimmed sapien built for this machine's
    # Python, installed with --target into a temp dir, must make and step both GPU-check
    # tasks on the CPU sim with the project's .venv python (PYTHONPATH first at that dir).
    [[ -x .venv/bin/python ]] || die "--verify needs .venv (make setup)"
    tag="$(.venv/bin/python -c 'import sys; print(f"cp{sys.version_info[0]}{sys.version_info[1]}")')"
    vdir="$CACHE/verify-$tag"
    mkdir -p "$vdir/in"
    if ! ls "$vdir"/in/sapien-3.0.3-"$tag"-*.whl >/dev/null 2>&1; then
        .venv/bin/python -m pip download -q --no-deps --only-binary=:all: -d "$vdir/in" sapien==3.0.3 2>&1 |
            { grep -v "^WARNING: Location 'file://.*' is ignored" || true; }
    fi
    "$PY" scripts/gpu_kit_slim.py "$(ls "$vdir"/in/sapien-3.0.3-"$tag"-*.whl | head -1)" "$vdir/slim" >/dev/null
    target="$(mktemp -d)"
    trap 'rm -rf "$target"' EXIT
    .venv/bin/python -m pip install -q --no-index --no-deps --no-compile --target "$target" \
        "$vdir"/slim/sapien-*.whl "$KIT"/kit*/wheels/mani_skill-*.whl
    log "verify: slimmed mani_skill + sapien ($tag) from $target, CPU sim: the CPU suite's tasks, state and rgb"
    PYTHONPATH="$target${PYTHONPATH:+:$PYTHONPATH}" .venv/bin/python - "$target" <<'EOF'
import os, sys, warnings
warnings.filterwarnings("ignore")
import gymnasium as gym
import mani_skill, sapien
import mani_skill.envs  # noqa: F401
target = sys.argv[1]
for mod in (mani_skill, sapien):
    assert mod.__file__.startswith(target), f"{mod.__name__} imported from {mod.__file__}, not {target}"
assert not os.path.exists(os.path.join(os.path.dirname(mani_skill.__file__), "assets", "environment_maps")), "not slimmed"
# The tasks that the GPU checks and the CPU suite make (scripts/gpu_kit_slim.py), with pictures:
# a camera or a render opens the visual meshes (the D415 of panda_wristcam, the D'Claw's .glb).
TASKS = ("PushCube-v1", "MS-CartpoleBalance-v1", "PickCube-v1", "PullCube-v1", "StackCube-v1",
         "TwoRobotPickCube-v1", "RotateValveLevel0-v1", "DrawTriangle-v1")
for env_id in TASKS:
    for obs_mode in ("state", "rgb"):
        env = gym.make(env_id, num_envs=1, obs_mode=obs_mode, render_mode="rgb_array", sim_backend="physx_cpu")
        obs, info = env.reset(seed=0)
        for _ in range(3):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        env.render()
        env.close()
    print(f"gpu-kit:   {env_id}: state and rgb, reset, step, render: ok")
print("gpu-kit: verify: ok")
EOF
fi
