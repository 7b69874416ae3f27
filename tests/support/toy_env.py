"""A small deterministic batched TorchRL env (plain torch, no ManiSkill) for tests.

It shows what one CPU ManiSkill env cannot: many envs that end at different
steps, by termination or truncation, with nested observations and infos.

Per env ``i`` of the batch (global id ``ids[i]``), with ``t`` the steps taken
since its last reset (``t = 1`` after the first step):

- ``"reward"`` [*B, 1] float32: :func:`toy_reward` ``(id, t)`` (non-trivial floats);
- ``"done"`` / ``"terminated"`` / ``"truncated"`` [*B, 1] bool: done once
  ``t >= ends[i]``, by termination where ``terminate[i]`` else by truncation.
  Stepping past the end keeps going (``t`` grows, rewards keep coming), as a
  batch-locked simulator does; done stays True, or with ``done_once=True`` is
  True at ``t == ends[i]`` only (an event that does not persist, like a
  success-based termination);
- ``"observation"`` [*B, 3] float32: ``[t, id, action[0]]``;
- ``("nested", "deep", "x")`` [*B, 2] uint8: :func:`toy_nested` ``(id, t)``;
- ``("nested", "count")`` [*B] int64: the env's total real steps (never reset);
- ``"elapsed_steps"`` [*B] int64: ``t``;
- ``"success"`` [*B] bool: ``t % 3 == 2``; ``"fail"`` [*B] bool: ``terminated``.

``step_count`` ([*B] int64 tensor attribute) counts the real steps of every env,
``reset_count`` the resets (a ``"_reset"`` mask resets only those envs). The
env is batch-locked and steps every env of its batch (it ignores ``"_step"``),
like ManiSkill's GPU sim; a :class:`~torchrl.envs.SerialEnv` of
``batch_size=[]`` toy envs honours partial steps.

``multi_agent=True`` moves reward and done flags under ``"agents"``, shaped
[*B, 2, 1] (agent ``a`` gets ``(a + 1) * toy_reward``; both agents end with the
env); top-level ``"done"`` / ``"terminated"`` / ``"truncated"`` stay.

Examples:
    >>> from torchrl.envs.utils import check_env_specs
    >>> env = ToyEnv([1, 3], terminate=[True, False])
    >>> check_env_specs(env)
    >>> td = env.rollout(3, break_when_any_done=False)
    >>> td["next", "done"].squeeze(-1).tolist()
    [[True, True, True], [False, False, True]]
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = ["ToyEnv", "toy_reward", "toy_nested"]


def toy_reward(env_id: torch.Tensor | int, t: torch.Tensor | int) -> torch.Tensor:
    """The float32 reward of env ``env_id`` at its step ``t`` (1-based).

    An integer over 7 in float32: not exactly representable, so sums round and
    their order matters, yet one correctly rounded division gives the same bits
    however it is vectorised (a reference may compute it one env at a time).
    """
    env_id = torch.as_tensor(env_id, dtype=torch.int64)
    t = torch.as_tensor(t, dtype=torch.int64)
    return ((13 * t * t + 7 * env_id + 5) % 97 - 40).to(torch.float32) / 7.0


def toy_nested(env_id: torch.Tensor | int, t: torch.Tensor | int) -> torch.Tensor:
    """The uint8 ``("nested", "deep", "x")`` entry [..., 2] of env ``env_id`` at step ``t``."""
    env_id = torch.as_tensor(env_id, dtype=torch.int64)
    t = torch.as_tensor(t, dtype=torch.int64)
    return torch.stack([(7 * t + 13 * env_id) % 256, (t * t + env_id) % 256], -1).to(torch.uint8)


class ToyEnv(EnvBase):
    """See the module docstring.

    Args:
        ends: episode length per env (a sequence of ints >= 1 for ``batch_size``
            ``[len(ends)]``, or one int for ``batch_size=[]``).
        terminate: per env, whether it ends by termination (True, the default)
            or by truncation; one bool for all envs.
        ids: the env ids used in rewards and observations (default ``0..B-1``;
            give distinct ids to the sub-envs of a SerialEnv).
        multi_agent: reward and done flags under ``"agents"`` (see module docstring).
        done_once: done is True at the end step only, not after it.
    """

    def __init__(
        self,
        ends: Sequence[int] | int,
        terminate: Sequence[bool] | bool = True,
        ids: Sequence[int] | int | None = None,
        multi_agent: bool = False,
        done_once: bool = False,
    ) -> None:
        scalar = isinstance(ends, int)
        batch = torch.Size([]) if scalar else torch.Size([len(ends)])
        super().__init__(batch_size=batch, device="cpu")
        self.ends = torch.as_tensor(ends, dtype=torch.int64).reshape(batch)
        self.terminate = torch.as_tensor(terminate, dtype=torch.bool).expand(batch).clone()
        if ids is None:
            ids = 0 if scalar else list(range(len(ends)))
        self.ids = torch.as_tensor(ids, dtype=torch.int64).reshape(batch)
        self.multi_agent = multi_agent
        self.done_once = done_once
        self.t = torch.zeros(batch, dtype=torch.int64)
        self.step_count = torch.zeros(batch, dtype=torch.int64)
        self.reset_count = torch.zeros(batch, dtype=torch.int64)

        b = batch
        flag = lambda: Categorical(2, shape=b + (1,), dtype=torch.bool)  # noqa: E731
        self.observation_spec = Composite(
            observation=Unbounded(b + (3,), dtype=torch.float32),
            nested=Composite(
                deep=Composite(x=Bounded(0, 255, b + (2,), dtype=torch.uint8), shape=b),
                count=Unbounded(b, dtype=torch.int64),
                shape=b,
            ),
            elapsed_steps=Unbounded(b, dtype=torch.int64),
            success=Categorical(2, shape=b, dtype=torch.bool),
            fail=Categorical(2, shape=b, dtype=torch.bool),
            shape=b,
        )
        self.action_spec = Bounded(-1.0, 1.0, b + (2,), dtype=torch.float32)
        if multi_agent:
            a = b + (2, 1)
            agent_flag = lambda: Categorical(2, shape=a, dtype=torch.bool)  # noqa: E731
            self.reward_spec = Composite(agents=Composite(reward=Unbounded(a), shape=b + (2,)), shape=b)
            self.done_spec = Composite(
                done=flag(),
                terminated=flag(),
                truncated=flag(),
                agents=Composite(done=agent_flag(), terminated=agent_flag(), truncated=agent_flag(), shape=b + (2,)),
                shape=b,
            )
        else:
            self.reward_spec = Unbounded(b + (1,), dtype=torch.float32)
            self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=b)

    def _ended(self) -> torch.Tensor:
        return self.t == self.ends if self.done_once else self.t >= self.ends

    def _obs(self, action: torch.Tensor | None) -> dict:
        t = self.t
        act0 = action[..., 0] if action is not None else torch.zeros(self.batch_size)
        ended = self._ended()
        return {
            "observation": torch.stack([t.float(), self.ids.float(), act0], -1),
            "nested": {"deep": {"x": toy_nested(self.ids, t)}, "count": self.step_count.clone()},
            "elapsed_steps": t.clone(),
            "success": t % 3 == 2,
            "fail": ended & self.terminate,
        }

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.t = self.t + 1
        self.step_count = self.step_count + 1
        t = self.t
        out = self._obs(tensordict.get("action"))
        done = self._ended().unsqueeze(-1)
        term = done & self.terminate.unsqueeze(-1)
        trunc = done & ~self.terminate.unsqueeze(-1)
        reward = toy_reward(self.ids, t).unsqueeze(-1)
        out.update(done=done, terminated=term, truncated=trunc)
        if self.multi_agent:
            agents = self.batch_size + (2, 1)
            scale = torch.tensor([1.0, 2.0]).reshape(2, 1)
            out["agents"] = TensorDict(
                reward=reward.unsqueeze(-2) * scale,
                done=done.unsqueeze(-2).expand(agents).clone(),
                terminated=term.unsqueeze(-2).expand(agents).clone(),
                truncated=trunc.unsqueeze(-2).expand(agents).clone(),
                batch_size=agents[:-1],
            )
        else:
            out["reward"] = reward
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        mask = torch.ones(self.batch_size, dtype=torch.bool) if reset is None else reset.reshape(self.batch_size)
        self.t = self.t.masked_fill(mask, 0)
        self.reset_count = self.reset_count + mask.long()
        out = self._obs(None)
        zeros = torch.zeros(self.batch_size + (1,), dtype=torch.bool)
        out.update(done=zeros, terminated=zeros.clone(), truncated=zeros.clone())
        if self.multi_agent:
            z = torch.zeros(self.batch_size + (2, 1), dtype=torch.bool)
            out["agents"] = TensorDict(done=z, terminated=z.clone(), truncated=z.clone(), batch_size=z.shape[:-1])
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _set_seed(self, seed: int | None) -> None:  # deterministic: nothing to seed
        return None


def serial_toy_env(
    ends: Sequence[int],
    terminate: Sequence[bool] | bool = True,
    *,
    done_once: bool = False,
    multi_agent: bool = False,
    **serial_kwargs,
):
    """A ``SerialEnv`` of ``batch_size=[]`` toy envs (ids ``0..B-1``): honours partial steps.

    The sub-envs (``env._envs[i]`` once started) hold the ``step_count`` counters.
    """
    from torchrl.envs import SerialEnv

    if isinstance(terminate, bool):
        terminate = [terminate] * len(ends)
    fns = [
        (lambda e=int(e), k=bool(k), i=i: ToyEnv(e, terminate=k, ids=i, done_once=done_once, multi_agent=multi_agent))
        for i, (e, k) in enumerate(zip(ends, terminate))
    ]
    return SerialEnv(len(ends), fns, **serial_kwargs)


if __name__ == "__main__":  # pragma: no cover
    import doctest

    doctest.testmod(verbose=False)
