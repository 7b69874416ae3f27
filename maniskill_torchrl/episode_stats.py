"""Per-env episode statistics, laid out by one field table.

:data:`EPISODE_FIELDS` defines the ``"episode"`` entry once: its names, dtypes,
what each field computes and which task info it needs. The ``EpisodeMetrics``
spec, :meth:`EpisodeStats.zeros`, :meth:`EpisodeStats.update` and the gym shim's
``info["episode"]`` are all derived from it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict

from maniskill_torchrl._private import new_tensordict
from maniskill_torchrl.numpy_sum import RunningNumpySum

__all__ = ["EPISODE_FIELDS", "EpisodeField", "EpisodeStats", "episode_fields"]


@dataclass(frozen=True)
class EpisodeField:
    """One entry of ``"episode"``.

    ``kind`` says what it holds: ``"sum"`` (the episode's rewards summed as
    ``numpy.sum``), ``"count"`` (steps since the reset), ``"mean"`` (sum / count),
    ``"once"`` (``source`` ever True in the episode), ``"at_end"`` (``source`` at
    this step). ``source`` is the task info a flag field needs (``"success"`` /
    ``"fail"``): the field exists only where the task reports it.
    """

    name: str
    dtype: torch.dtype
    kind: str
    source: str | None = None


EPISODE_FIELDS: tuple[EpisodeField, ...] = (
    EpisodeField("return", torch.float32, "sum"),
    EpisodeField("episode_len", torch.int64, "count"),
    EpisodeField("reward", torch.float32, "mean"),
    EpisodeField("success_once", torch.bool, "once", "success"),
    EpisodeField("success_at_end", torch.bool, "at_end", "success"),
    EpisodeField("fail_once", torch.bool, "once", "fail"),
    EpisodeField("fail_at_end", torch.bool, "at_end", "fail"),
)


def episode_fields(has_success: bool, has_fail: bool) -> tuple[EpisodeField, ...]:
    """The fields of a task that reports ``success`` / ``fail`` or not, in table order."""
    sources = {None, *(["success"] if has_success else []), *(["fail"] if has_fail else [])}
    return tuple(f for f in EPISODE_FIELDS if f.source in sources)


class EpisodeStats:
    """Running per-env episode metrics, reset per env.

    ``update`` takes one step's reward (and ``success`` / ``fail`` where the
    task reports them) for every env and returns the ``"episode"`` entries of
    :data:`EPISODE_FIELDS`:

    - ``return``: the sum of the episode's rewards, float32, summed as
      ``numpy.sum`` does (bit for bit with ManiSkill's ``CPUGymWrapper``);
    - ``episode_len``: steps since the env's last reset (int64);
    - ``reward``: ``return / episode_len``;
    - ``success_once`` / ``fail_once``: whether success / fail was ever reported;
    - ``success_at_end`` / ``fail_at_end``: the value at this step.

    Args:
        batch_size: the env batch.
        device: where the statistics live (the env's device).
        has_success, has_fail: whether the task reports ``success`` / ``fail``.

    Examples:
        >>> import torch
        >>> from maniskill_torchrl.episode_stats import EpisodeStats
        >>> stats = EpisodeStats([2], torch.device("cpu"), has_success=True, has_fail=False)
        >>> ep = stats.update(torch.tensor([1.0, 2.0]), success=torch.tensor([False, True]))
        >>> ep = stats.update(torch.tensor([1.0, 2.0]), success=torch.tensor([False, False]))
        >>> ep["return"].tolist(), ep["success_once"].tolist(), ep["success_at_end"].tolist()
        ([2.0, 4.0], [False, True], [False, False])
        >>> stats.reset(torch.tensor([False, True]))
        >>> stats.update(torch.tensor([1.0, 2.0]), success=torch.tensor([False, False]))["episode_len"].tolist()
        [3, 1]
    """

    def __init__(
        self,
        batch_size: Sequence[int] | torch.Size,
        device: torch.device | str | None = None,
        *,
        has_success: bool = True,
        has_fail: bool = True,
    ) -> None:
        self.batch_size = torch.Size(batch_size)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.has_success = has_success
        self.has_fail = has_fail
        self.fields = episode_fields(has_success, has_fail)
        self._sum = RunningNumpySum(self.batch_size, self.device)
        self._zero_state()

    def _zero_state(self) -> None:
        b, dev = self.batch_size, self.device
        self._return = torch.zeros(b, dtype=torch.float32, device=dev)
        self._len = torch.zeros(b, dtype=torch.int64, device=dev)
        self._once = {f.source: torch.zeros(b, dtype=torch.bool, device=dev) for f in self.fields if f.kind == "once"}

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Starts a new episode for the envs in ``mask`` (all envs if ``None``)."""
        # Out of place: earlier "episode" outputs share these tensors.
        if mask is None:
            self._zero_state()
            self._sum.reset()
            return
        mask = mask.reshape(self.batch_size)
        self._return = self._return.masked_fill(mask, 0)
        self._len = self._len.masked_fill(mask, 0)
        self._once = {k: v.masked_fill(mask, False) for k, v in self._once.items()}

    def zeros(self) -> TensorDict:
        """The ``"episode"`` TensorDict of a fresh episode (all zeros), as :meth:`update` lays it out."""
        b, dev = self.batch_size, self.device
        out = {f.name: torch.zeros(b, dtype=f.dtype, device=dev) for f in self.fields}
        return new_tensordict(out, batch_size=b, device=dev)

    def update(
        self,
        reward: torch.Tensor,
        success: torch.Tensor | None = None,
        fail: torch.Tensor | None = None,
    ) -> TensorDict:
        """Adds one step for every env and returns the ``"episode"`` TensorDict."""
        b = self.batch_size
        n = self._len
        self._return = total = self._sum.add(self._return, reward.reshape(b).to(torch.float32), n)
        n = self._len = n + 1
        flags = {"success": success, "fail": fail}
        once = self._once
        out = {}
        for f in self.fields:
            kind = f.kind
            if kind == "sum":
                out[f.name] = total
            elif kind == "count":
                out[f.name] = n
            elif kind == "mean":
                out[f.name] = total / n
            elif kind == "once":
                once[f.source] = once[f.source] | flags[f.source].reshape(b)
                out[f.name] = once[f.source]
            else:  # "at_end"
                out[f.name] = flags[f.source].reshape(b)
        return new_tensordict(out, batch_size=b, device=self.device)
