""":class:`ManiSkillExperienceReplay`: a ManiSkill trajectory file as a TorchRL replay buffer."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.data.datasets.common import BaseDatasetExperienceReplay
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import TensorStorage
from torchrl.data.replay_buffers.writers import ImmutableDatasetWriter, Writer

from maniskill_torchrl.data.trajectory_file import TrajectoryFile

__all__ = ["ManiSkillExperienceReplay"]

# Bumped when the layout written to the cache changes, so that old caches are rebuilt.
_LAYOUT_VERSION = 1


def _default_root() -> Path:
    return Path(os.path.expanduser("~")) / ".cache" / "torchrl" / "maniskill"


class ManiSkillExperienceReplay(BaseDatasetExperienceReplay):
    """A ManiSkill trajectory file (``.h5`` + ``.json``) as a TorchRL replay buffer.

    The file's episodes are laid out as ``ManiSkillEnv(env_id, batch_size=[], **env_kwargs)``
    steps (:mod:`maniskill_torchrl.data.trajectory_file` lists the keys), concatenated along the
    batch, with ``("collector", "traj_ids")`` holding each step's episode id, and memory-mapped
    once under ``root``: later loads of the same file (same size and modification time, same
    options) read the cache, and thousands of episodes never need to fit in RAM. ``storage[:]``
    reads like a collector batch; a policy trained on it runs on the env unchanged.

    Read directly rather than through TorchRL's LeRobot reader after ManiSkill's
    ``convert_to_lerobot``: the direct path keeps ManiSkill's own keys, nesting and dtypes (and
    needs no conversion step or video decoding), which is what makes the layout the env's.

    Args:
        path: the ``.h5`` file (its ``.json`` beside it).
        batch_size: the sample size of :meth:`sample`.

    Keyword Args:
        env_id (str, optional): the task the file must hold (a clear error otherwise).
        success_only (bool): keep only the episodes that end in success.
        num_episodes (int, optional): keep the first ``num_episodes`` (after ``success_only``).
        root (path, optional): the cache folder (default ``~/.cache/torchrl/maniskill``).
        sampler, writer, collate_fn, pin_memory, prefetch, transform: as in
            :class:`~torchrl.data.TensorDictReplayBuffer`; for episode slices (sequence models)
            pass ``sampler=SliceSampler(slice_len=..., traj_key=("collector", "traj_ids"))``.

    Examples:
        >>> from torchrl.data.replay_buffers import SliceSampler
        >>> from maniskill_torchrl.data import ManiSkillExperienceReplay
        >>> demos = ManiSkillExperienceReplay("demos/PickCube-v1/trajectory.state.pd_joint_pos.h5", 256)
        >>> batch = demos.sample()  # doctest: +SKIP
        >>> batch["observation"].shape, batch["next", "reward"].shape  # doctest: +SKIP
    """

    def __init__(
        self,
        path: str | Path,
        batch_size: int,
        *,
        env_id: str | None = None,
        success_only: bool = False,
        num_episodes: int | None = None,
        root: str | Path | None = None,
        sampler: Sampler | None = None,
        writer: Writer | None = None,
        collate_fn: Callable | None = None,
        pin_memory: bool = False,
        prefetch: int | None = None,
        transform: Any = None,
    ) -> None:
        self.file_path = Path(path)
        if num_episodes is not None and (not isinstance(num_episodes, int) or num_episodes < 1):
            raise ValueError(f"num_episodes must be a positive int or None, got {num_episodes!r}.")
        self.success_only = bool(success_only)
        self.num_episodes = num_episodes
        self.root = root if root is not None else _default_root()
        trajectories = TrajectoryFile(self.file_path)
        try:
            if env_id is not None and trajectories.env_id != env_id:
                raise ValueError(f"{self.file_path} holds episodes of {trajectories.env_id!r}, not {env_id!r}.")
            self.env_id = trajectories.env_id
            self.env_kwargs = trajectories.env_kwargs
            self.episodes = self._selected(trajectories.episodes)
            if not self.episodes:
                raise ValueError(
                    f"{self.file_path}: no episode left (success_only={success_only}, num_episodes={num_episodes})."
                )
            self._key = self._cache_key()
            if self._is_downloaded():
                data = TensorDict.load_memmap(self.data_path)
            else:
                data = self._convert(trajectories)
        finally:
            trajectories.close()
        super().__init__(
            storage=TensorStorage(data),
            sampler=sampler,
            writer=writer if writer is not None else ImmutableDatasetWriter(),
            collate_fn=collate_fn,
            pin_memory=pin_memory,
            prefetch=prefetch,
            batch_size=batch_size,
            transform=transform,
        )

    # ------------------------------------------------------------------ the dataset
    def _selected(self, episodes: list[dict]) -> list[dict]:
        if self.success_only:
            episodes = [e for e in episodes if bool(e.get("success", False))]
        if self.num_episodes is not None:
            episodes = episodes[: self.num_episodes]
        return episodes

    def _cache_key(self) -> str:
        stat = self.file_path.stat()
        ids = [int(e["episode_id"]) for e in self.episodes]
        what = [str(self.file_path.resolve()), stat.st_size, stat.st_mtime_ns, ids, _LAYOUT_VERSION]
        return hashlib.sha1(json.dumps(what).encode()).hexdigest()[:16]

    @property
    def data_path_root(self) -> Path:
        return Path(self.root)

    @property
    def data_path(self) -> Path:
        return self.data_path_root / f"{self.file_path.stem}-{self._key}"

    def _is_downloaded(self) -> bool:
        return (self.data_path / "meta.json").exists()

    def _convert(self, trajectories: TrajectoryFile) -> TensorDict:
        """Every selected episode, concatenated and memory-mapped under :attr:`data_path`."""
        steps = torch.cat([trajectories.episode(info) for info in self.episodes])
        tmp = self.data_path.with_name(self.data_path.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        steps.memmap_(tmp)
        shutil.rmtree(self.data_path, ignore_errors=True)
        tmp.rename(self.data_path)  # a half-written cache is never read
        return TensorDict.load_memmap(self.data_path)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({str(self.file_path)!r}, env_id={self.env_id!r}, "
            f"episodes={len(self.episodes)}, steps={len(self)})"
        )
