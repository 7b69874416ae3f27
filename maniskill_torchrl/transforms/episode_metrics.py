"""Per-env episode metrics (return, length, success / fail) as a TorchRL transform."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase, Transform, TransformedEnv

from maniskill_torchrl._internal.episode_stats import SUMMATIONS, EpisodeField, EpisodeStats, episode_fields
from maniskill_torchrl._internal.host_gather import HostGather
from maniskill_torchrl.envs.hooks import env_hooks

__all__ = ["EpisodeMetrics"]


class EpisodeMetrics(Transform):
    """Records ManiSkill's standard evaluation metrics per env, under ``"episode"``.

    At every step, for every env of the batch (TorchRL's counterpart of
    ``CPUGymWrapper(env, record_metrics=True)``, and the same numbers, bit
    for bit, on one CPU env's linear rollouts):

    - ``("episode", "return")`` float32: the sum of the episode's rewards,
      summed as ``numpy.sum`` does;
    - ``("episode", "episode_len")`` int64: steps since the env's reset;
    - ``("episode", "reward")`` float32: ``return / episode_len``;
    - ``("episode", "success_once")`` / ``("episode", "success_at_end")``
      bool: success ever reported in the episode / reported at this step,
      where the parent reports ``"success"`` (an entry of its observation
      spec, as :class:`~maniskill_torchrl.ManiSkillWrapper` declares infos);
    - ``("episode", "fail_once")`` / ``("episode", "fail_at_end")`` likewise
      for ``"fail"``.

    The entries are declared in the observation spec, so batched envs and
    collectors keep them; each has the parent's batch shape. They are also the
    transform's running state, declared in ``full_state_spec`` as TorchRL's
    ``RewardSum`` declares its ``episode_reward``: each step reads the last ones
    from the input tensordict, as ``StepCounter`` and ``RewardSum`` do, so stepping
    twice from the same root (``env.rollout(n, tensordict=root)``, planners)
    starts both branches from that root's values. At reset they are zeros for
    the envs being reset; a ``"_reset"`` mask resets only those envs (partial
    resets of the GPU sim, or of a batched env with the transform on top), the
    others carry on. Any batch works: one unbatched CPU env (after
    :class:`~maniskill_torchrl.transforms.CPUUnbatch`), a ``ParallelEnv`` of
    them, or ``num_envs`` GPU-sim envs; the statistics live on the parent's
    device.

    ``return`` is summed one of two ways (``summation``), after the two anchors:

    - ``"numpy"`` (default on ManiSkill's CPU sim, whatever ``device`` its outputs
      are on): ``numpy.sum`` of the episode's rewards, bit for bit ``CPUGymWrapper``'s;
      one host-side numpy reduction per env per step. numpy's pairwise order needs the
      episode's rewards, which the transform keeps itself (the tensordict holds only the
      return): an env whose input state is not the continuation of that history (a step
      kept from an earlier episode, stepped again after others ran) goes on from the
      tensordict's return with a running float32 sum until its next reset. So bit-equality
      with ``CPUGymWrapper`` holds on linear rollouts (and on branches from a root of the
      last episode run); the return always continues from the tensordict's state.
    - ``"running"`` (default on the GPU sim): a running float32 sum,
      bit for bit ``ManiSkillVectorEnv(record_metrics=True)``'s; a few tensor ops
      per step whatever the batch and the episode lengths, and no host sync.

    Add :class:`~maniskill_torchrl.transforms.IgnoreTerminations` before it
    to measure episodes that run to the time limit (what ManiSkill's
    evaluation does with ``ignore_terminations=True``).

    Args:
        summation (str, optional): ``"numpy"`` or ``"running"``; None (default) picks
            by the sim, as above: the base env under the transformed envs says which
            (a :class:`~maniskill_torchrl.ManiSkillWrapper`'s ``gpu_sim_enabled``); where it cannot (a
            ``ParallelEnv`` of single envs, a non-ManiSkill env), by the parent's device:
            ``"numpy"`` on the CPU, ``"running"`` elsewhere.

    Examples:
        >>> from torchrl.envs import TransformedEnv, Compose
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import CPUUnbatch, EpisodeMetrics, IgnoreTerminations
        >>> env = TransformedEnv(
        ...     ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=10),
        ...     Compose(CPUUnbatch(), IgnoreTerminations(), EpisodeMetrics()),
        ... )
        >>> _ = env.set_seed(0)
        >>> td = env.rollout(10)
        >>> td["next", "episode", "episode_len"].tolist()
        [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]
        >>> sorted(td["next", "episode"].keys())
        ['episode_len', 'return', 'reward', 'success_at_end', 'success_once']
    """

    def __init__(self, summation: str | None = None) -> None:
        if summation is not None and summation not in SUMMATIONS:
            raise ValueError(f"summation={summation!r}: use one of {SUMMATIONS} (or None: by the env's device).")
        super().__init__()
        self.summation = summation
        self._stats: EpisodeStats | None = None
        self._host_value = None

    # ----------------------------------------------------------- set-up
    def _flags(self) -> tuple[bool, bool]:
        keys = self.parent.observation_spec.keys()
        return "success" in keys, "fail" in keys

    def _make_stats(self) -> EpisodeStats:
        parent = self.parent
        if parent is None:
            raise RuntimeError("EpisodeMetrics needs a parent env: use it in a TransformedEnv.")
        reward_keys = parent.reward_keys
        reward_shape = parent.full_reward_spec[reward_keys[0]].shape if reward_keys else None
        if len(reward_keys) != 1 or reward_shape.numel() != parent.batch_size.numel():
            raise ValueError(
                "EpisodeMetrics needs one reward per env (a single reward entry of shape "
                f"[*batch, 1], batch {list(parent.batch_size)}), got reward keys {reward_keys}"
                + (f" with shape {list(reward_shape)}" if reward_keys else "")
                + ". For several agents, sum their rewards into one entry first."
            )
        has_success, has_fail = self._flags()
        summation = self.summation if self.summation is not None else _default_summation(parent)
        self._stats = EpisodeStats(
            parent.batch_size,
            parent.device,
            has_success=has_success,
            has_fail=has_fail,
            summation=summation,
            gather=HostGather,  # the env's own one-transfer move, for sums made on the host
        )
        self._reward_key = reward_keys[0]
        self._reset_keys = list(parent.reset_keys)
        # Where the env keeps the host values of what it moved up (a CPU-sim env on an
        # accelerator, through the EnvHooks protocol): the numpy summation reads rewards and
        # flags there, not from the device.
        hooks = env_hooks(parent)
        self._host_value = None if hooks is None else hooks.host_value
        return self._stats

    def to(self, *args, **kwargs) -> EpisodeMetrics:
        device = torch._C._nn._parse_to(*args, **kwargs)[0]
        out = super().to(*args, **kwargs)
        if device is not None and self._stats is not None:
            self._stats.to(device)  # the episodes under way and their history go on
        return out

    def set_container(self, container) -> None:
        super().set_container(container)
        # A new parent may have another batch, device or info keys.
        self._stats = None

    def _episode_spec(self) -> Composite:
        parent = self.parent
        batch, device = parent.batch_size, parent.device

        def spec(field: EpisodeField) -> TensorSpec:
            if field.dtype == torch.bool:
                return Categorical(2, shape=batch, dtype=torch.bool, device=device)
            return Unbounded(shape=batch, dtype=field.dtype, device=device)

        fields = episode_fields(*self._flags())
        return Composite({f.name: spec(f) for f in fields}, shape=batch, device=device)

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        observation_spec["episode"] = self._episode_spec()
        return observation_spec

    def transform_input_spec(self, input_spec: TensorSpec) -> TensorSpec:
        # The running state, as RewardSum's: batched envs send it to their workers with the
        # action, and an ActionRepeat placed after this transform carries it between inner steps.
        state_spec = input_spec["full_state_spec"]
        if state_spec is None:
            state_spec = Composite(shape=input_spec.shape, device=input_spec.device)
        state_spec["episode"] = self._episode_spec()
        input_spec["full_state_spec"] = state_spec
        return input_spec

    # ----------------------------------------------------------- data
    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        stats = self._stats
        if stats is None:
            stats = self._make_stats()
        episode = stats.update(
            tensordict.get("episode", None),
            next_tensordict.get(self._reward_key),
            next_tensordict.get("success") if stats.has_success else None,
            next_tensordict.get("fail") if stats.has_fail else None,
            host=self._host_value,
        )
        next_tensordict.set("episode", episode)
        return next_tensordict

    def _reset_mask(self, tensordict: TensorDictBase, batch: torch.Size) -> torch.Tensor | None:
        """Per env: whether it is being reset (``None``: all of them)."""
        mask = None
        for key in self._reset_keys:
            reset = tensordict.get(key, None)
            if reset is None:
                return None
            # Reset entries are [*batch, 1] (or per agent): reduce them to the env batch.
            reset = reset.reshape(*batch, -1).any(-1)
            mask = reset if mask is None else mask | reset
        return mask

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        stats = self._stats
        if stats is None:
            stats = self._make_stats()
        previous = tensordict.get("episode", None) if tensordict is not None else None
        mask = self._reset_mask(tensordict, stats.batch_size) if previous is not None else None
        # No ``mask.all()`` shortcut: on the GPU sim it would sync the host at every reset.
        episode = stats.zeros() if mask is None else stats.restart(previous, mask)
        tensordict_reset.set("episode", episode)
        return tensordict_reset

    def __repr__(self) -> str:
        arg = "" if self.summation is None else f"summation={self.summation!r}"
        return f"{type(self).__name__}({arg})"


def _default_summation(parent: EnvBase) -> str:
    """By the sim where the env says which it is, else by the device.

    The base env under the transformed envs (a :class:`~maniskill_torchrl.ManiSkillWrapper`, or
    anything with a ``gpu_sim_enabled`` class attribute) answers: ``"running"`` on ManiSkill's
    GPU sim, ``"numpy"`` on its CPU sim, whatever device its outputs are moved to. Elsewhere
    (a ``ParallelEnv`` of single envs, a toy env): ``"numpy"`` on the CPU, ``"running"`` on
    other devices.
    """
    base = _base_env(parent)
    # Asked of the class: batched envs hand unknown attributes on to their sub-envs (a list).
    if hasattr(type(base), "gpu_sim_enabled"):
        return "running" if base.gpu_sim_enabled else "numpy"
    device = parent.device
    return "numpy" if device is None or torch.device(device).type == "cpu" else "running"


def _base_env(env: EnvBase) -> EnvBase:
    """The env under ``env``'s transformed envs."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env
