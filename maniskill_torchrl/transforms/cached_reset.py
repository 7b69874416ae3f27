""":class:`CachedReset`: ManiSkill's ``CachedResetWrapper`` on TensorDicts, resets drawn from saved states."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import Transform

from maniskill_torchrl.envs.hooks import EnvHooks, env_hooks

__all__ = ["CachedReset"]


class CachedReset(Transform):
    """Resets every env to a state drawn from a cache of saved reset states, with their cached
    observations, as ManiSkill's ``CachedResetWrapper`` does: the task's episode initialization and
    the reset's observation (camera renders included) are skipped.

    The cache is ``num_resets`` ordinary resets of the env (ManiSkill's ``CachedResetsConfig``:
    ``num_resets`` defaults to the env's number of envs; the first reset seeded with ``seed``,
    taken ``num_envs`` at a time), their :meth:`~maniskill_torchrl.ManiSkillWrapper.get_state`
    rows and observations, held on ``device``; or the ``env_states`` (and ``obs``) given, ManiSkill's
    ``reset_to_env_states``. It is built at the first reset, not when the transform is placed (a
    reset then would change the env's later seeded resets), in the same order of calls as
    ManiSkill's wrapper makes at its construction. Each later reset, full or partial (a
    ``"_reset"`` mask), draws one cache row per env being reset with ``torch.randint`` on the
    cache's device, from torch's global RNG, as ManiSkill does, and resets those envs to them
    (ManiSkill's ``options["reset_to_env_states"]``, through the env's
    :meth:`~maniskill_torchrl.envs.hooks.EnvHooks.request_reset_states`).

    A seeded first round reproduces ManiSkill's wrapper to the bit (observations after reset and
    after steps). Rounds after the first (``num_resets > num_envs``) are seeded by the env's seed
    stream (``set_seed``: the next draws), where ManiSkill's wrapper resets unseeded.

    It works on this library's :class:`~maniskill_torchrl.ManiSkillEnv` / ``ManiSkillWrapper``
    (one env, the batched CPU env, the GPU sim), anywhere in the transforms: it acts before the
    env's reset and changes no data or spec. The states must stay valid for the env: a task that
    reconfigures (``reconfiguration_freq``) changes its objects and so its states' layout.

    Where it pays: a reset through it skips ``_initialize_episode`` and ``get_obs``; the state is
    still set and the controllers and infos reset. benchmarks/RESULTS.md has the reset cost and
    the frames/s it makes on the CPU sim.

    Args:
        num_resets (int, optional): how many reset states to cache. Defaults to the env's number
            of envs (ManiSkill's default).
        device (torch.device, optional): where the cache is held (and the draws made). Defaults to
            the env's device.
        seed (int, optional): the seed of the first of the cache's resets. Defaults to None (the
            env's next seed: after ``env.set_seed(s)``, ``s``).

    Keyword Args:
        env_states (TensorDictBase or dict, optional): the states to reset to instead, ``[K]`` rows
            of ``get_state()``'s layout (ManiSkill's ``reset_to_env_states["env_states"]``).
        obs (TensorDictBase, optional): with ``env_states``, their observations: ``[K]`` rows of
            the env's reset tensordicts. Without it the sim computes the observations.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import CachedReset
        >>> env = TransformedEnv(ManiSkillEnv("PushCube-v1", obs_mode="state"), CachedReset(num_resets=4, seed=0))
        >>> td = env.reset()  # four plain resets fill the cache, then a reset to one of them
        >>> env.transform.env_states.batch_size
        torch.Size([4])
    """

    def __init__(
        self,
        num_resets: int | None = None,
        device: torch.device | str | None = None,
        seed: int | None = None,
        *,
        env_states: TensorDictBase | Mapping | None = None,
        obs: TensorDictBase | None = None,
    ) -> None:
        super().__init__()
        bad = isinstance(num_resets, bool) or not isinstance(num_resets, int) or num_resets < 1
        if num_resets is not None and bad:
            raise ValueError(f"num_resets must be a positive int or None, got {num_resets!r}.")
        if obs is not None and env_states is None:
            raise ValueError("obs= are the observations of env_states=: give both, or neither.")
        self.num_resets, self.seed = num_resets, seed
        self.cache_device = None if device is None else torch.device(device)
        self.env_states = None if env_states is None else _rows(env_states, "env_states")
        self.obs = None if obs is None else _rows(obs, "obs")
        if self.obs is not None and self.obs.batch_size != self.env_states.batch_size:
            raise ValueError(
                f"obs has {self.obs.batch_size[0]} rows, env_states {self.env_states.batch_size[0]}: one per state."
            )
        if self.env_states is not None:
            self.env_states = self._held(self.env_states)
            self.obs = None if self.obs is None else self._held(self.obs)

    # ------------------------------------------------------------------ the reset
    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase | None:
        tensordict = super()._reset_env_preprocess(tensordict)
        env = self._env()
        if self.env_states is None:
            self._fill(env)
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        count = env.batch_size.numel() if reset is None else int(reset.sum())
        if count:  # a reset of no env is none: no request left for the next
            ids = torch.randint(0, self.env_states.batch_size[0], (count,), device=self.env_states.device)
            env.request_reset_states(self.env_states[ids], None if self.obs is None else self.obs[ids])
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset

    # ------------------------------------------------------------------ the cache
    def _fill(self, env: EnvHooks) -> None:
        """ManiSkill's construction of its cache: resets of ``num_envs`` envs at a time (the first
        ``k`` of a last partial round), the first one seeded, their states and observations."""
        num_envs = env.batch_size.numel()
        want = self.num_resets or num_envs
        keys = list(env.observation_spec.keys())
        done = env.full_done_spec["done"]
        states, obs = [], []
        got = 0
        while got < want:
            k = min(want - got, num_envs)
            mask = None
            if k < num_envs:
                reset = torch.zeros(done.shape, dtype=torch.bool, device=env.device)
                reset.view(num_envs, -1)[:k] = True
                mask = TensorDict({"_reset": reset}, batch_size=env.batch_size, device=env.device)
            out = env.reset(mask, seed=self.seed if got == 0 else None).select(*keys)
            state = env.get_state()
            if not env.batch_size:  # one unbatched env: a row of one
                out, state = out.unsqueeze(0), state.unsqueeze(0)
            states.append(self._held(state[:k]))
            obs.append(self._held(out[:k]))
            got += k
        self.env_states, self.obs = torch.cat(states), torch.cat(obs)

    def _held(self, td: TensorDictBase) -> TensorDictBase:
        # Copies (the env may write into what it handed out), on the cache's device.
        device = self.cache_device if self.cache_device is not None else td.device
        return td.to(device).clone() if device is not None else td.clone()

    def _env(self) -> EnvHooks:
        parent = self.parent
        env = None if parent is None else env_hooks(parent)
        if env is None or not hasattr(env, "get_state"):
            raise TypeError(
                "CachedReset resets a ManiSkill env to saved states: put it in a TransformedEnv on "
                "maniskill_torchrl's ManiSkillEnv / ManiSkillWrapper (not a ParallelEnv: ManiSkillEnv(num_envs=N) "
                "batches the CPU sim itself)."
            )
        if self.cache_device is None and self.env_states is None:
            self.cache_device = env.device
        return env

    def __repr__(self) -> str:
        held = "none yet" if self.env_states is None else self.env_states.batch_size[0]
        return f"{type(self).__name__}(num_resets={self.num_resets}, seed={self.seed}, cached={held})"


def _rows(data: TensorDictBase | Mapping, name: str) -> TensorDictBase:
    """``data`` as a TensorDict of its ``[K]`` rows (a dict's leaves' first dim)."""
    td = data if isinstance(data, TensorDictBase) else TensorDict(dict(data), batch_size=[])
    if not td.batch_dims:
        leaves = list(td.values(True, True))
        if not leaves or leaves[0].ndim == 0:
            raise ValueError(f"{name}: [K, ...] rows of tensors expected.")
        td.batch_size = leaves[0].shape[:1]
    elif td.batch_dims > 1:
        td.batch_size = td.batch_size[:1]
    return td
