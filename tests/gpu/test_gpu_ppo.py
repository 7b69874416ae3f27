"""examples/ppo_torchrl.py on the GPU sim: a few PPO iterations through TorchRL's Collector, with
no host sync per step from this library.

``train()`` of the example runs with its GPU configuration (one ``ManiSkillEnv(PushCube-v1,
num_envs=512, sim_backend="gpu")`` -> ``EpisodeMetrics``, ``Collector``, GAE, ``ClipPPOLoss``)
at a small size: 4 iterations of 16 steps, 25-step episodes (so that a few resets happen),
1 epoch. Every CUDA host sync that torch sees
(``torch.cuda.set_sync_debug_mode("warn")``) is recorded with its Python stack and
attributed (gpu_helpers.attribute_sync) to this library, ManiSkill, TorchRL (e.g. its
auto-reset's ``any_done`` check, one per step, and the policy's sampling) or the example's own
logging. The test fails if this library makes more syncs than one per masked reset (reading
which envs to reset) plus a few while building the env: none per step. The counts per culprit and the
library's sync sites are printed and recorded as junit properties.

Skipped without CUDA (``python3 scripts/gpu_check.py`` runs it on an accelerator machine).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from unittest import mock

import pytest
import torch

from gpu_helpers import CUDA, NUM_ENVS, count_host_syncs, requires_gpu, sync_counts, sync_sites
from maniskill_torchrl import ManiSkillWrapper

pytestmark = requires_gpu

ROOT = Path(__file__).resolve().parents[2]
ITERATIONS, STEPS, EPISODE_STEPS = 4, 16, 25
SET_UP = 8  # host syncs allowed once, while the env and its specs are built and first reset


def _load_example():
    spec = importlib.util.spec_from_file_location("ppo_torchrl_example", ROOT / "examples" / "ppo_torchrl.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ppo_collector_iterations_without_per_step_host_sync(tmp_path, record_property):
    ppo = _load_example()
    frames = NUM_ENVS * STEPS
    argv = [
        "--env-id",
        "PushCube-v1",
        "--device",
        "cuda" if CUDA else "cpu",
        "--num-envs",
        str(NUM_ENVS),
        "--num-steps",
        str(STEPS),
        "--total-frames",
        str(frames * ITERATIONS),
        "--epochs",
        "1",
        "--minibatch-size",
        str(max(frames // 2, 1)),
        "--max-episode-steps",
        str(EPISODE_STEPS),
        "--eval-every",
        "0",  # evaluation has its own tests (test_evaluate.py); here: the training loop
        "--out",
        str(tmp_path),
    ]
    if not CUDA:  # the CPU check of this test's code: the GPU configuration's code path on one env
        argv += ["--vec", "batched", "--hidden", "16"]
    args = ppo.parse_args(argv)
    assert args.vec == "batched" and args.repeat == 1

    # Count the resets that carry a "_reset" mask: each may read its mask back once (nonzero).
    resets = []
    masked_reset = ManiSkillWrapper._reset

    def counting_reset(self, tensordict=None, **kwargs):
        if tensordict is not None and "_reset" in tensordict.keys():
            resets.append(1)
        return masked_reset(self, tensordict, **kwargs)

    with count_host_syncs() as stacks, mock.patch.object(ManiSkillWrapper, "_reset", counting_reset):
        record = ppo.train(args)

    assert record["iteration"] == ITERATIONS
    assert record["frames"] == frames * ITERATIONS
    assert torch.isfinite(torch.tensor([record["loss_objective"], record["loss_critic"]])).all()
    assert (tmp_path / "ppo_checkpoint.pt").exists() and (tmp_path / "metrics.jsonl").exists()
    lines = (tmp_path / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == ITERATIONS
    # 64 steps with 25-step episodes: the last iteration (steps 48-63) sees episodes end at step 50.
    assert record["episodes"] > 0

    if not CUDA:
        # The training above ran on the CPU stand-in; its host syncs are only counted on CUDA.
        pytest.skip("host syncs are counted on CUDA only (the PPO run above passed)")
    env_steps = ITERATIONS * STEPS
    counts = sync_counts(stacks)
    lib_sites = sync_sites(stacks, "maniskill_torchrl")
    summary = {who: counts.get(who, 0) for who in ("maniskill_torchrl", "mani_skill", "torchrl", "user")}
    print(f"host syncs over {env_steps} env steps (x{NUM_ENVS} envs): {summary}")
    print("this library's sync sites:\n  " + "\n  ".join(lib_sites or ["none"]))
    print("TorchRL's sync sites:\n  " + "\n  ".join(sync_sites(stacks, "torchrl")))
    for who, n in summary.items():
        record_property(f"host_syncs_{who}", n)
    record_property("env_steps", env_steps)
    record_property("library_sync_sites", " | ".join(lib_sites))
    # The bound, from the code: one sync per masked reset (its nonzero), none per step
    # (EpisodeMetrics' running sum, the wrapper's step), plus SET_UP for building the env and its
    # specs. 512 envs with success terminations may reset some env at nearly every step, so the
    # bound follows the resets counted, not the steps.
    record_property("masked_resets", len(resets))
    bound = len(resets) + SET_UP
    assert counts.get("maniskill_torchrl", 0) <= bound, (
        f"maniskill_torchrl made {counts.get('maniskill_torchrl', 0)} host syncs over {env_steps} env steps "
        f"and {len(resets)} masked resets (at most {bound}: one per masked reset); where:\n  " + "\n  ".join(lib_sites)
    )
