"""One CPU ManiSkill env (batch ``[1]``) as an unbatched TorchRL env (batch ``[]``)."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data import Composite
from torchrl.envs import BatchSizeTransform, EnvBase, Transform

__all__ = ["CPUUnbatch"]


def _squeeze_env_dim(data):
    # A module-level function, not a lambda: the transform must pickle (ParallelEnv, collectors).
    return data.squeeze(0)


class CPUUnbatch(BatchSizeTransform):
    """Turns a ``[1]``-batched ManiSkill env into an unbatched one (``batch_size=[]``).

    ManiSkill's CPU sim holds one env per process and still returns batched
    tensors (``[1, ...]``). This transform squeezes that leading env dim out
    of every spec and every entry (observations at any depth, infos, reward
    ``[1]``, done flags ``[1]``) and puts it back on the actions on their way
    in (Box ``"action"`` and Dict ``("action", <agent>)`` alike). Unbatched
    envs are what :class:`~torchrl.envs.ParallelEnv` /
    :class:`~torchrl.envs.SerialEnv` stack: ``ParallelEnv(N, make_env)`` then
    has ``batch_size=[N]``. It is the TorchRL counterpart of the unbatching
    done by ManiSkill's ``CPUGymWrapper``. For a ManiSkill env you make yourself,
    ``ManiSkillEnv(env_id, batch_size=[])`` gives the same specs and entries without a
    ``TransformedEnv`` (less CPU per step: no transformed env's step on top of ManiSkill's).

    It is a :class:`~torchrl.envs.BatchSizeTransform` with a squeeze as
    ``reshape_fn`` (outputs and specs) plus checks: the parent must have
    ``batch_size=[1]`` and, if it is a ManiSkill env, run on the CPU sim. A
    GPU-sim env is already a batched TorchRL env; use it directly
    (``ManiSkillEnv(..., num_envs=N)`` has ``batch_size=[N]``). On the way in
    only the parent's inputs (actions, state entries) get their env dim back
    and the tensordict stays unbatched, because TorchRL hands that same
    tensordict to the transforms placed after this one (a
    :class:`~torchrl.envs.StepCounter` there keeps ``[1]``-shaped counts).
    Any ``[1]``-batched env is accepted, ManiSkill or not.

    Place it first, right after the ManiSkill env: transforms after it see
    unbatched data. A ``"_reset"`` entry (shape ``[1]`` in the unbatched
    env) reaches the ManiSkill env as is; ManiSkill reshapes it to its batch.

    Examples:
        >>> from torchrl.envs import ParallelEnv, TransformedEnv
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import CPUUnbatch
        >>> env = TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state"), CPUUnbatch())
        >>> env.batch_size, env.observation_spec["observation"].shape, env.action_spec.shape
        (torch.Size([]), torch.Size([42]), torch.Size([8]))
        >>> env.rollout(3)["next", "reward"].shape
        torch.Size([3, 1])
        >>> def make_env():
        ...     return TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state"), CPUUnbatch())
        >>> penv = ParallelEnv(2, make_env)
        >>> penv.rollout(3)["next", "observation"].shape
        torch.Size([2, 3, 42])
        >>> penv.close()
    """

    def __init__(self) -> None:
        super().__init__(reshape_fn=_squeeze_env_dim)
        # The parent's input keys (actions, state), read on the first step and dropped with the
        # parent (set_container, empty_cache).
        self._parent_in_keys_cache: list[NestedKey] | None = None

    def set_container(self, container: Transform | EnvBase) -> None:
        super().set_container(container)
        self._parent_in_keys_cache = None
        # Fail when the transform is attached, not at the first spec access. Inside a
        # Compose without an env yet there is no parent: transform_output_spec checks then.
        parent = self.parent
        if parent is not None:
            self._check_parent(parent)

    def _check_parent(self, parent: EnvBase) -> None:
        base = getattr(parent, "base_env", parent)
        if getattr(base, "gpu_sim_enabled", False):
            raise ValueError(
                f"CPUUnbatch is for ManiSkill's CPU sim, but {base} runs on the GPU sim "
                f"(device {base.device}). A GPU-sim env is a batched TorchRL env already: use the batched "
                "env directly (ManiSkillEnv(env_id, num_envs=N, sim_backend='gpu') has batch_size [N])."
            )
        batch_size = parent.batch_size
        if batch_size != torch.Size([1]):
            raise ValueError(
                f"CPUUnbatch needs a parent env with batch_size [1] (one ManiSkill env, num_envs=1), "
                f"got batch_size {list(batch_size)}. A batched env needs no CPUUnbatch: "
                "ManiSkillEnv(env_id, num_envs=N) has batch_size [N] on the CPU and GPU sims alike "
                "(or stack single ones: ParallelEnv(N, lambda: TransformedEnv(ManiSkillEnv(env_id), CPUUnbatch())))."
            )

    def transform_env_batch_size(self, batch_size: torch.Size) -> torch.Size:
        # squeeze(0) would silently keep a batch of 3: refuse anything but [1] (a cheap size compare).
        if batch_size != torch.Size([1]):
            parent = self.parent
            if parent is not None:
                self._check_parent(parent)
            raise ValueError(f"CPUUnbatch needs a parent env with batch_size [1], got {list(batch_size)}.")
        return torch.Size([])

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        parent = self.parent
        if parent is not None:
            self._check_parent(parent)
        return super().transform_output_spec(output_spec)

    @property
    def _parent_in_keys(self) -> list[NestedKey]:
        keys = self._parent_in_keys_cache
        if keys is None:
            parent = self.parent
            if parent is None:
                return ["action"]
            spec = parent.input_spec
            keys = list(spec["full_action_spec"].keys()) + list(spec["full_state_spec"].keys())
            self._parent_in_keys_cache = keys
        return keys

    def empty_cache(self) -> None:
        self._parent_in_keys_cache = None
        super().empty_cache()

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Only what the parent reads (actions, state) gets the env dim back, and the
        # tensordict stays unbatched: TorchRL hands this inverted tensordict to the
        # ``_step`` of the transforms placed after this one, which expect batch [].
        # ``inv`` gave us a shallow copy, so setting top-level entries is safe.
        for key in self._parent_in_keys:
            val = tensordict.get(key, None)
            if val is not None:
                tensordict.set(key, val.unsqueeze(0))
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if tensordict_reset.batch_dims == 0:
            # A no-op reset ("_reset" all False): the parent handed back our unbatched
            # input and TorchRL filled in the parent's [1, 1] done flags; unbatch those.
            parent = self.parent
            done_spec = parent.full_done_spec
            for key in parent.done_keys:
                val = tensordict_reset.get(key, None)
                if val is not None and val.shape == done_spec[key].shape:
                    tensordict_reset.set(key, val.squeeze(0))
            return tensordict_reset
        return tensordict_reset.squeeze(0)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
