"""TorchRL rollouts and collector batches written in ManiSkill's trajectory format (``.h5`` +
``.json``), which ManiSkill's ``ManiSkillTrajectoryDataset``, ``replay_trajectory`` and the
library's :class:`~maniskill_torchrl.data.ManiSkillExperienceReplay` read."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

__all__ = ["save_trajectories"]


def _episodes(done: torch.Tensor) -> list[tuple[int, int, int]]:
    """``(row, start, stop)`` of each episode in a ``[rows, T]`` done mask: a done step ends one,
    and the steps after a row's last done form one more (not finished) episode."""
    out = []
    for row, flags in enumerate(done.tolist()):
        start = 0
        for t, d in enumerate(flags):
            if d:
                out.append((row, start, t + 1))
                start = t + 1
        if start < len(flags):
            out.append((row, start, len(flags)))
    return out


def _max_episode_steps(wrapper: Any) -> int | None:
    """The time limit of the wrapped ManiSkill env, as ``RecordEpisode`` finds it."""
    return wrapper.max_episode_steps


def _write(group: Any, name: str, value: Any) -> None:
    if isinstance(value, TensorDictBase):
        sub = group.create_group(name, track_order=True)
        for key in value.keys():
            _write(sub, key, value.get(key))
        return
    array = value.detach().cpu().numpy()
    compression = dict(compression="gzip", compression_opts=5) if array.dtype == np.uint8 and array.ndim >= 3 else {}
    group.create_dataset(name, data=array, dtype=array.dtype, **compression)


def save_trajectories(path: str | Path, rollout: TensorDictBase, env: Any) -> list[int]:
    """Writes ``rollout`` (``env.rollout(...)``, a collector batch: ``[T]`` or ``[*batch, T]``) as a
    ManiSkill trajectory file pair: ``path`` (``.h5``) and its ``.json``.

    Each env's row is cut into episodes after every done step (the steps after its last done
    make one more, unfinished, episode). Per episode ``traj_<k>``, as ``RecordEpisode`` writes
    them: ``obs`` (``T + 1`` rows: the first step's observation, then every ``"next"`` one;
    nested groups for a dict observation), ``actions``, ``terminated``, ``truncated``, ``success`` /
    ``fail`` where the env reports them, ``rewards`` (float32) and, where the rollout carries them
    (:class:`~maniskill_torchrl.transforms.EnvStates`), ``env_states`` (``T + 1`` rows: the first
    step's root state, then every ``"next"`` one). The ``.json`` holds ``env_info`` (``env_id``,
    ``env_kwargs``, ``max_episode_steps``) and each episode's ``episode_id``, ``control_mode``,
    ``elapsed_steps``, ``success`` / ``fail``. ``max_episode_steps`` is the env's real time limit
    (what ``RecordEpisode`` writes), also put in ``env_kwargs`` so that ``ManiSkillEnv(env_id,
    **env_kwargs)`` replays with the recorded episode length.

    Args:
        path: the ``.h5`` file to write (replaced if it exists).
        rollout: the steps, with ``("next", ...)`` entries.
        env: the :class:`~maniskill_torchrl.ManiSkillWrapper` (or a ``TransformedEnv`` of one)
            that produced them: its observation keys and ManiSkill's ``gym.make`` arguments.

    Returns:
        The episode ids written, in order.
    """
    import h5py

    from maniskill_torchrl.envs.engine_env import ManiSkillWrapper

    wrapper = env
    while not isinstance(wrapper, ManiSkillWrapper):
        inner = getattr(wrapper, "base_env", None)
        if inner is None or inner is wrapper:
            raise TypeError(
                f"save_trajectories needs the ManiSkill env that made the rollout, got {type(env).__name__}."
            )
        wrapper = inner
    base = wrapper.unwrapped
    infos = set(wrapper.info_entries.values())
    obs_keys = [k for k in wrapper.observation_spec.keys() if k not in infos and k != "pixels"]
    steps = rollout if rollout.batch_dims > 1 else rollout.unsqueeze(0)
    steps = steps.reshape(-1, steps.shape[-1])  # [rows, T]
    has_states = "env_states" in steps.keys() and ("next", "env_states") in steps.keys(True)
    flat = obs_keys == ["observation"]
    spec = base.spec
    # gym.make's arguments: the spec's for a ManiSkill env, the CPUVectorEnv's own for its sub-envs.
    env_kwargs = dict(getattr(base, "maniskill_kwargs", None) or spec.kwargs or {})
    env_kwargs.pop("num_envs", None)
    max_episode_steps = _max_episode_steps(wrapper)
    if max_episode_steps is not None:
        # gym.make takes the limit out of the spec's kwargs: put it back, so that
        # ManiSkillEnv(env_id, **env_kwargs) ends its episodes where these ended.
        env_kwargs["max_episode_steps"] = max_episode_steps
    meta = {
        "env_info": {
            "env_id": spec.id,
            "env_kwargs": env_kwargs,
            "max_episode_steps": max_episode_steps,
        },
        "episodes": [],
    }
    control_mode = env_kwargs.get("control_mode") or getattr(base, "control_mode", None)
    path = Path(path)
    ids = []
    with h5py.File(path, "w") as h5:
        for k, (row, start, stop) in enumerate(_episodes(steps["next", "done"].reshape(steps.shape[0], -1))):
            ep = steps[row, start:stop]
            group = h5.create_group(f"traj_{k}", track_order=True)
            first, nxt = ep.select(*obs_keys), ep["next"].select(*obs_keys)
            all_obs = torch.cat([first[:1], nxt])
            _write(group, "obs", all_obs["observation"] if flat else all_obs)
            _write(group, "actions", ep["action"])
            _write(group, "terminated", ep["next", "terminated"].reshape(-1))
            _write(group, "truncated", ep["next", "truncated"].reshape(-1))
            # The rollout does not know its reset seeds: ManiSkill's replay_trajectory then needs
            # --use-env-states (record them with EnvStates) to reproduce the episode.
            info = {
                "episode_id": k,
                "episode_seed": None,
                "control_mode": control_mode,
                "elapsed_steps": stop - start,
                "reset_kwargs": {},
            }
            for flag in ("success", "fail"):
                if flag in infos:
                    values = ep["next", flag].reshape(-1)
                    _write(group, flag, values)
                    info[flag] = bool(values[-1])
            _write(group, "rewards", ep["next", "reward"].reshape(-1).to(torch.float32))
            if has_states:
                _write(group, "env_states", torch.cat([ep[:1]["env_states"], ep["next", "env_states"]]))
            meta["episodes"].append(info)
            ids.append(k)
    path.with_suffix(".json").write_text(json.dumps(meta, indent=2, default=str))
    return ids
