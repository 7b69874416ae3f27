"""Per-env episode statistics, laid out by one field table.

:data:`EPISODE_FIELDS` defines the ``"episode"`` entry once: its names, dtypes,
what each field computes and which task info it needs. The ``EpisodeMetrics``
spec, :meth:`EpisodeStats.zeros`, :meth:`EpisodeStats.update` and the gym shim's
``info["episode"]`` are all derived from it.

:class:`NumpyOrderSums` sums episode returns bit for bit as ``numpy.sum`` gives them (what
``CPUGymWrapper`` reports): ``numpy.sum`` of a float32 array adds pairwise (blocks of 8 running
partial sums folded as a tree, recursion above 128 elements: numpy's ``pairwise_sum``), so the
split points move as an episode grows and no running total reproduces it past 8 steps. It keeps
each env's rewards at their positions in the episode and lets numpy itself sum them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from maniskill_torchrl._private import entries, new_tensordict

__all__ = ["EPISODE_FIELDS", "SUMMATIONS", "EpisodeField", "EpisodeStats", "NumpyOrderSums", "episode_fields"]


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


SUMMATIONS = ("numpy", "running")


class EpisodeStats:
    """Per-env episode metrics, one step at a time, with the running state passed in.

    :meth:`update` takes the previous step's ``"episode"`` TensorDict (None at an episode's
    start), one step's reward (and ``success`` / ``fail`` where the task reports them) for every
    env, and returns the new ``"episode"`` entries of :data:`EPISODE_FIELDS`:

    - ``return``: the sum of the episode's rewards, float32;
    - ``episode_len``: steps since the env's last reset (int64);
    - ``reward``: ``return / episode_len``;
    - ``success_once`` / ``fail_once``: whether success / fail was ever reported;
    - ``success_at_end`` / ``fail_at_end``: the value at this step.

    The caller keeps the state (the returned TensorDict): :class:`EpisodeMetrics
    <maniskill_torchrl.transforms.EpisodeMetrics>` in the env's tensordicts, as TorchRL's
    ``StepCounter`` does, the gym shim in its wrapper.

    Two summations of ``return``, one per anchor:

    - ``"numpy"``: bit for bit ``numpy.sum`` of the episode's rewards, as ManiSkill's
      ``CPUGymWrapper(record_metrics=True)`` reports it. It keeps each env's rewards by position
      (:class:`~NumpyOrderSums`) and costs one numpy reduction per env
      per step on the host. Default on the CPU. An env whose ``previous`` state is not the
      continuation of the rewards kept (a step from an earlier episode passed back) goes on
      from ``previous["return"]`` with a running sum until its next reset: bit-equality with
      ``CPUGymWrapper`` holds on linear rollouts, and the return always continues ``previous``.
    - ``"running"``: ``return + reward`` in float32, as ``ManiSkillVectorEnv(record_metrics=True)``
      keeps it on the GPU sim: a few tensor ops per step whatever the batch and the episode
      lengths, and no host sync. Default on other devices.

    Args:
        batch_size: the env batch.
        device: where the statistics live (the env's device).
        has_success, has_fail: whether the task reports ``success`` / ``fail``.
        summation: ``"numpy"``, ``"running"`` or None (by device, as above).
        native_return (bool): with ``"numpy"``, keep ``numpy.sum``'s dtype of the task's own
            rewards, as ``CPUGymWrapper`` reports it (bool rewards: int64 ``return`` and float64
            ``reward``; float64 rewards: float64 both): the gym shim's. False (default): float32.
        arrays (str): ``"torch"`` (default): :meth:`update` takes tensors and returns a TensorDict.
            ``"numpy"`` (with ``summation="numpy"`` on the CPU): it takes numpy arrays and returns
            a dict of numpy arrays, the same entries computed by the same code without a tensor
            op: the gym shim's, whose API is numpy (a torch op on a one-env batch costs
            microseconds, a numpy one a fraction of that). Only :meth:`update` and :meth:`zeros`.

    Examples:
        >>> import torch
        >>> from maniskill_torchrl._internal.episode_stats import EpisodeStats
        >>> stats = EpisodeStats([2], torch.device("cpu"), has_success=True, has_fail=False)
        >>> ep = stats.update(None, torch.tensor([1.0, 2.0]), success=torch.tensor([False, True]))
        >>> ep = stats.update(ep, torch.tensor([1.0, 2.0]), success=torch.tensor([False, False]))
        >>> ep["return"].tolist(), ep["success_once"].tolist(), ep["success_at_end"].tolist()
        ([2.0, 4.0], [False, True], [False, False])
        >>> ep = stats.restart(ep, torch.tensor([False, True]))
        >>> stats.update(ep, torch.tensor([1.0, 2.0]), success=torch.tensor([False, False]))["episode_len"].tolist()
        [3, 1]
    """

    def __init__(
        self,
        batch_size: Sequence[int] | torch.Size,
        device: torch.device | str | None = None,
        *,
        has_success: bool = True,
        has_fail: bool = True,
        summation: str | None = None,
        native_return: bool = False,
        gather: Callable[[torch.device], Callable[[dict], dict]] | None = None,
        arrays: str = "torch",
    ) -> None:
        self.batch_size = torch.Size(batch_size)
        # What moves host-side sums up to an accelerator in one transfer, made for a device (the env
        # adapter's gather); without it, the sums on an accelerator take the device path.
        self._make_gather = gather
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.has_success = has_success
        self.has_fail = has_fail
        self.fields = episode_fields(has_success, has_fail)
        if summation is None:
            summation = "numpy" if self.device.type == "cpu" else "running"
        if summation not in SUMMATIONS:
            raise ValueError(f"summation={summation!r}: use one of {SUMMATIONS} (or None: by device).")
        #: ``"numpy"`` or ``"running"`` (see the class docstring)
        self.summation = summation
        if native_return and summation != "numpy":
            raise ValueError("native_return=True needs summation='numpy' (numpy.sum's dtypes).")
        if arrays not in ("torch", "numpy"):
            raise ValueError(f"arrays={arrays!r}: use 'torch' or 'numpy'.")
        if arrays == "numpy" and (summation != "numpy" or self.device.type != "cpu"):
            raise ValueError("arrays='numpy' needs summation='numpy' on the CPU.")
        #: ``"torch"`` or ``"numpy"``: what :meth:`update` takes and returns
        self.arrays = arrays
        self._numpy = NumpyOrderSums(self.batch_size, native=native_return) if summation == "numpy" else None
        self._set_host_side()

    def to(self, device: torch.device | str) -> EpisodeStats:
        """The statistics on ``device`` from now on (the summation and its history kept). Returns self."""
        self.device = torch.device(device)
        self._set_host_side()
        return self

    def _set_host_side(self) -> None:
        # numpy's summation for an env on an accelerator (the CPU sim with device="cuda"): summed
        # on the host from a host-side mirror of the last output (no device read), then moved up
        # in one transfer.
        self._host = self._numpy is not None and self.device.type != "cpu" and self._make_gather is not None
        self._up = self._make_gather(self.device) if self._host else None
        self._mirror: tuple[TensorDictBase, dict] | None = None

    def zeros(self) -> TensorDict | dict[str, np.ndarray]:
        """The ``"episode"`` entries of a fresh episode (all zeros), as :meth:`update` lays them out."""
        b, dev = self.batch_size, self.device
        out = {f.name: torch.zeros(b, dtype=f.dtype, device=dev) for f in self.fields}
        if self.arrays == "numpy":
            return {name: value.numpy() for name, value in out.items()}
        out = new_tensordict(out, batch_size=b, device=dev)
        if self._host:
            self._mirror = (out, {f.name: torch.zeros(b, dtype=f.dtype) for f in self.fields})
        return out

    def restart(self, previous: TensorDictBase, mask: torch.Tensor) -> TensorDictBase:
        """``previous`` with the envs in ``mask`` (a bool tensor shaped as the batch) back at zero."""
        mask = mask.reshape(self.batch_size)
        if self._host:  # on the host mirror (the mask read once, at a reset), moved up once
            mask = mask.cpu()
            out = {k: v.masked_fill(mask, 0) for k, v in self._host_previous(previous).items()}
            return self._moved_up(out)
        # Out of place: ``previous`` may be a step the caller keeps.
        return previous.apply(lambda value: value.masked_fill(mask, 0))

    def _host_previous(self, previous: TensorDictBase) -> dict:
        """``previous`` on the host: the mirror of this object's last output if it is that output
        (no device read), else read from the device."""
        mirror = self._mirror
        if mirror is not None and all(previous.get(k) is mirror[0].get(k) for k in mirror[1]):
            return mirror[1]
        return {f.name: previous.get(f.name).cpu() for f in self.fields}

    def _moved_up(self, out: dict) -> TensorDict:
        """Host entries ``out`` on the device in one transfer; the host side kept as the mirror."""
        moved = new_tensordict(self._up(out), batch_size=self.batch_size, device=self.device)
        # The at_end flags may be views of an env's host buffer, which its later steps rewrite.
        self._mirror = (moved, {f.name: _kept(out[f.name], f) for f in self.fields})
        return moved

    def update(
        self,
        previous: TensorDictBase | None,
        reward: torch.Tensor,
        success: torch.Tensor | None = None,
        fail: torch.Tensor | None = None,
        *,
        host: Callable[[torch.Tensor], torch.Tensor | None] | None = None,
    ) -> TensorDict:
        """The ``"episode"`` TensorDict after one more step of every env.

        ``previous`` is the last step's (or :meth:`restart`'s) output, None for a fresh episode of
        every env. Nothing is written into ``previous``. ``host`` (optional) gives the host values
        of a device tensor where they are at hand (an env's
        :meth:`~maniskill_torchrl.ManiSkillWrapper.host_value`), else None: with numpy's
        summation on an accelerator, ``reward``, ``success`` and ``fail`` are read from there
        rather than from the device. With ``arrays="numpy"``: numpy arrays in, the entries as a
        dict of numpy arrays out.
        """
        if self._host:
            return self._update_on_host(previous, reward, success, fail, host)
        if previous is None:
            previous = self.zeros()
        out = self._next(_fields_of(previous), reward, success, fail)
        if self.arrays == "numpy":
            return out
        return new_tensordict(out, batch_size=self.batch_size, device=self.device)

    def _update_on_host(self, previous, reward, success, fail, host) -> TensorDict:
        def on_host(value: torch.Tensor | None) -> torch.Tensor | None:
            if value is None or value.device.type == "cpu":
                return value
            mirrored = host(value) if host is not None else None
            return mirrored if mirrored is not None else value.cpu()

        if previous is None:
            self.zeros()
            state = self._mirror[1]
        else:
            state = self._host_previous(previous)
        return self._moved_up(self._next(state, on_host(reward), on_host(success), on_host(fail)))

    def _next(self, previous: Any, reward: torch.Tensor, success: Any, fail: Any) -> dict:
        """The entries after one more step, from ``previous``'s (a TensorDict or a dict of them)."""
        b = self.batch_size
        n = previous.get("episode_len")
        reward = _shaped(reward, b)
        if self._numpy is not None:
            total = self._numpy.add(reward, n, previous.get("return"))
        else:
            # ManiSkillVectorEnv's ``returns += rew`` into float32 (rew promoted first, as torch does).
            total = torch.add(previous.get("return"), reward).to(torch.float32)
        n = n + 1
        flags = {"success": success, "fail": fail}
        flags = {k: _shaped(v, b) for k, v in flags.items() if v is not None}
        out = {}
        for f in self.fields:
            kind = f.kind
            if kind == "sum":
                out[f.name] = total
            elif kind == "count":
                out[f.name] = n
            elif kind == "mean":
                out[f.name] = _mean(total, n)
            elif kind == "once":
                out[f.name] = previous.get(f.name) | flags[f.source]
            else:  # "at_end"
                out[f.name] = flags[f.source]
        return out


def _mean(total: torch.Tensor | np.ndarray, n: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """``total / n`` as numpy's true division of a sum by a python int: a float sum keeps its
    dtype, an int64 one gives float64. Tensors or numpy arrays: numpy would promote a float32
    array divided by an int64 one to float64, so ``n`` takes a float sum's dtype first (exact:
    a count below 2**24; torch's float32 / int64 divides in float32 just so)."""
    if isinstance(total, np.ndarray):
        return total / n.astype(total.dtype) if total.dtype.kind == "f" else total / n
    return (total if total.is_floating_point() else total.to(torch.float64)) / n


def _fields_of(td: TensorDictBase | dict) -> TensorDictBase | dict:
    """``td``'s entries by name: a plain TensorDict's own dict (a lookup per entry costs a dict
    access, not ``TensorDict.get``'s key parsing), any other TensorDict (or a dict) as it is."""
    return entries(td) if type(td) is TensorDict else td


def _shaped(value: torch.Tensor | np.ndarray, shape: torch.Size | tuple[int, ...]) -> torch.Tensor | np.ndarray:
    """``value.reshape(shape)``, or ``value`` itself where it has that shape already (a reshape
    to the same shape still makes a view: microseconds per step on the CPU sim)."""
    return value if value.shape == shape else value.reshape(shape)


def _kept(value: torch.Tensor, field: EpisodeField) -> torch.Tensor:
    """``value`` as the host mirror keeps it: an at_end flag copied (it may be an env's buffer)."""
    return value.clone() if field.kind == "at_end" else value


class NumpyOrderSums:
    """Per-env episode returns equal to ``numpy.sum`` of the episode's float32 rewards.

    :meth:`add` writes each env's reward at its position in its episode (its length so far,
    which the caller keeps) and returns numpy's sum of the rewards up to there. The history is
    indexed by position, not appended to, so a rollout that branches again from an earlier step
    of the same episode (``env.rollout(tensordict=root)`` twice) overwrites the abandoned branch.

    The caller's state decides, not the history: :meth:`add` is given the return the caller
    holds for the step before (``previous``). An env continues numpy's sum only where that
    return is the one :meth:`add` gave at that position of the history it still holds (the
    last branch written, not overwritten since). Otherwise (a step kept from an earlier
    episode, another env's state, a state made by hand), the history does not hold that
    episode's rewards: the env goes on with a running sum, ``previous + reward``, until its
    next reset. So ``numpy.sum``'s bits hold on linear rollouts and on branches from a root of
    the last episode run (what ``CPUGymWrapper`` sees); elsewhere the return is a float32
    running sum from the caller's state, never another episode's rewards. (A step of another
    episode whose return has the very same bits at the same length is taken for the one held:
    the sum is then over rewards with that same float32 prefix sum, equal up to rounding.)

    One numpy reduction per env per step, on the host: the CPU sim's summation (a handful of
    envs). The GPU sim's anchor, ``ManiSkillVectorEnv(record_metrics=True)``, keeps a running
    float32 sum instead (:class:`EpisodeStats`,
    ``summation="running"``).

    Args:
        batch_size: the env batch.
        native (bool): keep the rewards' own dtype, as ``numpy.sum`` of ManiSkill's numpy rewards
            does (bool rewards sum to int64, float64 ones to float64: what ``CPUGymWrapper``
            reports); False (default): rewards and sums in float32.

    Examples:
        >>> import numpy as np, torch
        >>> sums = NumpyOrderSums([1])
        >>> rewards = torch.rand(300).float()
        >>> total = None
        >>> for n, r in enumerate(rewards):
        ...     total = sums.add(r.reshape(1), torch.tensor([n]), total)
        >>> total.item() == float(np.sum(rewards.numpy()))
        True
    """

    def __init__(self, batch_size: Sequence[int] | torch.Size, *, native: bool = False) -> None:
        self.batch_size = torch.Size(batch_size)
        self.native = native
        n = self.batch_size.numel()
        self._flat = torch.Size([n])  # the batch as one dim: the layout of the history's rows
        # Per env and position in the episode: the reward, the return add() gave, and whether
        # that return was numpy's sum of the episode's rewards (False: a running sum).
        self._hist = np.zeros((n, 256), np.float32)
        self._sums = np.zeros((n, 256), np.float32)
        self._exact = np.zeros((n, 256), bool)
        # The last position written per env: the positions after it are an abandoned branch.
        self._top = [-1] * n

    def _fit(self, last: int, dtype: np.dtype) -> None:
        """Room for position ``last`` in rewards of ``dtype``."""
        hist = self._hist
        if last < hist.shape[1] and hist.dtype == dtype:
            return
        width = max(hist.shape[1], 2 * (last + 1))
        # numpy.sum's dtype: float32 for float32 rewards, int64 for bool ones, float64 for float64.
        sum_dtype = np.add.reduce(np.zeros((1, 1), dtype), axis=1).dtype
        for name, kind in (("_hist", dtype), ("_sums", sum_dtype), ("_exact", bool)):
            old = getattr(self, name)
            grown = np.zeros((old.shape[0], width), kind)
            grown[:, : old.shape[1]] = old
            setattr(self, name, grown)

    def add(self, reward: torch.Tensor, position: torch.Tensor, previous: torch.Tensor | None = None) -> torch.Tensor:
        """Each env's return after ``reward`` at ``position`` (0 for an episode's first step).

        ``reward``, ``position`` and ``previous`` are shaped as the batch. ``previous`` is the
        return the caller holds for position - 1 (not read at position 0): where it is not the
        one this history gave there, the env's return is ``previous + reward`` (see the class
        docstring). None: every env continues the history (a caller that keeps no state). The
        result is float32 (or numpy.sum's dtype with ``native``), shaped as the batch, on
        ``reward``'s device; all three numpy arrays instead: a numpy array.
        """
        flat = self._flat
        as_numpy = isinstance(reward, np.ndarray)
        if as_numpy:
            on_host = True
            rewards = _shaped(reward, flat)
            if not self.native and rewards.dtype != np.float32:
                rewards = rewards.astype(np.float32)
        else:
            on_host = reward.is_cpu
            rewards = _shaped(reward.detach(), flat)
            dtype = rewards.dtype if self.native else torch.float32
            if not on_host or rewards.dtype != dtype:
                rewards = rewards.to("cpu", dtype)
            rewards = rewards.numpy()
        positions = _shaped(position, flat).tolist()
        held = None if previous is None else _shaped(previous, flat).tolist()
        self._fit(max(positions, default=0), rewards.dtype)
        hist, sums, exact, top = self._hist, self._sums, self._exact, self._top
        scalar = sums.dtype.type
        totals = np.empty(len(positions), sums.dtype)
        # One env at a time: each sums its own episode's length.
        for i, k in enumerate(positions):
            hist[i, k] = rewards[i]
            # Continues the history: a first step, or the return given at k - 1 on the branch
            # last written (nothing after top[i] is). Else a running sum from the caller's return.
            follows = k == 0 or held is None or (k <= top[i] + 1 and exact[i, k - 1] and sums[i, k - 1] == held[i])
            total = np.add.reduce(hist[i, : k + 1]) if follows else scalar(held[i]) + rewards[i]
            totals[i] = sums[i, k] = total
            exact[i, k] = follows
            top[i] = k
        if as_numpy:
            return _shaped(totals, self.batch_size)
        out = _shaped(torch.from_numpy(totals), self.batch_size)
        return out if on_host else out.to(reward.device)
