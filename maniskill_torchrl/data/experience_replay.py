""":class:`ManiSkillExperienceReplay`: a ManiSkill trajectory file as a TorchRL replay buffer."""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import shutil
import socket
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

# Bumped when the layout written to the cache changes, so that old caches are rebuilt (and,
# being another version of the same source, removed). 2: env_states loaded.
_LAYOUT_VERSION = 2
_TMP = ".tmp."  # in the name of a copy being written: <name>.tmp.<host>.<pid>.<random>
_OLD = ".old."  # in the name of a copy being removed (download="force")


def _default_root() -> Path:
    return Path(os.path.expanduser("~")) / ".cache" / "torchrl" / "maniskill"


def _digest(what: Any) -> str:
    return hashlib.sha1(json.dumps(what).encode()).hexdigest()[:12]


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


class ManiSkillExperienceReplay(BaseDatasetExperienceReplay):
    """A ManiSkill trajectory file (``.h5`` + ``.json``) as a TorchRL replay buffer.

    The file's episodes are laid out as ``ManiSkillEnv(env_id, batch_size=[], **env_kwargs)``
    steps (:mod:`maniskill_torchrl.data.trajectory_file` lists the keys, ``"env_states"``
    included where the file has them), concatenated along the batch, with
    ``("collector", "traj_ids")`` holding each step's episode id, and memory-mapped once under
    ``root``: later loads of the same file (same size and modification time, same options) read
    the cache, and thousands of episodes never need to fit in RAM. ``storage[:]`` reads like a
    collector batch; a policy trained on it runs on the env unchanged, and
    ``ManiSkillEnv(rb.env_id, **rb.env_kwargs)`` is the env the file was recorded on (its time
    limit included).

    The cache, as TorchRL's datasets keep theirs: every copy made from one file lives in
    :attr:`data_path_root` (``<root>/<file stem>-<hash of the file's path>``), the current one in
    :attr:`data_path`. A copy is written to a folder of its own process
    (``<name>.tmp.<host>.<pid>.<random>``) and renamed into place, so that several processes
    loading the same file at once (training workers on first use) never read or remove one
    another's half-written files: the first rename wins and the others use its copy. When the
    file changes (size or modification time), the new copy replaces the copies of the old file
    under ``data_path_root``; :meth:`delete` removes them all.

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
        download (bool or "force"): as in TorchRL's datasets, with the local file as the source
            (nothing is fetched from the network): ``True`` (default) builds the cache from the
            file when it is missing, ``"force"`` rebuilds it, and ``False`` only reads a cache
            built before (a ``FileNotFoundError`` says so if there is none).
        split_trajs (bool): as in TorchRL's datasets: ``True`` stores one padded row per episode
            (batch ``[episodes, longest]``, from :func:`torchrl.collectors.utils.split_trajectories`)
            with ``("collector", "mask")`` marking the real steps; ``sample()`` then draws
            episodes. Default ``False``: the steps one after another.
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
        download: bool | str = True,
        split_trajs: bool = False,
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
        if download not in (True, False, "force"):
            raise ValueError(
                f"download must be True (build the cache if missing), 'force' (rebuild it) or False "
                f"(read an existing cache only), got {download!r}."
            )
        self.success_only = bool(success_only)
        self.num_episodes = num_episodes
        self.download = download
        self.split_trajs = bool(split_trajs)
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
            self._version, self._key = self._cache_key()
            data = None
            if download != "force" and self._is_downloaded():
                try:
                    data = TensorDict.load_memmap(self.data_path)
                except (FileNotFoundError, RuntimeError):
                    if not download:
                        raise
                    # Removed while read (another process's "force" or stale clean-up; tensordict
                    # reports a missing .memmap as a RuntimeError): built again below. A copy
                    # that is really broken fails again when the built one is read.
                    data = None
            if data is None:
                if not download:
                    raise FileNotFoundError(
                        f"No cache of {self.file_path} under {self.data_path_root} (download=False reads only a "
                        "cache built before): pass download=True (the default) to build it from the file."
                    )
                data = self._convert(trajectories, replace=download == "force")
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

    def _cache_key(self) -> tuple[str, str]:
        """(the file's version: size, modification time, layout; the selection: episodes, split)."""
        stat = self.file_path.stat()
        version = _digest([stat.st_size, stat.st_mtime_ns, _LAYOUT_VERSION])
        selection = _digest([[int(e["episode_id"]) for e in self.episodes], self.split_trajs])
        return version, selection

    @property
    def data_path_root(self) -> Path:
        """The folder of every cached copy of this file (all its versions and selections)."""
        source = _digest(str(self.file_path.resolve()))
        return Path(self.root) / f"{self.file_path.stem}-{source}"

    @property
    def data_path(self) -> Path:
        """The folder of this dataset's copy (the file's current version, these episodes, this layout)."""
        return self.data_path_root / f"{self._version}-{self._key}"

    def _is_downloaded(self) -> bool:
        return (self.data_path / "meta.json").exists()

    def _convert(self, trajectories: TrajectoryFile, replace: bool) -> TensorDict:
        """Every selected episode, concatenated (split per episode with ``split_trajs``) and
        memory-mapped under :attr:`data_path`, then the copies of older versions removed."""
        steps = torch.cat([trajectories.episode(info) for info in self.episodes])
        if self.split_trajs:
            from torchrl.collectors.utils import split_trajectories

            steps = split_trajectories(steps, trajectory_key=("collector", "traj_ids"))
        final = self.data_path
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.with_name(f"{final.name}{_TMP}{socket.gethostname()}.{os.getpid()}.{secrets.token_hex(4)}")
        try:
            steps.memmap_(tmp)
            if replace:
                self._remove(final)
            try:
                os.replace(tmp, final)  # atomic: a half-written copy is never read
            except OSError:
                # Another process renamed its complete copy into place first: use it.
                if not (final / "meta.json").exists():
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        self._remove_stale()
        return TensorDict.load_memmap(final)

    @staticmethod
    def _remove(folder: Path) -> None:
        """Removes a cached copy: renamed aside first, so that no reader finds it half-removed."""
        aside = folder.with_name(f"{folder.name}{_OLD}{os.getpid()}.{secrets.token_hex(4)}")
        try:
            folder.rename(aside)
        except FileNotFoundError:
            return
        shutil.rmtree(aside, ignore_errors=True)

    def _remove_stale(self) -> None:
        """Removes the copies of other versions of this file (never this version's, never
        another file's), and the temporary folders of processes on this host that died."""
        host = socket.gethostname()
        for entry in self.data_path_root.iterdir():
            name = entry.name
            if _TMP in name:
                # Only another process's unfinished copy: removed once that process is gone.
                writer, _, rest = name.partition(_TMP)[2].rpartition(".")[0].rpartition(".")
                if writer != host or not rest.isdigit() or _pid_alive(int(rest)):
                    continue
                shutil.rmtree(entry, ignore_errors=True)
            elif _OLD in name:
                continue  # being removed by its own process
            elif not name.startswith(f"{self._version}-"):
                self._remove(entry)

    def delete(self) -> None:
        """Removes every cached copy of this file under ``root``: this one, those of its older
        versions, and those of its other selections (``success_only``, ``num_episodes``,
        ``split_trajs``). The loaded data stays readable in this process; the next load rebuilds."""
        shutil.rmtree(self.data_path_root, ignore_errors=True)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({str(self.file_path)!r}, env_id={self.env_id!r}, "
            f"episodes={len(self.episodes)}, steps={len(self)})"
        )
