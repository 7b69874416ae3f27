"""The checkpoints ``examples/ppo_torchrl.py``, ``examples/sac_torchrl.py`` and ``examples/trainers/train.py``
save: loading, checking, and the policy they hold (each a TanhNormal actor reading ``"observation"``;
``format`` says which). ``train.py``'s ``policy.pt`` holds its actor's config as the YAML composed it
(``actor``, resolved), so that the actor is rebuilt from it whatever the overrides were (the ``hydra`` extra).

One implementation for the evaluation scripts (``evaluate_gym.py``, both its
gym and its TorchRL backend):

- :func:`load_checkpoint` reads ``<out>/ppo_checkpoint.pt`` and checks that it
  is one (file there, a torch file, our ``format``, the expected task), raising
  :class:`CheckpointError` with what is wrong and what to do otherwise;
- :func:`policy_from_checkpoint` builds the actor with ``ppo_torchrl.make_models`` (or SAC's)
  for the env it will act in, after checking the observation and action sizes;
- :func:`numpy_policy` turns it into ``obs (numpy) -> action (numpy)`` for gym
  code, acting deterministically: the TanhNormal's ``tanh(loc)`` scaled to the
  action bounds (``ExplorationType.DETERMINISTIC``), as ``evaluate_policy`` does.

This file sits beside ``ppo_torchrl.py`` (``examples/`` is ``sys.path[0]`` when
a script there runs).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from ppo_torchrl import CHECKPOINT_FORMAT, make_models

SAC_FORMAT = "maniskill_torchrl.sac.v1"  # sac_torchrl.CHECKPOINT_FORMAT (imported lazily: torchrl's SAC)
TRAINER_FORMAT = "maniskill_torchrl.trainer.v1"  # trainers/train.py's POLICY_FORMAT (train.py needs hydra)
FORMATS = (CHECKPOINT_FORMAT, SAC_FORMAT, TRAINER_FORMAT)
CHECKPOINT_NAME = "ppo_checkpoint.pt"
CHECKPOINT_NAMES = (CHECKPOINT_NAME, "sac_checkpoint.pt", "policy.pt")
REQUIRED_KEYS = ("env_id", "obs_mode", "control_mode", "obs_dim", "act_dim", "hidden", "repeat", "policy")
TRAINER_KEYS = ("env_id", "obs_mode", "control_mode", "obs_dim", "act_dim", "actor", "policy")
_WHAT_TO_PASS = (
    f"pass the {CHECKPOINT_NAME} that examples/ppo_torchrl.py writes to its --out folder "
    f"(default outputs/ppo/{CHECKPOINT_NAME}), the sac_checkpoint.pt of examples/sac_torchrl.py, or the "
    "policy.pt that examples/trainers/train.py writes to its run folder"
)


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable, of another format or for another env."""


def load_checkpoint(path: str | Path, env_id: str | None = None) -> dict[str, Any]:
    """Loads and checks a checkpoint of the examples (on the CPU): PPO's, SAC's or train.py's ``policy.pt``.

    ``path`` is the file or the ``--out`` folder holding it. ``env_id``: the task
    the caller means to evaluate; ``None`` takes the checkpoint's. Raises
    :class:`CheckpointError` for a missing file, a file torch cannot load safely,
    another format, an incomplete dict or another task.
    """
    path = Path(path)
    if path.is_dir():
        found = [path / name for name in CHECKPOINT_NAMES if (path / name).is_file()]
        if not found:
            raise CheckpointError(f"checkpoint folder {path} has no {' or '.join(CHECKPOINT_NAMES)}: {_WHAT_TO_PASS}")
        path = found[0]
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} not found: {_WHAT_TO_PASS}")
    try:
        # weights_only: tensors and plain containers only, no arbitrary code from the file.
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError... by file kind
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(
            f"{path} is not a PyTorch checkpoint that torch.load(weights_only=True) can read "
            f"({type(exc).__name__}: {reason[:200]}): {_WHAT_TO_PASS}"
        ) from exc
    if not isinstance(ckpt, dict) or "format" not in ckpt:
        what = f"a {type(ckpt).__name__}" if not isinstance(ckpt, dict) else "a dict without a 'format' key"
        raise CheckpointError(
            f"{path} is not a maniskill_torchrl PPO checkpoint ({what}; expected format "
            f"{CHECKPOINT_FORMAT!r}). A bare state_dict, e.g. from ManiSkill's own PPO baseline, "
            f"holds no task or network sizes: evaluate it with that baseline, or {_WHAT_TO_PASS}"
        )
    if ckpt["format"] not in FORMATS:
        raise CheckpointError(
            f"{path} has checkpoint format {ckpt['format']!r}; this script reads {' or '.join(map(repr, FORMATS))}: "
            f"{_WHAT_TO_PASS} with this version of the examples"
        )
    trainer = ckpt["format"] == TRAINER_FORMAT
    if trainer:
        ckpt.setdefault("repeat", 1)
        ckpt.setdefault("hidden", None)
    missing = [k for k in (TRAINER_KEYS if trainer else REQUIRED_KEYS) if k not in ckpt]
    if missing:
        writer = "examples/trainers/train.py" if trainer else "examples/ppo_torchrl.py"
        raise CheckpointError(
            f"{path} is an incomplete {ckpt['format']} checkpoint (missing {', '.join(missing)}): "
            f"it was not written by this version of {writer} or was cut short; train again to rewrite it"
        )
    if ckpt["obs_mode"] != "state":
        raise CheckpointError(
            f"{path} was trained with obs_mode {ckpt['obs_mode']!r}; these scripts evaluate state policies only"
        )
    if env_id is not None and env_id != ckpt["env_id"]:
        raise CheckpointError(
            f"checkpoint {path} was trained on {ckpt['env_id']}, not on --env-id {env_id}: a policy only "
            f"acts on its own task. Drop --env-id (the checkpoint's task is the default) or pass "
            f"--env-id {ckpt['env_id']}"
        )
    ckpt["path"] = str(path)
    return ckpt


def check_sizes(ckpt: dict[str, Any], obs_dim: int, act_dim: int, control_mode: str | None = None) -> None:
    """Raises :class:`CheckpointError` unless the env built has the checkpoint's observation / action sizes."""
    where = ckpt.get("path", "the checkpoint")
    if obs_dim != ckpt["obs_dim"]:
        raise CheckpointError(
            f"observation size mismatch: {where} expects {ckpt['obs_dim']} state values "
            f"({ckpt['env_id']}, control mode {ckpt['control_mode']}), the env built gives {obs_dim}. "
            "Evaluate with the task, control mode and ManiSkill version it was trained with"
        )
    if act_dim != ckpt["act_dim"]:
        mode = f" (control mode {control_mode})" if control_mode else ""
        raise CheckpointError(
            f"action size mismatch: {where} outputs {ckpt['act_dim']} actions (control mode "
            f"{ckpt['control_mode']}), the env built takes {act_dim}{mode}. Drop --control-mode "
            f"(the checkpoint's is the default) or pass --control-mode {ckpt['control_mode']}"
        )


def specs_from_spaces(observation_space: Any, action_space: Any) -> SimpleNamespace:
    """What ``make_models`` reads from a TorchRL env, from one sub-env's gymnasium spaces (gym code)."""
    from torchrl.data import Bounded, Composite, Unbounded

    cpu = torch.device("cpu")
    low, high = (torch.as_tensor(b) for b in (action_space.low, action_space.high))
    action = Bounded(low=low, high=high, shape=low.shape, dtype=low.dtype, device=cpu)
    obs = Unbounded(shape=torch.Size(observation_space.shape), dtype=torch.float32, device=cpu)
    return SimpleNamespace(
        observation_spec=Composite(observation=obs),
        action_spec_unbatched=action,
        full_action_spec_unbatched=Composite(action=action),
    )


def policy_from_checkpoint(ckpt: dict[str, Any], env: Any, control_mode: str | None = None) -> Any:
    """The checkpoint's actor (``ProbabilisticActor``, CPU, eval mode) for ``env``.

    ``env``: a TorchRL env, or :func:`specs_from_spaces` of gym spaces. Sizes are
    checked first (:func:`check_sizes`), so a mismatch is an error message, not a shape trace.
    """
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec_unbatched.shape[-1]
    check_sizes(ckpt, obs_dim, act_dim, control_mode)
    if ckpt["format"] == TRAINER_FORMAT:
        policy = actor_from_config(ckpt["actor"])
        built_by = "its saved config (the actor of examples/trainers/train.py)"
    elif ckpt["format"] == SAC_FORMAT:
        from sac_torchrl import make_models as make_sac_models

        policy, _ = make_sac_models(obs_dim, env.action_spec_unbatched, ckpt["hidden"], torch.device("cpu"))
        built_by = f"examples/sac_torchrl.py (hidden {ckpt['hidden']})"
    else:
        policy, _ = make_models(env, ckpt["hidden"], torch.device("cpu"))
        built_by = f"examples/{ckpt.get('algorithm', 'ppo')}_torchrl.py (hidden {ckpt['hidden']})"
    try:
        policy.load_state_dict(ckpt["policy"])
    except (RuntimeError, KeyError) as exc:
        raise CheckpointError(
            f"the policy weights in {ckpt.get('path', 'the checkpoint')} do not fit the actor of "
            f"{built_by}, obs {obs_dim}, act {act_dim}: {str(exc).splitlines()[0]}. "
            "Re-train with this version of the example"
        ) from exc
    return policy.eval()


def actor_from_config(actor_yaml: str) -> Any:
    """The actor ``train.py``'s YAML built (TorchRL's model config, resolved, as saved in ``policy.pt``),
    with fresh weights, on the CPU. Needs the ``hydra`` extra, as ``train.py`` does."""
    from maniskill_torchrl._internal.extras import require

    require("hydra", "evaluating a policy.pt of examples/trainers/train.py")
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    import maniskill_torchrl.configs  # noqa: F401  (the library's config targets, e.g. the ppo_mlp network)

    return instantiate(OmegaConf.create(actor_yaml))


def actor_sizes(actor: Any) -> tuple[int, int]:
    """``(obs_dim, act_dim)`` of an MLP actor reading ``"observation"``: its first ``Linear``'s inputs,
    and the action its deterministic step gives for a zero observation (what ``train.py`` records)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    first = next(m for m in actor.modules() if isinstance(m, torch.nn.Linear))
    td = TensorDict({"observation": torch.zeros(1, first.in_features, device=first.weight.device)}, batch_size=[1])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        action = actor(td).get("action")
    return first.in_features, action.shape[-1]


def numpy_policy(policy: Any) -> Callable[[np.ndarray], np.ndarray]:
    """``obs [N, obs_dim] -> action [N, act_dim]`` in numpy, deterministic (the TanhNormal's tanh(loc))."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    def act(obs: np.ndarray) -> np.ndarray:
        td = TensorDict({"observation": torch.as_tensor(obs)}, batch_size=[obs.shape[0]])
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return policy(td).get("action").numpy()

    return act
