"""What copying ManiSkill's observations costs, where ManiSkillWrapper copies them.

On the GPU sim (and the CPU sim rendering with ``sapien_cuda``) ManiSkill hands out buffers that
its next step or render overwrites, so the wrapper copies every observation entry it returns, once,
onto ``env.device`` (``envs/maniskill.py``, ``ManiSkillWrapper._to_device``). This times that copy on the CPU, with the
wrapper's own code, on PickCube-v1's real ``obs_mode="rgb"`` observation at 128 x 128 (agent and
extra state, camera parameters, ``sensor_data/base_camera/rgb`` uint8), tiled to the batch:

- ``as is``: the TensorDict built from ManiSkill's tensors without a copy (the CPU sim);
- ``copied``: the same with every entry cloned first (the GPU sim's path).

Beside them, one CPU-sim ``env.step`` of that task at batch 1 (128 px rgb, rendered with
lavapipe) gives the scale. Contenders interleaved (``common.interleave``), this process's CPU time,
medians over rounds.

Then, with ``--transfers``, the device rule counted on a stand-in CUDA machine (the test double of
``tests/support/cuda_double.py``: ManiSkill's CPU sim with ``sapien_cuda`` pictures on a second torch
device): the copies between host and device that one ``env.step`` makes, raw ManiSkill's own
(the double's render upload included) and the library's on top, for ``env.device`` the CPU
(pictures moved to the host) and the device (pictures copied there, the host outputs gathered
and uploaded in one copy). Counts and bytes, not seconds: the double's copies are CPU copies.

Then, with ``--timing --out FILE.json`` (on a CUDA machine; the GPU check calls it so), the device
rule's cost in time: one CPU-sim ``env.step`` of PickCube-v1 with ``device="cuda"`` against
``device="cpu"``, ``obs_mode`` state and rgb (128 x 128 camera), N = 1 and 8 (the batched CPU
env). One env per case, moved between the two devices with ``env.to()`` before each contender's
turn (the same sim, the same renderer: only the copies differ), contenders interleaved, wall
clock with the device synchronised at the end of each timed block, medians and the ratio
cuda / cpu per case. All in this one process (a fresh process takes 20-30 s to start on the
H100 machine); under 90 s there. Without CUDA it says so and writes ``{"skipped": ...}``.

Run: ``python -m benchmarks.bench_obs_copy [--batches 2 64] [--rounds 31] [--transfers]``, or
``python -m benchmarks.bench_obs_copy --timing --out device_copy.json``.
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import subprocess
import sys
import warnings
from pathlib import Path

from benchmarks.common import Contender, interleave, make_actions, paired_ratio, report
from benchmarks.machine import machine_line


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[2, 64])
    parser.add_argument("--size", type=int, default=128, help="camera width and height")
    parser.add_argument("--rounds", type=int, default=31)
    parser.add_argument("--calls", type=int, default=20, help="copies per round")
    parser.add_argument("--transfers", action="store_true", help="also count the device rule's copies")
    parser.add_argument("--steps", type=int, default=20, help="steps counted per setting (--transfers)")
    parser.add_argument("--timing", action="store_true", help="time device='cuda' against 'cpu' (CUDA only)")
    parser.add_argument("--out", type=Path, help="--timing: the JSON file to write")
    parser.add_argument("--_under-double", dest="under_double", action="store_true", help=argparse.SUPPRESS)
    # --timing's logic tried under the CUDA double (tests/support/cuda_double.py): its device, smaller batches.
    parser.add_argument("--_timing-device", dest="timing_device", default="cuda", help=argparse.SUPPRESS)
    parser.add_argument(
        "--_timing-batches", dest="timing_batches", type=int, nargs="+", default=[1, 8], help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.under_double:
        return count_transfers(args.size, args.steps)
    if args.timing:
        return time_device_rule(args.out, args.size, device=args.timing_device, batches=tuple(args.timing_batches))

    warnings.filterwarnings("ignore")
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    import torch

    from maniskill_torchrl._private import new_tensordict
    from maniskill_torchrl.envs.maniskill import _mapped

    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    torch.set_num_threads(1)
    print(machine_line())
    cpu = torch.device("cpu")

    def copy(x: torch.Tensor) -> torch.Tensor:  # ManiSkillWrapper._to_device's copy of each leaf
        return x.to(cpu, copy=True)

    cam = dict(width=args.size, height=args.size)
    env = gym.make("PickCube-v1", num_envs=1, obs_mode="rgb", sensor_configs=cam)
    obs, _ = env.reset(seed=0)
    actions = make_actions(env.unwrapped.single_action_space, args.calls, batch=(1,))

    def tiled(x, b):
        if isinstance(x, torch.Tensor):
            return x.expand(b, *x.shape[1:]).contiguous()
        return {k: tiled(v, b) for k, v in x.items()}

    def step() -> int:
        for a in actions:
            env.step(a)
        return len(actions)

    for b in args.batches:
        batch_obs = tiled(obs, b)
        size = batch_obs["sensor_data"]["base_camera"]["rgb"]
        print(f"\nbatch {b}: rgb {tuple(size.shape)} uint8, {size.numel() / 2**20:.2f} MiB of pixels per step")

        def as_is(o=batch_obs, b=b) -> int:
            for _ in range(args.calls):
                new_tensordict(dict(o), batch_size=[b])
            return args.calls

        def copied(o=batch_obs, b=b) -> int:
            for _ in range(args.calls):
                new_tensordict(_mapped(o, copy), batch_size=[b])
            return args.calls

        contenders = [Contender("as is", as_is), Contender("copied", copied)]
        if b == args.batches[0]:
            contenders.append(Contender("CPU-sim env.step, batch 1", step, setup=lambda: env.reset(seed=0)))
        results = interleave(contenders, rounds=args.rounds, warmup=2, clock="cpu")
        print(report(results, baseline="as is", unit="call", difference=True))
    env.close()
    if args.transfers:
        root = Path(__file__).resolve().parents[1]
        tests = root / "tests"
        paths = [tests / "gpu" / "cuda_site", tests, root, *filter(None, [os.environ.get("PYTHONPATH")])]
        env_vars = dict(os.environ, MANISKILL_TORCHRL_CUDA_DOUBLE="1", PYTHONPATH=os.pathsep.join(map(str, paths)))
        cmd = [sys.executable, "-m", "benchmarks.bench_obs_copy", "--_under-double", "--size", str(args.size)]
        return subprocess.run([*cmd, "--steps", str(args.steps)], env=env_vars, cwd=root).returncode
    return 0


def count_transfers(size: int, steps: int) -> int:
    """Under the CUDA double: host/device copies per ``env.step``, raw ManiSkill and the library."""
    warnings.filterwarnings("ignore")
    import gymnasium as gym
    import torch

    from maniskill_torchrl import ManiSkillEnv
    from support import cuda_double

    cam = dict(obs_mode="rgb", sensor_configs=dict(width=size, height=size), sim_backend="cpu")
    kinds = ("d2h", "h2d", "d2d")
    waits = ("sync", "event_wait", "render_upload")

    def per_step(step) -> dict:
        before = dict(cuda_double.TRANSFERS)
        for _ in range(steps):
            step()
        after = cuda_double.TRANSFERS
        keys = [*kinds, *(f"{k}_bytes" for k in kinds), *waits]
        return {k: (after[k] - before.get(k, 0)) / steps for k in keys}

    rows = []
    raw = gym.make("PickCube-v1", num_envs=1, **cam)
    raw.reset(seed=0)
    action = torch.zeros(raw.action_space.shape)
    rows.append(("raw ManiSkill step", per_step(lambda: raw.step(action))))
    raw.close()
    for device in ("cpu", cuda_double.DEVICE):
        env = ManiSkillEnv("PickCube-v1", device=device, **cam)
        td = env.reset(seed=0)
        td.set("action", torch.zeros(env.action_spec.shape, device=env.device))
        rows.append((f"ManiSkillEnv(device={str(device)!r}).step", per_step(lambda e=env, t=td: e.step(t))))
        env.close()
    print(f"\nPickCube-v1 rgb {size} px, batch 1, CPU sim with sapien_cuda pictures (the CUDA double), per step:")
    print("| what | device->host | host->device | on the device | host syncs | event waits | renderer's uploads |")
    print("|---|---|---|---|---|---|---|")
    for name, c in rows:
        cells = [f"{c[k]:.0f} ({c[k + '_bytes'] / 1024:.1f} KiB)" for k in kinds] + [f"{c[k]:.0f}" for k in waits]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("(device->host and its sync: the picture for device='cpu'; the action, which the CPU sim takes on the host,")
    print(" for the device. Event waits: for the copy out of a host buffer before its reuse, long ended by then.)")
    return 0


def time_device_rule(
    out: Path | None, size: int, budget_s: float = 75.0, device: str = "cuda", batches: tuple = (1, 8)
) -> int:
    """``device="cuda"`` against ``device="cpu"`` on CPU-sim steps (see the module docstring)."""
    import time

    import torch

    start = time.perf_counter()
    result: dict = {"what": "CPU-sim PickCube-v1 env.step, device='cuda' / device='cpu'", "size": size}
    if not torch.get_device_module(device).is_available():
        print("--timing: no CUDA on this machine (torch.cuda.is_available() is False): skipped.")
        result["skipped"] = "no CUDA"
        _write(out, result)
        return 0
    warnings.filterwarnings("ignore")
    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    from maniskill_torchrl import ManiSkillEnv

    print(machine_line())
    result["machine"] = machine_line()
    result["device"] = torch.cuda.get_device_name() if device == "cuda" else device
    sync = torch.get_device_module(device).synchronize
    cases = []
    steps, rounds = 20, 9
    build_s = 0.0  # the last env's build time: a case is left out where it would not fit
    for n in batches:
        for obs_mode in ("state", "rgb"):
            left = budget_s - (time.perf_counter() - start)
            if left < 8 + (build_s if n > 1 else 0):
                print(f"N={n} {obs_mode}: left out, {left:.0f} s of the {budget_s:.0f} s budget left")
                result.setdefault("left_out", []).append({"num_envs": n, "obs_mode": obs_mode})
                continue
            t0 = time.perf_counter()
            kwargs = dict(obs_mode=obs_mode, sim_backend="cpu", max_episode_steps=100_000)
            if obs_mode == "rgb":
                kwargs["sensor_configs"] = dict(width=size, height=size)
            env = ManiSkillEnv("PickCube-v1", num_envs=n, **kwargs)
            build_s = time.perf_counter() - t0
            tds: dict = {}

            def setup(name, env=env, tds=tds) -> None:
                env.to(name if name == "cpu" else device)
                if name not in tds:  # one reset per device, then one long episode
                    tds[name] = env.reset(seed=0).set("action", env.action_spec.zero())
                env.step(tds[name])  # untimed: the first step after a move lays out its buffers

            def run(name, env=env, tds=tds) -> int:
                td = tds[name]
                for _ in range(steps):
                    env.step(td)
                sync()  # what the steps sent up has arrived
                return steps

            contenders = [
                Contender(d, functools.partial(run, d), setup=functools.partial(setup, d)) for d in ("cpu", "cuda")
            ]
            built = time.perf_counter()
            results = interleave(contenders, rounds=rounds, warmup=1, clock="wall")
            cpu, cuda = results["cpu"].median, results["cuda"].median
            case = {
                "num_envs": n,
                "obs_mode": obs_mode,
                "cpu_median_s": cpu,
                "cuda_median_s": cuda,
                "ratio_cuda_cpu": cuda / cpu,
                "paired_ratio_cuda_cpu": paired_ratio(results, "cuda", "cpu", clock="wall"),
                "steps_per_round": steps,
                "rounds": rounds,
                "build_s": build_s,
                "timed_s": time.perf_counter() - built,
                "results": {k: r.as_dict() for k, r in results.items()},
            }
            cases.append(case)
            print(
                f"N={n} {obs_mode:<5}: cpu {1e3 * cpu:7.3f} ms/step, cuda {1e3 * cuda:7.3f} ms/step, "
                f"cuda/cpu {cuda / cpu:.3f}"
            )
            env.close()
    result["cases"] = cases
    result["wall_s"] = time.perf_counter() - start
    _write(out, result)
    return 0


def _write(out: Path | None, result: dict) -> None:
    if out is not None:
        import json

        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1))
        print(f"wrote {out}")


if __name__ == "__main__":
    raise SystemExit(main())
