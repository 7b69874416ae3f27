"""Every private TorchRL / tensordict name the library relies on, in one place.

TorchRL 0.14 and tensordict 0.14 keep these out of their public API; each is used
for speed (the per-step path of the CPU sim counts microseconds) or because the
public class is the only way in. When an upgrade renames one, this module is the
one to change. The tensordict names are imported eagerly; the gym shim uses them and
must not import TorchRL, so the TorchRL ones are reached through the objects passed in.

- :func:`new_tensordict`: ``TensorDict._new_unsafe``, a TensorDict from a dict of
  tensors already shaped for the batch, without per-entry validation.
- :func:`entries`: ``TensorDict._tensordict``, the top-level dict of a TensorDict.
- :func:`has_names`: ``TensorDictBase._has_names()``, whether it has dim names.
- :func:`fast_apply`: ``TensorDictBase._fast_apply``, ``apply`` without the checks.
- :func:`env_step`: ``EnvBase._step``, one step without ``EnvBase.step``'s checks and
  bookkeeping (``ActionRepeat``'s inner steps).
- :func:`complete_done`: ``EnvBase._complete_done``, fills missing done entries
  as ``TransformedEnv`` does.
- :func:`done_flags`, :func:`uses_buffers`, :func:`workers`, :func:`start_method`,
  :func:`shutdown_workers`: the private attributes of
  ``torchrl.envs.ParallelEnv`` that :mod:`maniskill_torchrl.parallel` reads (its
  overrides of ``_wait_for_workers`` / ``_start_workers`` keep their TorchRL names).
- :func:`trainer_ops`: ``Trainer._<dest>_ops``, the ops a ``torchrl.trainers.Trainer`` registered
  at one point of its loop (:mod:`maniskill_torchrl.trainer_hooks` finds the replay buffer's
  ``extend`` there).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from tensordict import TensorDict, TensorDictBase

__all__ = [
    "complete_done",
    "done_flags",
    "entries",
    "env_step",
    "fast_apply",
    "has_names",
    "new_tensordict",
    "shutdown_workers",
    "start_method",
    "trainer_ops",
    "uses_buffers",
    "workers",
]

# ------------------------------------------------------------------ tensordict
#: ``new_tensordict(source, batch_size=..., device=...)``: no copy, no validation.
new_tensordict: Callable[..., TensorDict] = TensorDict._new_unsafe


def entries(td: TensorDict) -> dict[str, Any]:
    """The top-level ``{key: tensor or sub-TensorDict}`` dict of a plain TensorDict (not a copy)."""
    return td._tensordict


def has_names(td: TensorDictBase) -> bool:
    return td._has_names()


def fast_apply(td: TensorDictBase, fn: Callable, *others: TensorDictBase, **kwargs: Any) -> TensorDictBase:
    return td._fast_apply(fn, *others, **kwargs)


# ---------------------------------------------------------------------- torchrl
def env_step(env: Any, td: TensorDictBase) -> TensorDictBase:
    """``env._step(td)``: the env's own step, returning the ``"next"`` data."""
    return env._step(td)


def complete_done(env: Any, td: TensorDictBase) -> None:
    """Fills the done entries ``td`` lacks from those it has, as ``TransformedEnv._step`` does."""
    env._complete_done(env.full_done_spec, td)


def done_flags(env: Any) -> tuple[Any, Any]:
    """A ``ParallelEnv``'s shared-memory done flags and its worker -> flag index map."""
    return env._shm_done_flags, env._worker_indices


def uses_buffers(env: Any) -> bool:
    return env._use_buffers


def workers(env: Any) -> list:
    """A ``ParallelEnv``'s worker processes."""
    return env._workers


def start_method(env: Any) -> str | None:
    return env._mp_start_method


def shutdown_workers(env: Any) -> None:
    env._shutdown_workers()


def trainer_ops(trainer: Any, dest: str) -> list[tuple[Callable, dict]]:
    """The ``(op, kwargs)`` pairs a ``torchrl.trainers.Trainer`` runs at ``dest`` (``"pre_epoch"``...),
    in order: ``Trainer._<dest>_ops``, what ``register_op(dest, op)`` appends to."""
    return getattr(trainer, f"_{dest}_ops")
