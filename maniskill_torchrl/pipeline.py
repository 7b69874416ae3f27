"""The one recipe that stacks the library's transforms on a ManiSkill env.

The CLI demo, the examples (PPO training and evaluation, Ray) and the README build
their envs with :func:`make_env`, so the order of the transforms is written once:
``ManiSkillEnv [-> FlattenRGBD] [-> IgnoreTerminations] [-> ActionRepeat] [-> EpisodeMetrics]``.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import Compose, TransformedEnv

from maniskill_torchrl._internal.repeat import check_repeat
from maniskill_torchrl.envs.engine_env import ManiSkillEnv
from maniskill_torchrl.transforms.action_repeat import ActionRepeat
from maniskill_torchrl.transforms.episode_metrics import EpisodeMetrics
from maniskill_torchrl.transforms.flatten_rgbd import FlattenRGBD
from maniskill_torchrl.transforms.terminations import IgnoreTerminations

__all__ = ["make_env"]


def make_env(
    env_id: str,
    *,
    num_envs: int | None = None,
    repeat: int = 1,
    ignore_terminations: bool = False,
    metrics: bool = True,
    flatten_rgbd: dict[str, Any] | None = None,
    **maniskill_kwargs: Any,
) -> TransformedEnv:
    """A ManiSkill task with the library's transforms, in their one sensible order.

    - ``num_envs=None``: one unbatched CPU-sim env (``ManiSkillEnv(env_id, batch_size=[])``,
      batch ``[]``): the worker of a ``ParallelEnv`` / ``SerialEnv``, a ``MultiSyncCollector``
      or a Ray collector. ``functools.partial(make_env, env_id, ...)`` pickles into worker
      processes.
    - ``num_envs=N``: ``ManiSkillEnv(env_id, num_envs=N)``, batch ``[N]`` (one GPU simulator
      with ``sim_backend="gpu"``, one process per env on the CPU sim).

    Then ``FlattenRGBD(**flatten_rgbd)`` where given (camera observations as ManiSkill's visual
    baselines flatten them), ``IgnoreTerminations`` (episodes run to the time limit, as ManiSkill's evaluation
    does), ``ActionRepeat(repeat)`` where ``repeat > 1`` (inside the worker: no round trip
    per inner step) and ``EpisodeMetrics`` last, so that episode lengths count agent steps
    and repeated rewards arrive summed. The result is always a ``TransformedEnv``, possibly
    with no transform (``env.transform`` and ``env.append_transform`` work alike); for a bare
    worker env, whose steps skip a transformed env's bookkeeping, use
    ``ManiSkillEnv(env_id, batch_size=[])`` directly.

    Args:
        env_id: a registered ManiSkill task, e.g. ``"PickCube-v1"``.
        num_envs: ``None`` for one unbatched CPU env, else the batch size.
        repeat: inner steps per agent step (``ActionRepeat``; 1: none).
        ignore_terminations: add ``IgnoreTerminations``.
        metrics: add ``EpisodeMetrics``.
        flatten_rgbd: the options of a :class:`~maniskill_torchrl.transforms.FlattenRGBD` put first
            (``{"depth": False}``: ManiSkill's PPO-from-rgb inputs); ``None``: none.
        **maniskill_kwargs: passed to :class:`~maniskill_torchrl.ManiSkillEnv` (``obs_mode``,
            ``control_mode``, ``sim_backend``, ``render_mode``, ``max_episode_steps``...).
            ``num_envs=None`` defaults ``sim_backend`` to the CPU sim.

    Examples:
        >>> from maniskill_torchrl.pipeline import make_env
        >>> env = make_env("PickCube-v1", repeat=2, obs_mode="state")
        >>> [type(t).__name__ for t in env.transform], env.batch_size
        (['ActionRepeat', 'EpisodeMetrics'], torch.Size([]))
        >>> env.close()
    """
    repeat = check_repeat(repeat)  # before any env is built
    transforms: list = []
    if num_envs is None:
        maniskill_kwargs.setdefault("sim_backend", "physx_cpu")
        base = ManiSkillEnv(env_id, batch_size=[], **maniskill_kwargs)
    else:
        base = ManiSkillEnv(env_id, num_envs=num_envs, **maniskill_kwargs)
    if flatten_rgbd is not None:
        transforms.append(FlattenRGBD(**flatten_rgbd))
    if ignore_terminations:
        transforms.append(IgnoreTerminations())
    if repeat != 1:
        transforms.append(ActionRepeat(repeat))
    if metrics:
        transforms.append(EpisodeMetrics())
    return TransformedEnv(base, Compose(*transforms))
