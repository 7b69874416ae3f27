"""Saved sim states of :class:`~maniskill_torchrl.ManiSkillWrapper`: :meth:`get_state`,
:meth:`reset_to_state`, and the check of a state before it reaches the sim.

ManiSkill's ``set_state_dict`` trusts its input: a state of the wrong batch fails deep in SAPIEN
(``Pose.__init__``) or in a CPU worker, which then dies and leaves the batched env unusable, and a
state that lacks an entry (``actors``) silently leaves that part of the scene where it was. So
every state is checked against the layout of the env's own :meth:`get_state` (its keys, each
entry's shape per env, its dtype) first, with an error that names what differs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from maniskill_torchrl._private import new_tensordict

__all__ = ["SavedStates", "check_set_state", "tensor_tree"]


class SavedStates:
    """The saved-state methods of :class:`~maniskill_torchrl.ManiSkillWrapper` (mixed into it).

    Reads the host's ``base_env``, ``_env``, ``_sim_mode``, ``_unbatched``, ``device``,
    ``_sim_device``, ``batch_size``, ``_to_tensordict`` and ``_on_device``.
    """

    _state_row: TensorDictBase | None = None  # one env's state: the layout states are checked against

    def get_state(self) -> TensorDictBase:
        """Every env's ManiSkill sim state (``get_state_dict()``: the poses and velocities of its
        ``actors``, the root poses, velocities and joint positions / velocities of its
        ``articulations``; not the controllers' targets) as a TensorDict of this env's batch on
        ``env.device``, to reset to later with :meth:`reset_to_state` (or
        ``env.reset(td, set_state=True, env_states=state)``).

        Examples:
            >>> from maniskill_torchrl import ManiSkillEnv
            >>> env = ManiSkillEnv("PickCube-v1", obs_mode="state")
            >>> start = env.reset(seed=1)
            >>> state = env.get_state()
            >>> _ = env.rollout(3)
            >>> (env.reset_to_state(state)["observation"] == start["observation"]).all().item()
            True
        """
        with self._sim_mode():
            state = self.base_env.get_state_dict()
        num_envs = self.base_env.num_envs
        state = new_tensordict(tensor_tree(state, self.device), batch_size=torch.Size([num_envs]), device=self.device)
        if self._state_row is None:
            self._state_row = state[0]
        return state[0] if self._unbatched else state

    def reset_to_state(
        self, env_states: TensorDictBase | Mapping, tensordict: TensorDictBase | None = None, **kwargs: Any
    ) -> TensorDictBase:
        """Resets to saved ManiSkill states: every env, or those of ``tensordict``'s ``"_reset"`` mask.

        ``env_states`` is :meth:`get_state`'s layout (a TensorDict or a nested dict of tensors):
        one row per env (this env's batch; the rows of the envs not being reset are not read), or
        one env's state without a batch dim (a trajectory file's ``data[i]["env_states"]``), which
        every env being reset then takes. Its keys, shapes and dtypes are checked before anything
        reaches the sim: a :class:`ValueError` names the entry that differs.

        The same as ``env.reset(tensordict, set_state=True, env_states=env_states)``; on a
        :class:`~torchrl.envs.TransformedEnv`, call that form on the transformed env so that its
        transforms reset too.
        """
        return self.reset(tensordict, set_state=True, env_states=env_states, **kwargs)

    def _reset_to_states(
        self, env_states: TensorDictBase | Mapping, env_idx: torch.Tensor | None, seed: int | None, options: dict
    ) -> TensorDictBase:
        """``_reset`` to saved states (``options`` may hold ``env_idx``, the envs being reset)."""
        options["reset_to_env_states"] = {"env_states": self._state_rows(env_states, env_idx)}
        # Nothing is drawn: the saved state, not a seed, makes this episode's start.
        with self._sim_mode():
            obs, info = self._env.reset(seed=seed, options=options)
        source = self._on_device(self._to_tensordict(obs, info))
        return new_tensordict(source, batch_size=self.batch_size, device=self.device)

    def _state_rows(self, env_states: TensorDictBase | Mapping, env_idx: torch.Tensor | None) -> dict:
        """ManiSkill's ``reset_to_env_states`` batch: the rows of the envs being reset, on the sim's device."""
        states = self._checked_states(env_states).to(self._sim_device)
        if env_idx is not None:
            states = states[env_idx]  # the envs being reset, in env order
        return states.to_dict()

    def _checked_states(self, env_states: TensorDictBase | Mapping) -> TensorDictBase:
        """``env_states`` as a ``[num_envs]`` TensorDict of the layout of :meth:`get_state`, or an
        error that says what differs."""
        if not isinstance(env_states, (TensorDictBase, Mapping)):
            raise TypeError(
                "env_states must be a TensorDict or a dict of tensors (env.get_state()), "
                f"got {type(env_states).__name__}."
            )
        if not isinstance(env_states, TensorDictBase):
            env_states = TensorDict(tensor_tree(env_states), batch_size=[])
        if self._state_row is None:
            self.get_state()  # a read of the sim: learns the layout, changes nothing
        row = self._state_row
        want, got = set(row.keys(True, True)), set(env_states.keys(True, True))
        if want != got:
            missing, extra = sorted(want - got, key=str), sorted(got - want, key=str)
            raise ValueError(
                "env_states does not have this env's layout (env.get_state()): "
                + (f"missing {missing}" if missing else "")
                + ("; " if missing and extra else "")
                + (f"unknown {extra}" if extra else "")
                + ". Pass a state saved from this task (env.get_state(), or a trajectory file's env_states)."
            )
        num_envs = self.base_env.num_envs
        out, batches = {}, {}  # batch per entry: None for one env's state without a batch dim
        for key in sorted(want, key=str):
            ref, value = row.get(key), env_states.get(key)
            if value.shape == ref.shape:
                batches[key] = None
            elif value.ndim == ref.ndim + 1 and value.shape[1:] == ref.shape:
                batches[key] = value.shape[0]
            else:
                raise ValueError(
                    f"env_states{_path(key)} has shape {list(value.shape)}; this env's is {list(ref.shape)} per "
                    f"env: pass [{num_envs}, {', '.join(map(str, ref.shape))}] (one row per env) or "
                    f"{list(ref.shape)} (one env's state, for every env being reset)."
                )
            if value.dtype != ref.dtype and not (value.is_floating_point() and ref.is_floating_point()):
                raise ValueError(f"env_states{_path(key)} has dtype {value.dtype}; this env's is {ref.dtype}.")
            # A plain copy: a dataset's rows are memory-mapped tensors, which cannot be sent to CPU workers.
            out[key] = value.as_subclass(torch.Tensor).to(ref.dtype, copy=True)
        rows = set(batches.values())
        if len(rows) > 1:
            raise ValueError(f"env_states' entries have different batches: {batches}.")
        (rows,) = rows
        if rows is None:
            out = {k: v.expand(num_envs, *v.shape) for k, v in out.items()}
        elif rows != num_envs:
            raise ValueError(
                f"env_states has a batch of {rows} and this env has {num_envs} env(s): pass one row per env, "
                "or one env's state without a batch dim (every env being reset then takes it)."
            )
        states = TensorDict(batch_size=[num_envs])
        for key, value in out.items():
            states.set(key, value)
        return states


def check_set_state(set_state: bool | None, env_states: Any) -> None:
    """``reset(set_state=True, env_states=...)`` takes both or neither."""
    if (env_states is not None) != bool(set_state):
        raise ValueError(
            "A reset to saved states takes both set_state=True and env_states (from env.get_state()): "
            "env.reset(td, set_state=True, env_states=states), or env.reset_to_state(states, td)."
        )


def _path(key: Any) -> str:
    """``("actors", "cube")`` -> ``["actors", "cube"]``, as a user indexes the TensorDict."""
    key = key if isinstance(key, tuple) else (key,)
    return "".join(f"[{k!r}]" for k in key)


def tensor_tree(tree: Mapping, device: torch.device | None = None) -> dict:
    """A nested dict of tensors (ManiSkill's state dict) as plain dicts of normal tensors, copied
    (onto ``device`` if given)."""
    return {
        k: tensor_tree(v, device) if isinstance(v, Mapping) else torch.as_tensor(v).to(device, copy=True)
        for k, v in tree.items()
    }
