"""Loading and sampling a ManiSkill trajectory file: ``ManiSkillExperienceReplay`` against
ManiSkill's ``ManiSkillTrajectoryDataset`` with a torch ``DataLoader``, on the same file.

The file is written here in ManiSkill's format (what ``RecordEpisode`` writes: ``obs`` with the
reset's row, ``actions``, flags, ``success``, ``rewards``), PickCube-v1 ``obs_mode="state"``
shapes, ``--episodes`` episodes of ``--steps`` steps, synthetic values (speed does not depend
on them). Contenders take turns (``common.interleave``), this process's CPU time, medians:

- loading (episodes/s): ``ManiSkillTrajectoryDataset(file)``; ``ManiSkillExperienceReplay`` the
  first time (read, lay out, memory-map to a fresh cache folder); and again from its cache;
- sampling (transitions/s) at batch 256: ``DataLoader(dataset, batch_size=256, shuffle=True)``
  (one iterator, ``num_workers=0``); ``ManiSkillExperienceReplay.sample()`` (random steps); the
  same with ``SliceSampler(slice_len=16)`` (16 slices of 16 steps, for sequence models).

Run: ``python -m benchmarks.bench_demos [--episodes 500] [--steps 50] [--rounds 7]``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

from benchmarks.common import Contender, interleave, report
from benchmarks.machine import machine_line


def write_file(path: Path, episodes: int, steps: int) -> None:
    import h5py
    import numpy as np

    rng = np.random.default_rng(0)
    meta = {"env_info": {"env_id": "PickCube-v1", "env_kwargs": {"obs_mode": "state"}}, "episodes": []}
    with h5py.File(path, "w") as f:
        for i in range(episodes):
            g = f.create_group(f"traj_{i}")
            g.create_dataset("obs", data=rng.standard_normal((steps + 1, 42), dtype=np.float32))
            g.create_dataset("actions", data=rng.uniform(-1, 1, (steps, 8)).astype(np.float32))
            g.create_dataset("terminated", data=np.zeros(steps, bool))
            g.create_dataset("truncated", data=np.arange(steps) == steps - 1)
            g.create_dataset("success", data=rng.random(steps) < 0.1)
            g.create_dataset("rewards", data=rng.random(steps, dtype=np.float32))
            meta["episodes"].append({"episode_id": i, "elapsed_steps": steps, "success": True})
    path.with_suffix(".json").write_text(json.dumps(meta))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--batches", type=int, default=50, help="batches of 256 per sampling round")
    args = parser.parse_args(argv)

    import torch
    from mani_skill.trajectory.dataset import ManiSkillTrajectoryDataset
    from torch.utils.data import DataLoader
    from torchrl.data.replay_buffers import SliceSampler

    from maniskill_torchrl.data import ManiSkillExperienceReplay

    torch.set_num_threads(1)
    print(machine_line())

    def compare(title: str, contenders: list, unit: str) -> None:
        """Interleaved rounds, the table against the first contender, and units/s per contender."""
        results = interleave(contenders, rounds=args.rounds, warmup=1, clock="cpu")
        print(f"\n{title}")
        print(report(results, baseline=contenders[0].name, unit=unit))
        for name, res in results.items():
            print(f"  {name}: {1 / res.median:,.0f} {unit}s/s")

    work = Path(tempfile.mkdtemp(prefix="bench_demos-"))
    try:
        path = work / "trajectory.h5"
        write_file(path, args.episodes, args.steps)
        n = args.episodes
        print(f"{n} episodes x {args.steps} steps, {path.stat().st_size / 2**20:.1f} MiB")
        caches = iter(range(10**6))

        def load_maniskill() -> int:
            ManiSkillTrajectoryDataset(str(path))
            return n

        def load_ours_first() -> int:
            ManiSkillExperienceReplay(path, 256, root=work / f"cache{next(caches)}")
            return n

        ManiSkillExperienceReplay(path, 256, root=work / "cache")  # the cache the next one reads

        def load_ours_cached() -> int:
            ManiSkillExperienceReplay(path, 256, root=work / "cache")
            return n

        import logging

        logging.disable(logging.WARNING)
        import tqdm as _tqdm  # ManiSkill's loader prints a progress bar per load

        _tqdm.tqdm.__init__.__kwdefaults__ = {**(_tqdm.tqdm.__init__.__kwdefaults__ or {}), "disable": True}
        compare(
            "loading",
            [
                Contender("ManiSkillTrajectoryDataset", load_maniskill),
                Contender("ManiSkillExperienceReplay, first load", load_ours_first),
                Contender("ManiSkillExperienceReplay, cached", load_ours_cached),
            ],
            "episode",
        )

        dataset = ManiSkillTrajectoryDataset(str(path))
        loader = iter(DataLoader(dataset, batch_size=256, shuffle=True, drop_last=True))
        ours = ManiSkillExperienceReplay(path, 256, root=work / "cache")
        slices = ManiSkillExperienceReplay(
            path, 256, root=work / "cache", sampler=SliceSampler(slice_len=16, traj_key=("collector", "traj_ids"))
        )

        def sample_loader() -> int:
            nonlocal loader
            for _ in range(args.batches):
                try:
                    next(loader)
                except StopIteration:
                    loader = iter(DataLoader(dataset, batch_size=256, shuffle=True, drop_last=True))
                    next(loader)
            return 256 * args.batches

        def sample(buffer):
            def run() -> int:
                for _ in range(args.batches):
                    buffer.sample()
                return 256 * args.batches

            return run

        compare(
            "sampling, batch 256",
            [
                Contender("DataLoader(ManiSkillTrajectoryDataset)", sample_loader),
                Contender("ManiSkillExperienceReplay.sample()", sample(ours)),
                Contender("ManiSkillExperienceReplay + SliceSampler(16)", sample(slices)),
            ],
            "transition",
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
