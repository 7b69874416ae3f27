"""TorchRL's own sota trainer scripts, unmodified, on ManiSkill (issue 62).

``tests/configs/sota/`` holds ``sota-implementations/{sac,ppo}_trainer`` of pytorch/rl (its README names the
commit). Their own target, ``make test-sota`` (about 6 minutes on 2 cores: each
run a fresh process tree of TorchRL's workers, each importing torch, TorchRL and ManiSkill). Each runs as a TorchRL
user starts it, ``python train.py env@training_env.create_env_fn.base_env=maniskill
...``, in a subprocess with a timeout (a hang fails the test, never CI): the library's nodes come from its
``hydra_plugins`` module, the env is built inside TorchRL's ``_partial_`` node and pickled into the collectors'
workers as its constructor. Frame budgets are tiny: these check that the pipeline runs, not that it learns.

Overrides beyond the env's, each needed by TorchRL 0.14.1 whatever the env (Pendulum-v1 too):
``collector.track_policy_version=false`` (0.14.1 refuses policy-version tracking over a ``BatchedEnvBase``),
``trainer.logger=...`` (SAC's default logger is wandb; PPO's YAML gives the csv logger ``offline``/``project``
keys that 0.14.1's ``CSVLoggerConfig`` lacks, so ``logger=wandb`` composes it and ``trainer.logger`` builds a CSV
logger), and PPO's ``trainer.weight_update_map`` (0.14.1's PPOTrainer asks for it when the collector has weight
sync schemes, as multi_async has; without it the trainer raises after the collector's workers started, and the
main process then never exits: a TorchRL hang, whatever the env, that the timeout here turns into a failure).
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

SOTA = Path(__file__).resolve().parents[1] / "configs" / "sota"
TIMEOUT = 480  # seconds: a hung worker or main process fails here
ENV = "env@training_env.create_env_fn.base_env=maniskill"
BASE = "training_env.create_env_fn.base_env"


def _run(args: list[str], cwd: Path, timeout: int = TIMEOUT) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as err:  # the process group is killed by subprocess.run
        out = (err.stdout or b"")[-3000:], (err.stderr or b"")[-3000:]
        pytest.fail(f"{args[1]} ran past {timeout} s (a hang?): {out}")


def test_sac_sota_trainer_multi_async(tmp_path):
    """TorchRL's SAC sota trainer, its default collector (multi_async, 4 workers cut to 2), on PushCube-v1."""
    out = _run(
        [
            sys.executable,
            str(SOTA / "sac_trainer" / "train.py"),
            ENV,
            f"{BASE}.env_name=PushCube-v1",
            f"{BASE}.obs_mode=state",
            "networks.policy_network.in_features=35",
            "networks.policy_network.out_features=16",
            "networks.value_network.in_features=35",
            "networks.qvalue_network.in_features=43",
            "trainer.logger=null",
            "collector.track_policy_version=false",
            "collector.total_frames=200",
            "collector.frames_per_batch=100",
            "collector.init_random_frames=100",
            "collector.num_workers=2",
            "training_env.num_workers=2",
            "trainer.optim_steps_per_batch=2",
            "replay_buffer.batch_size=16",
            f"hydra.run.dir={tmp_path}",
        ],
        tmp_path,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    assert "200/200" in out.stderr, out.stderr[-2000:]


def test_ppo_sota_trainer(tmp_path):
    """TorchRL's PPO sota trainer (multi_async over a batched_env of one unbatched env) on PullCube-v1, its CSV
    logs written where ``scripts/trainer_csv.py`` reads them."""
    out = _run(
        [
            sys.executable,
            str(SOTA / "ppo_trainer" / "train.py"),
            ENV,
            f"{BASE}.env_name=PullCube-v1",
            f"{BASE}.obs_mode=state",
            "networks.policy_network.in_features=35",
            "networks.policy_network.out_features=16",
            "networks.value_network.in_features=35",
            "logger=wandb",
            "trainer.logger={_target_:torchrl.record.loggers.csv.CSVLogger,exp_name:ppo_sota,log_dir:csv_logs}",
            "trainer.weight_update_map={policy:loss_module.actor_network}",
            "collector.track_policy_version=false",
            "collector.total_frames=256",
            "trainer.total_frames=256",
            "collector.frames_per_batch=128",
            "replay_buffer.storage.max_size=128",
            "replay_buffer.batch_size=64",
            "trainer.num_epochs=1",
            f"hydra.run.dir={tmp_path}",
        ],
        tmp_path,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    logs = sorted((tmp_path / "csv_logs").glob("ppo_sota*/scalars/*.csv"))
    assert logs, sorted(str(p) for p in tmp_path.rglob("*"))
    with logs[0].open() as f:
        rows = list(csv.reader(f))
    assert rows and int(float(rows[-1][0])) > 0


_COLLECTORS = """
import functools, sys
from torchrl.collectors import Collector, MultiAsyncCollector, MultiSyncCollector
from torchrl.envs import StepCounter, TransformedEnv
from torchrl.trainers.algorithms.configs.envs import make_batched_env

from maniskill_torchrl import ManiSkillEnv, ManiSkillWrapper

if sys.argv[1] == "wrapper":
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401

    base = ManiSkillWrapper(gym.make("PushCube-v1", obs_mode="state", render_backend="cpu"), batch_size=[])
    kinds = [sys.argv[2]]
else:
    base = ManiSkillEnv("PushCube-v1", obs_mode="state", batch_size=[])
    kinds = ["sync", "multi_sync", "multi_async"]
# TorchRL's sota layout: batched_env -> create_env_fn: a partial of transformed_env holding the live base env.
make = functools.partial(TransformedEnv, base_env=base, transform=StepCounter())
for kind in kinds:
    if kind == "sync":  # the ParallelEnv's workers unpickle the env
        collector = Collector(make_batched_env(make, num_workers=2), policy=None, frames_per_batch=20, total_frames=40)
    else:  # the collector's worker unpickles the ParallelEnv, whose worker unpickles the env
        cls = MultiSyncCollector if kind == "multi_sync" else MultiAsyncCollector
        env = make_batched_env(make, num_workers=1)
        collector = cls([env], policy=None, frames_per_batch=20, total_frames=40)
    frames = sum(batch.numel() for batch in collector)
    collector.shutdown()
    print("RESULT", kind, frames, flush=True)  # TorchRL's logger writes to stdout too
"""


def test_a_live_env_in_a_partial_node_crosses_every_collector(tmp_path):
    """The live ManiSkillEnv of a ``_partial_`` node pickles as its constructor: TorchRL's sync, multi_sync and
    multi_async collectors over a ParallelEnv of it (each worker a new env) run."""
    out = _run([sys.executable, "-c", _COLLECTORS, "env"], tmp_path, timeout=540)
    assert out.returncode == 0, out.stderr[-4000:]
    results = [line.split()[1:] for line in out.stdout.splitlines() if line.startswith("RESULT ")]
    assert results == [["sync", "40"], ["multi_sync", "40"], ["multi_async", "40"]], out.stdout[-2000:]


@pytest.mark.parametrize("kind", ["sync", "multi_async"])
def test_a_wrapper_that_cannot_be_rebuilt_fails_in_the_main_process(tmp_path, kind):
    """A ManiSkillWrapper around a user's gym env has nothing to rebuild it from: the main process raises the
    library's "cannot pickle" TypeError (multi_async: chained under TorchRL's "non-serializable object"), fast,
    never a silently lost worker and a hang."""
    out = _run([sys.executable, "-c", _COLLECTORS, "wrapper", kind], tmp_path, timeout=240)
    assert out.returncode != 0
    assert "cannot pickle 'ManiSkillWrapper' object: it holds a live ManiSkill sim" in out.stderr, out.stderr[-3000:]
