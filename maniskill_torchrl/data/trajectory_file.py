"""ManiSkill's trajectory files (``.h5`` + ``.json``, what ``RecordEpisode``, the motion planners
and ``replay_trajectory`` write) read into TensorDicts laid out as the library's env steps.

One episode ``traj_<i>`` of ``T`` steps holds ``obs`` (``T + 1`` rows, the reset's first;
nested groups for dict observations), ``actions``, ``terminated``, ``truncated``, optionally
``success``, ``fail`` and ``rewards`` (``T`` rows), and ``env_states`` (``T + 1`` rows). It becomes
a TensorDict of batch ``[T]`` with the keys of a ``ManiSkillEnv(env_id, batch_size=[])`` rollout:

- the observation at the root (``"observation"`` for a flat one, the nested keys of a dict one)
  and in ``"next"``, dtypes as stored (ManiSkill's own);
- ``"action"`` (``("action", agent)`` for several agents);
- ``("next", "reward")`` ``[T, 1]`` float32 where the file has rewards; ``terminated`` /
  ``truncated`` / ``done`` ``[T, 1]`` bool at the root (False: no step ends before its own) and
  in ``"next"``;
- the infos the file keeps, ``success`` and ``fail``, and ``elapsed_steps`` (int32, ManiSkill's),
  at the root (the previous step's; False / 0 after the reset) and in ``"next"``;
- ``("collector", "traj_ids")`` int64: the episode id (what TorchRL's ``SliceSampler`` reads);
- where the file has them, ``"env_states"`` (ManiSkill's ``get_state_dict()`` layout: ``actors``,
  ``articulations``) laid out as :class:`~maniskill_torchrl.transforms.EnvStates` lays out a
  rollout: row ``t`` of the file's ``T + 1`` at the root (the state step ``t`` starts from, the
  one its observation shows) and row ``t + 1`` in ``"next"`` (the state after the step). One
  step's ``data[i]["env_states"]`` is what ``env.reset_to_state`` takes to go back to step ``i``.

Other task infos (``is_grasped``...) are not in ManiSkill's files, so they are not here.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

__all__ = ["TrajectoryFile", "episode_tensordict"]

_REQUIRED = ("actions", "terminated", "truncated")


class TrajectoryFile:
    """A ManiSkill trajectory file pair, opened and checked.

    Args:
        path: the ``.h5`` file; its ``.json`` is the same path with that suffix.

    Raises:
        FileNotFoundError: a file of the pair is missing.
        ValueError: the ``.json`` is not ManiSkill's (no ``env_info`` / ``episodes``), or an
            episode it lists is not in the ``.h5``, or lacks ``actions`` / flags / observations.
        OSError: the ``.h5`` cannot be read (truncated, or not HDF5), with its path.
    """

    def __init__(self, path: str | Path) -> None:
        import h5py

        self.path = Path(path)
        self.json_path = self.path.with_suffix(".json")
        for p, what in ((self.path, "trajectory file"), (self.json_path, "trajectory metadata (.json)")):
            if not p.exists():
                raise FileNotFoundError(
                    f"ManiSkill {what} {p} not found: ManiSkill writes an .h5 and a .json of the same name "
                    "(RecordEpisode, replay_trajectory, the motion planners); pass the .h5 path."
                )
        try:
            meta = json.loads(self.json_path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{self.json_path} is not valid JSON ({e}).") from e
        if not isinstance(meta, dict) or "env_info" not in meta or "episodes" not in meta:
            raise ValueError(
                f"{self.json_path} is not a ManiSkill trajectory .json: it needs 'env_info' and 'episodes'."
            )
        self.meta = meta
        try:
            self.h5 = h5py.File(self.path, "r")
        except OSError as e:
            raise OSError(
                f"Cannot read {self.path} as HDF5 ({e}): the file is truncated or is not a ManiSkill .h5."
            ) from e

    @property
    def env_id(self) -> str:
        return self.meta["env_info"]["env_id"]

    @property
    def env_kwargs(self) -> dict:
        """The ``gym.make`` arguments the episodes were recorded with (``obs_mode``, ``control_mode``...).

        ``max_episode_steps`` is added from ``env_info`` where ``env_kwargs`` lacks it:
        ``RecordEpisode`` records the time limit only there, and ``ManiSkillEnv(env_id,
        **env_kwargs)`` must end its episodes where the recorded ones ended.
        """
        info = self.meta["env_info"]
        kwargs = dict(info.get("env_kwargs") or {})
        if kwargs.get("max_episode_steps") is None and info.get("max_episode_steps") is not None:
            kwargs["max_episode_steps"] = info["max_episode_steps"]
        return kwargs

    @property
    def episodes(self) -> list[dict]:
        return list(self.meta["episodes"])

    def episode(self, info: Mapping) -> TensorDict:
        """Episode ``info`` (an entry of :attr:`episodes`) laid out as env steps (see the module)."""
        key = f"traj_{info['episode_id']}"
        if key not in self.h5:
            raise ValueError(
                f"{self.path}: episode {info['episode_id']} is listed in the .json but {key} is not in the .h5."
            )
        group = self.h5[key]
        missing = [k for k in _REQUIRED if k not in group]
        if missing:
            raise ValueError(f"{self.path}: {key} has no {missing}: not a ManiSkill trajectory.")
        # RecordEpisode(obs_mode="none") writes an empty ``obs`` group: no observation either.
        if "obs" not in group or not _has_data(group["obs"]):
            raise ValueError(
                f"{self.path}: {key} has no observations (ManiSkill distributes its demos without them). "
                "Add them once with ManiSkill's replay: python -m mani_skill.trajectory.replay_trajectory "
                f"--traj-path {self.path} -o state --save-traj (then load the file it writes)."
            )
        return episode_tensordict(group, int(info["episode_id"]))

    def close(self) -> None:
        self.h5.close()


def _has_data(node: Any) -> bool:
    """Whether an h5 node is a dataset or a group holding one at any depth."""
    import h5py

    if isinstance(node, h5py.Group):
        return any(_has_data(node[k]) for k in node.keys())
    return True


def _read(node: Any) -> Any:
    """An h5 group or dataset as nested dicts of tensors (numpy arrays read whole)."""
    import h5py

    if isinstance(node, h5py.Group):
        return {k: _read(node[k]) for k in node.keys()}
    return torch.from_numpy(np.asarray(node[()]))


def _leaves(tree: Any) -> list:
    if isinstance(tree, dict):
        return [leaf for v in tree.values() for leaf in _leaves(v)]
    return [tree]


def _rows(tree: Any, index: slice) -> Any:
    if isinstance(tree, dict):
        return {k: _rows(v, index) for k, v in tree.items()}
    return tree[index]


def episode_tensordict(group: Any, episode_id: int) -> TensorDict:
    """One ``traj_<i>`` group as a TensorDict of batch ``[T]`` (the module says which keys)."""
    actions = _read(group["actions"])
    terminated = _read(group["terminated"]).bool()
    truncated = _read(group["truncated"]).bool()
    n = terminated.shape[0]
    obs = _read(group["obs"])
    first = obs if isinstance(obs, dict) else {"observation": obs}
    root: dict = dict(_rows(first, slice(0, n)))
    nxt: dict = dict(_rows(first, slice(1, n + 1)))
    root["action"] = actions
    false = torch.zeros(n, 1, dtype=torch.bool)
    root.update(terminated=false, truncated=false, done=false)
    nxt.update(
        terminated=terminated.reshape(n, 1),
        truncated=truncated.reshape(n, 1),
        done=(terminated | truncated).reshape(n, 1),
    )
    if "rewards" in group:
        nxt["reward"] = _read(group["rewards"]).to(torch.float32).reshape(n, 1)
    for flag in ("success", "fail"):
        if flag in group:
            value = _read(group[flag]).bool()
            nxt[flag] = value
            root[flag] = torch.cat([torch.zeros(1, dtype=torch.bool), value[:-1]])
    steps = torch.arange(n + 1, dtype=torch.int32)
    root["elapsed_steps"], nxt["elapsed_steps"] = steps[:-1], steps[1:]
    root["collector"] = {"traj_ids": torch.full((n,), episode_id, dtype=torch.int64)}
    if "env_states" in group and _has_data(group["env_states"]):
        # T + 1 rows: the state each step starts from at the root, the one it ends in in "next".
        states = _read(group["env_states"])
        rows = {leaf.shape[0] for leaf in _leaves(states)}
        if rows != {n + 1}:
            raise ValueError(
                f"{group.file.filename}: {group.name}/env_states has {sorted(rows)} rows for {n} steps; "
                f"ManiSkill's files hold T + 1 = {n + 1} (the reset's state, then one per step)."
            )
        root["env_states"], nxt["env_states"] = _rows(states, slice(0, n)), _rows(states, slice(1, n + 1))
    root["next"] = nxt
    return TensorDict(root, batch_size=[n])
