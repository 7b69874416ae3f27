"""ManiSkill's sparse reward from the success / fail entries: ``success - fail``."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs import Transform

__all__ = ["SparseReward"]


class SparseReward(Transform):
    """Writes ManiSkill's sparse reward, ``success - fail`` as float32, into ``"reward"``.

    ManiSkill's ``reward_mode="sparse"`` (``BaseEnv.compute_sparse_reward``): +1 on success, -1
    on failure, 0 otherwise, from the step's ``success`` / ``fail`` infos (a task that reports
    only one of them uses that one). ManiSkill's RLPD reads demonstrations this way, whatever
    reward their file holds, if any: put this transform on a demonstration buffer (or on an
    ``OfflineToOnlineReplayBuffer``'s mixed batches) to train on the sparse reward an env made
    with ``reward_mode="sparse"`` gives. On stored data (a replay buffer's transform, which runs
    :meth:`forward` on each sample) it writes ``("next", "reward")`` from ``("next", "success")``
    and ``("next", "fail")``; on an env, the reward of each step. The reward is shaped as the
    library's envs shape it (``[*batch, 1]``); specs are unchanged.

    TorchRL's own :class:`~torchrl.envs.transforms.SuccessReward` (0.14.1) is the success term alone: it has no
    fail term (a failed step gets 0, not -1), writes the reward shaped as the success entry (``[*batch]`` for
    ManiSkill's, not the env's ``[*batch, 1]``) and rewrites the env's reward spec to ``{0, scale}``. On a task
    that never fails (``fail`` always False, or absent), ``SuccessReward`` gives the same values; for ManiSkill's
    sparse reward on every task, use this transform.

    Args:
        success_key (NestedKey): default ``"success"``.
        fail_key (NestedKey): default ``"fail"``.
        reward_key (NestedKey): default ``"reward"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from maniskill_torchrl.transforms import SparseReward
        >>> steps = TensorDict({"next": {"success": torch.tensor([False, True])}}, [2])
        >>> SparseReward()(steps)["next", "reward"]
        tensor([[0.],
                [1.]])
    """

    def __init__(
        self, success_key: NestedKey = "success", fail_key: NestedKey = "fail", reward_key: NestedKey = "reward"
    ) -> None:
        super().__init__(in_keys=[success_key, fail_key], out_keys=[reward_key])
        self.success_key, self.fail_key, self.reward_key = success_key, fail_key, reward_key

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        success = next_tensordict.get(self.success_key, None)
        fail = next_tensordict.get(self.fail_key, None)
        if success is None and fail is None:
            raise KeyError(
                f"SparseReward needs {self.success_key!r} or {self.fail_key!r} in the step (ManiSkill's "
                "trajectory files and envs report them where the task defines them)."
            )
        reward = torch.zeros((), dtype=torch.float32, device=next_tensordict.device)
        if success is not None:
            reward = reward + success.to(torch.float32)
        if fail is not None:
            reward = reward - fail.to(torch.float32)
        if reward.shape == next_tensordict.batch_size:
            reward = reward.unsqueeze(-1)
        next_tensordict.set(self.reward_key, reward)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The rule on stored data: the ``"next"`` entries (where a transition's reward is)."""
        next_tensordict = tensordict.get("next", None)
        if next_tensordict is None:
            return self._call(tensordict)
        tensordict.set("next", self._call(next_tensordict))
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
