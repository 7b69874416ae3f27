"""EpisodeMetrics' step on a large batch: its two summations against the running sum of
``ManiSkillVectorEnv(record_metrics=True)``, and their op counts.

One ``EpisodeMetrics._step`` on envs whose episodes are ``0 .. max-len`` steps long (4096 envs,
lengths spread up to 1000 by default: about 980 distinct lengths), on CPU tensors:

- ``ManiSkillVectorEnv``: its bookkeeping, inlined (``returns += rew``, ``success_once |=``,
  ``fail_once |=``, the clones and the mean it reports): the GPU sim's anchor;
- ``running``: ``EpisodeMetrics(summation="running")``, the default off the CPU;
- ``numpy``: ``EpisodeMetrics(summation="numpy")``, the CPU's default (one numpy reduction per
  env per step, bit for bit ``CPUGymWrapper``).

Each contender's aten ops per step are counted too (a dispatch mode): on CUDA every op is a
kernel launch, and the ops that read a value back (``nonzero``, ``item``...) are host syncs.
Interleaved (``common.interleave``), this process's CPU time, medians over rounds.

Run: ``python -m benchmarks.bench_episode_metrics [--envs 4096] [--max-len 1000] [--rounds 15]``.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from benchmarks.common import Contender, interleave, report
from benchmarks.machine import machine_line

HERE = Path(__file__).resolve().parent
SYNC_OPS = ("nonzero", "is_nonzero", "_local_scalar_dense", "item", "equal")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=4096)
    parser.add_argument("--max-len", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--calls", type=int, default=10, help="steps per round")
    args = parser.parse_args(argv)

    import torch
    from tensordict import TensorDict
    from torch.utils._python_dispatch import TorchDispatchMode
    from torchrl.data import Categorical, Composite, Unbounded
    from torchrl.envs import EnvBase, TransformedEnv

    from maniskill_torchrl import EpisodeMetrics

    torch.set_num_threads(1)
    print(machine_line())
    n = args.envs

    class Batch(EnvBase):
        """Specs only: the transform needs a parent with reward, success and fail."""

        def __init__(self):
            super().__init__(batch_size=[n])
            self.observation_spec = Composite(
                success=Categorical(2, shape=(n,), dtype=torch.bool),
                fail=Categorical(2, shape=(n,), dtype=torch.bool),
                shape=(n,),
            )
            self.action_spec = Unbounded((n, 1))
            self.reward_spec = Unbounded((n, 1))

        def _step(self, td):
            raise NotImplementedError

        def _reset(self, td=None, **kwargs):
            raise NotImplementedError

        def _set_seed(self, seed):
            return seed

    g = torch.Generator().manual_seed(0)
    lengths = torch.randint(0, args.max_len, (n,), generator=g)
    print(f"{n} envs, {lengths.unique().numel()} distinct episode lengths up to {args.max_len}")
    nxt = TensorDict(
        reward=torch.randn(n, 1, generator=g),
        success=torch.rand(n, generator=g) < 0.1,
        fail=torch.rand(n, generator=g) < 0.1,
        batch_size=[n],
    )

    envs = {s: TransformedEnv(Batch(), EpisodeMetrics(summation=s)) for s in ("running", "numpy")}
    transforms = {s: env.transform for s, env in envs.items()}
    stats_root = {}
    for summation, t in transforms.items():
        t._make_stats()
        ep = t._stats.zeros()
        ep["episode_len"] = lengths.clone()
        ep["return"] = torch.randn(n, generator=g)
        if summation == "numpy":  # the history the lengths stand for
            for k in range(int(lengths.max())):
                t._stats._numpy.add(torch.randn(n, generator=g), torch.full((n,), k))
        stats_root[summation] = TensorDict(episode=ep, batch_size=[n])

    returns = torch.zeros(n)
    success_once = torch.zeros(n, dtype=torch.bool)
    fail_once = torch.zeros(n, dtype=torch.bool)
    elapsed = lengths.to(torch.int32)

    def vector_env_step():
        nonlocal returns, success_once, fail_once
        rew = nxt["reward"].squeeze(-1)
        returns += rew
        success_once = success_once | nxt["success"]
        fail_once = fail_once | nxt["fail"]
        info = {"success_once": success_once.clone(), "fail_once": fail_once.clone(), "return": returns.clone()}
        info["episode_len"] = (elapsed + 1).clone()
        info["reward"] = info["return"] / info["episode_len"]
        return info

    def metrics_step(summation):
        t, root = transforms[summation], stats_root[summation]
        return lambda: t._step(root, nxt.clone(False))

    steps = {
        "ManiSkillVectorEnv": vector_env_step,
        "EpisodeMetrics running": metrics_step("running"),
        "EpisodeMetrics numpy": metrics_step("numpy"),
    }

    class CountOps(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.ops = Counter()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.ops[func.overloadpacket.__name__] += 1
            return func(*args, **(kwargs or {}))

    print("\naten ops per step (host syncs on CUDA in brackets):")
    for name, step in steps.items():
        with CountOps() as c:
            step()
        syncs = sum(c.ops[s] for s in SYNC_OPS)
        print(f"  {name:<24} {sum(c.ops.values()):>6} ops  [{syncs} syncs]")

    def timed(step):
        def run():
            for _ in range(args.calls):
                step()
            return args.calls

        return run

    results = interleave(
        [Contender(name, timed(step)) for name, step in steps.items()], rounds=args.rounds, warmup=2, clock="cpu"
    )
    print()
    print(report(results, baseline="ManiSkillVectorEnv", unit="step"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
