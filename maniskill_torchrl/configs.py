"""This library in TorchRL's config system (Hydra): ManiSkill is one more ``env=`` choice of
TorchRL's trainers, its transforms more ``transform=`` choices, and its demonstrations one more
replay buffer.

``import maniskill_torchrl.configs`` (a ``train.py`` of the ``sota-implementations`` shape does
``from maniskill_torchrl.configs import *`` beside TorchRL's own) registers, in TorchRL's
``ConfigStore`` groups:

=================  ===========================  ==========================================
group              name                         node
=================  ===========================  ==========================================
``env``            ``maniskill``                :class:`ManiSkillEnvNodeConfig`
``transform``      ``action_repeat``            :class:`ActionRepeatConfig`
``transform``      ``episode_metrics``          :class:`EpisodeMetricsConfig`
``transform``      ``ignore_terminations``      :class:`IgnoreTerminationsConfig`
``transform``      ``cpu_unbatch``              :class:`CPUUnbatchConfig`
``transform``      ``sparse_reward``            :class:`SparseRewardConfig`
``transform``      ``exclude_keys``             :class:`ExcludeKeysConfig`
``replay_buffer``  ``maniskill``                :class:`ManiSkillExperienceReplayConfig`
``replay_buffer``  ``offline_to_online``        :class:`OfflineToOnlineReplayBufferConfig`
``hook``           ``success_rate_evaluation``  :class:`SuccessRateEvaluationConfig`
``hook``           ``log_episode_metrics``      :class:`LogEpisodeMetricsConfig`
``hook``           ``keep_random_frames``       :class:`KeepRandomFramesConfig`
``network``        ``ppo_mlp``                  :class:`PPOMLPConfig`
``loss``           ``sac_backup_entropy``       :class:`SACBackupEntropyLossConfig`
=================  ===========================  ==========================================

and the ``maniskill:`` prefix of :func:`torchrl.data.datasets.load_dataset`. It needs
``hydra-core`` (the ``hydra`` extra: ``pip install "maniskill-torchrl[hydra]"``).

:class:`ManiSkillEnvConfig` is the class the TorchRL pull request in ``upstream/`` adds to
``torchrl/trainers/algorithms/configs/envs_libs.py`` (``upstream/apply.py`` copies it from here),
with its ``_target_`` there TorchRL's ``ManiSkillEnv`` and here this library's. The ``env/maniskill``
node is one node, the upstream one's name: :class:`ManiSkillEnvNodeConfig`, a subclass of TorchRL's
``ManiSkillEnvConfig`` where TorchRL has one (of the copy here otherwise), so every YAML written for
either composes with it, and it replaces TorchRL's node on purpose: it builds this library's env (a
CPU-sim ``num_envs: 4`` runs the batched CPU engine) with TorchRL's gym node's defaults (one unbatched
env) and the library's render device.

TorchRL's own ``sota-implementations/*_trainer`` scripts get these nodes without an edit: the
``hydra_plugins/maniskill_torchrl`` module shipped with the library (Hydra's plugin discovery)
imports this module at app start where TorchRL's configs are imported (``python
sota-implementations/sac_trainer/train.py env@training_env.create_env_fn.base_env=maniskill
training_env.create_env_fn.base_env.env_name=PushCube-v1 ...``).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field
from typing import Any

if importlib.util.find_spec("hydra") is None:  # TorchRL's configs need it too
    from maniskill_torchrl._internal.extras import missing_extra

    raise missing_extra("hydra", "maniskill_torchrl.configs (TorchRL's config system and trainers)")

from hydra.core.config_store import ConfigStore  # noqa: E402
from omegaconf import MISSING  # noqa: E402
from torchrl.trainers.algorithms.configs.data import ReplayBufferBaseConfig  # noqa: E402
from torchrl.trainers.algorithms.configs.envs_libs import EnvLibsConfig  # noqa: E402
from torchrl.trainers.algorithms.configs.hooks import HookConfig  # noqa: E402
from torchrl.trainers.algorithms.configs.modules import MLPConfig  # noqa: E402
from torchrl.trainers.algorithms.configs.objectives import SACLossConfig  # noqa: E402
from torchrl.trainers.algorithms.configs.transforms import TransformConfig  # noqa: E402

import maniskill_torchrl.data  # noqa: E402, F401  (registers the maniskill: dataset prefix)

__all__ = [
    "ActionRepeatConfig",
    "CPUUnbatchConfig",
    "EpisodeMetricsConfig",
    "ExcludeKeysConfig",
    "IgnoreTerminationsConfig",
    "KeepRandomFramesConfig",
    "LogEpisodeMetricsConfig",
    "ManiSkillEnvConfig",
    "ManiSkillEnvNodeConfig",
    "ManiSkillExperienceReplayConfig",
    "OfflineToOnlineReplayBufferConfig",
    "PPOMLPConfig",
    "SACBackupEntropyLossConfig",
    "SparseRewardConfig",
    "SuccessRateEvaluationConfig",
    "make_maniskill_env",
]


# ----------------------------------------------------------------------------- env
@dataclass
class ManiSkillEnvConfig(EnvLibsConfig):
    """Configuration for ManiSkillEnv environment.

    Hydra configuration for :class:`~torchrl.envs.ManiSkillEnv`. ``obs_mode``,
    ``reward_mode``, ``control_mode``, ``render_mode``, ``sim_backend``,
    ``render_backend`` and ``max_episode_steps`` are passed to ``gym.make``; their
    defaults are ManiSkill's.
    """

    env_name: str = MISSING
    num_envs: int = 1
    obs_mode: str | None = None
    reward_mode: str | None = None
    control_mode: str | None = None
    render_mode: str | None = None
    sim_backend: str = "auto"
    render_backend: str = "gpu"
    max_episode_steps: int | None = None
    from_pixels: bool = False
    pixels_only: bool = False
    pixels_key: str = "pixels"
    info_keys: list[str] | None = None
    frame_skip: int = 1
    device: str | None = None
    batch_size: list[int] | None = None
    allow_done_after_reset: bool = False
    num_workers: int = 1
    _target_: str = "maniskill_torchrl.ManiSkillEnv"

    def __post_init__(self) -> None:
        """Post-initialization hook for ManiSkillEnv configuration."""
        super().__post_init__()


# The upstream node where TorchRL has one (the pull request of upstream/ merged), else the copy above.
from torchrl.trainers.algorithms.configs import envs_libs as _envs_libs  # noqa: E402

_UpstreamManiSkillEnvConfig = getattr(_envs_libs, "ManiSkillEnvConfig", ManiSkillEnvConfig)


@dataclass
class ManiSkillEnvNodeConfig(_UpstreamManiSkillEnvConfig):
    """The ``env/maniskill`` node: :class:`ManiSkillEnvConfig` (TorchRL's, or its copy here) building
    this library's :class:`~maniskill_torchrl.ManiSkillEnv` (:func:`make_maniskill_env`).

    Its defaults are those of TorchRL's gym node (``GymEnvConfig``) and the library's:

    - ``num_envs: 0``: one env, unbatched (batch ``[]``), as ``GymEnvConfig``'s ``num_envs: 0``, so a
      ``batched_env`` of them has batch ``[num_workers]``. ``num_envs: N >= 1``: one env of batch ``[N]``
      (on the CPU sim, the batched CPU engine: one process per sub-env).
    - ``render_backend: null``: the library's default, ``"cpu"`` where SAPIEN finds no CUDA device
      (no "Requested to use render device sapien_cuda" warning), ManiSkill's ``"gpu"`` otherwise; a
      name (``cpu``, ``gpu``, ``cuda:1``, ``none``: no rendering) is passed to ManiSkill.
    - ``in_process`` and ``inference_mode``: :class:`~maniskill_torchrl.ManiSkillEnv`'s, decided by the
      machine and the sim where null.

    The env it builds pickles as its constructor, so a ``_partial_`` node holding it (TorchRL's
    ``batched_env -> transformed_env -> base_env`` layout) works with every collector.
    """

    num_envs: int = 0
    render_backend: str | None = None
    in_process: bool | None = None
    inference_mode: bool | None = None
    _target_: str = "maniskill_torchrl.configs.make_maniskill_env"

    def __post_init__(self) -> None:
        super().__post_init__()


def make_maniskill_env(
    env_name: str,
    *,
    num_envs: int = 0,
    batch_size: Any = None,
    render_backend: str | None = None,
    **kwargs: Any,
) -> Any:
    """:class:`~maniskill_torchrl.ManiSkillEnv` as :class:`ManiSkillEnvNodeConfig` builds it:
    ``num_envs=0`` one unbatched env (``num_envs=1, batch_size=[]``), ``render_backend=None`` the
    library's default render device; every other argument is ``ManiSkillEnv``'s."""
    from maniskill_torchrl import ManiSkillEnv

    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 0:
        raise ValueError(f"num_envs must be 0 (one unbatched env) or a positive int, got {num_envs!r}.")
    if num_envs == 0:
        if batch_size is not None and list(batch_size) != []:
            raise ValueError(
                f"num_envs=0 is one unbatched env (batch_size []), and batch_size={list(batch_size)} asks for "
                "another: set num_envs to the batch size instead."
            )
        num_envs, batch_size = 1, []
    if render_backend is not None:
        kwargs["render_backend"] = render_backend
    if batch_size is not None:
        kwargs["batch_size"] = list(batch_size)
    return ManiSkillEnv(env_name, num_envs=num_envs, **kwargs)


# ----------------------------------------------------------------------------- transforms
@dataclass
class ActionRepeatConfig(TransformConfig):
    """:class:`~maniskill_torchrl.transforms.ActionRepeat`: ManiSkill's ``ActionRepeatWrapper``."""

    repeat: int = MISSING
    _target_: str = "maniskill_torchrl.transforms.ActionRepeat"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class EpisodeMetricsConfig(TransformConfig):
    """:class:`~maniskill_torchrl.transforms.EpisodeMetrics`: each episode's return, length and
    success / fail (ManiSkill's ``CPUGymWrapper`` episode info)."""

    summation: str | None = None
    _target_: str = "maniskill_torchrl.transforms.EpisodeMetrics"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class IgnoreTerminationsConfig(TransformConfig):
    """:class:`~maniskill_torchrl.transforms.IgnoreTerminations`: episodes end at the time limit
    (``as_truncations: true``: at a termination too, as a truncation)."""

    in_keys: list[Any] | None = None
    as_truncations: bool = False
    _target_: str = "maniskill_torchrl.transforms.IgnoreTerminations"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class CPUUnbatchConfig(TransformConfig):
    """:class:`~maniskill_torchrl.transforms.CPUUnbatch`: one CPU-sim env without its env dim."""

    _target_: str = "maniskill_torchrl.transforms.CPUUnbatch"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class SparseRewardConfig(TransformConfig):
    """:class:`~maniskill_torchrl.transforms.SparseReward`: ManiSkill's sparse reward (``success -
    fail``) into ``"reward"``, e.g. on demonstrations recorded with another reward or none."""

    success_key: Any = "success"
    fail_key: Any = "fail"
    reward_key: Any = "reward"
    _target_: str = "maniskill_torchrl.transforms.SparseReward"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class ExcludeKeysConfig(TransformConfig):
    """TorchRL's :class:`~torchrl.envs.ExcludeTransform` with nested keys, each a list
    (``exclude_keys: [env_states, [next, env_states]]``). TorchRL 0.14.1's ``exclude`` node passes
    ``exclude_keys=`` to a transform that takes the keys as positional arguments, and a YAML list
    is no nested key (noted for upstream)."""

    exclude_keys: list[Any] = field(default_factory=list)
    _target_: str = "maniskill_torchrl.configs._make_exclude_transform"

    def __post_init__(self) -> None:
        super().__post_init__()


def _make_exclude_transform(exclude_keys: Any = ()) -> Any:
    from torchrl.envs import ExcludeTransform

    keys = [key if isinstance(key, str) else tuple(key) for key in exclude_keys]
    return ExcludeTransform(*keys)


# ----------------------------------------------------------------------------- networks
@dataclass
class PPOMLPConfig(MLPConfig):
    """TorchRL's :class:`~torchrl.modules.MLP` as ManiSkill's PPO baseline builds its actor and
    critic (``examples/ppo_torchrl.py`` too): the last layer initialised orthogonally with gain
    ``last_layer_std`` and a zero bias, and, for the actor, a learnt state-independent scale
    (``state_independent_scale``: its initial log, e.g. -0.5) after it, through tensordict's
    :class:`~tensordict.nn.AddStateIndependentNormalScale`. The network then returns
    ``(loc, scale)``: a ``tanh_normal`` model takes it with ``extract_normal_params: false``.
    TorchRL 0.14.1's ``tanh_normal`` model has a state-dependent scale only (noted for upstream);
    with it, the PPO YAML's policy diverged (NaN actions at 85,000 frames, issue 53)."""

    last_layer_std: float | None = None
    state_independent_scale: float | None = None
    _target_: str = "maniskill_torchrl.configs._make_ppo_mlp"


def _make_ppo_mlp(
    *, last_layer_std: float | None = None, state_independent_scale: float | None = None, **mlp_kwargs: Any
) -> Any:
    import torch
    from tensordict.nn import AddStateIndependentNormalScale
    from torchrl.modules import MLP

    mlp = MLP(**mlp_kwargs)
    if last_layer_std is not None:
        last = [m for m in mlp.modules() if isinstance(m, torch.nn.Linear)][-1]
        with torch.no_grad():
            torch.nn.init.orthogonal_(last.weight, last_layer_std)
            last.bias.zero_()
    if state_independent_scale is None:
        return mlp
    scale = AddStateIndependentNormalScale(
        mlp_kwargs["out_features"], init_value=state_independent_scale, device=mlp_kwargs.get("device")
    )
    return torch.nn.Sequential(mlp, scale)


# ----------------------------------------------------------------------------- losses
@dataclass
class SACBackupEntropyLossConfig(SACLossConfig):
    """TorchRL's ``loss: sac`` node with ``backup_entropy`` (:class:`maniskill_torchrl.objectives.SACLoss`):
    ``false`` leaves the entropy term out of the critic's target, as ManiSkill's RLPD baseline does.
    Continuous actions only (TorchRL 0.14.1's ``DiscreteSACLoss`` has no such switch either)."""

    backup_entropy: bool = True
    _target_: str = "maniskill_torchrl.configs._make_sac_backup_entropy_loss"


def _make_sac_backup_entropy_loss(
    *, backup_entropy: bool = True, discrete: bool = False, gamma: float | None = None, **kwargs: Any
) -> Any:
    from maniskill_torchrl.objectives import SACLoss

    if discrete:
        raise ValueError(
            "loss: sac_backup_entropy is the continuous SACLoss; for discrete actions use TorchRL's `loss: sac` "
            "node with discrete: true"
        )
    for key in ("actor_network", "qvalue_network", "value_network"):  # config objects, as TorchRL's maker
        if hasattr(kwargs.get(key), "_target_"):
            kwargs[key] = kwargs[key]()
    for key in ("action_space", "num_actions", "target_entropy_weight"):  # DiscreteSACLoss's only
        kwargs.pop(key, None)
    loss = SACLoss(backup_entropy=backup_entropy, **kwargs)
    if gamma is not None:
        loss.make_value_estimator(gamma=gamma)
    return loss


# ----------------------------------------------------------------------------- demonstrations
@dataclass
class ManiSkillExperienceReplayConfig(ReplayBufferBaseConfig):
    """:class:`~maniskill_torchrl.data.ManiSkillExperienceReplay`: a ManiSkill trajectory file
    (``path``: the ``.h5`` file) as a replay buffer laid out as the env's steps."""

    path: str = MISSING
    batch_size: int = MISSING
    env_id: str | None = None
    success_only: bool = False
    num_episodes: int | None = None
    root: str | None = None
    download: Any = True
    split_trajs: bool = False
    sampler: Any = None
    writer: Any = None
    collate_fn: Any = None
    pin_memory: bool = False
    prefetch: int | None = None
    transform: Any = None
    _target_: str = "maniskill_torchrl.data.ManiSkillExperienceReplay"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class OfflineToOnlineReplayBufferConfig(ReplayBufferBaseConfig):
    """:class:`~torchrl.data.OfflineToOnlineReplayBuffer` (TorchRL has no config for it):
    ``offline_dataset`` a dataset id such as ``"maniskill:PickCube-v1/motionplanning"`` (or a
    buffer node), ``dataset_kwargs`` what the dataset is built with besides ``batch_size``. Its offline samples
    leave out TorchRL's ``"index"`` entry, which online samples lack (:class:`_WithoutIndex`)."""

    offline_dataset: Any = MISSING
    online_storage: Any = None
    online_capacity: int | None = None
    offline_fraction: float = 0.5
    batch_size: int | None = None
    transform: Any = None
    dataset_kwargs: dict[str, Any] | None = None
    _target_: str = "maniskill_torchrl.configs._make_offline_to_online_buffer"

    def __post_init__(self) -> None:
        super().__post_init__()


class _WithoutIndex:
    """An offline dataset whose samples leave out TorchRL's ``"index"`` entry.

    TorchRL 0.14.1's ``OfflineToOnlineReplayBuffer`` concatenates an offline sample (a dataset's, which has
    ``"index"``) with an online one (its plain ``ReplayBuffer``'s, which has none): a ``KeyError`` once online data
    is in (noted for upstream). Uniform sampling needs no index.
    """

    def __init__(self, dataset: Any) -> None:
        self.dataset = dataset

    def sample(self, batch_size: int | None = None) -> Any:
        return self.dataset.sample(batch_size).exclude("index")

    def __len__(self) -> int:
        return len(self.dataset)

    def __getattr__(self, name: str) -> Any:
        if name == "dataset":  # not set yet (unpickling)
            raise AttributeError(name)
        return getattr(self.dataset, name)


def _make_offline_to_online_buffer(
    offline_dataset: Any, *, batch_size: int | None = None, dataset_kwargs: dict | None = None, **kwargs: Any
) -> Any:
    # OfflineToOnlineReplayBuffer takes the dataset's arguments as **kwargs, which a config field cannot be.
    from torchrl.data import OfflineToOnlineReplayBuffer
    from torchrl.data.datasets import load_dataset

    if isinstance(offline_dataset, str):
        dataset_kwargs = {"batch_size": batch_size, **dict(dataset_kwargs or {})}
        offline_dataset = load_dataset(offline_dataset, **dataset_kwargs)
    elif dataset_kwargs:
        raise ValueError("dataset_kwargs is for an offline_dataset given as a dataset id (a string).")
    return OfflineToOnlineReplayBuffer(_WithoutIndex(offline_dataset), batch_size=batch_size, **kwargs)


# ----------------------------------------------------------------------------- trainer hooks
@dataclass
class SuccessRateEvaluationConfig(HookConfig):
    """:class:`~maniskill_torchrl.trainer_hooks.SuccessRateEvaluation`: ``episodes`` seeded episodes
    every ``interval`` frames on ``create_env_fn`` (an env node; ``IgnoreTerminations`` then
    ``EpisodeMetrics`` last), success rates logged as ``eval/success_once``..."""

    create_env_fn: Any = MISSING
    interval: int = 20_000
    episodes: int = 50
    seed: int = 10_000
    max_steps: int | None = None
    policy: Any = None
    at_start: bool = False
    prefix: str = "eval"
    _target_: str = "maniskill_torchrl.trainer_hooks.SuccessRateEvaluation"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class LogEpisodeMetricsConfig(HookConfig):
    """:class:`~maniskill_torchrl.trainer_hooks.LogEpisodeMetrics`: the training episodes'
    ``EpisodeMetrics`` (``train/success_once``...) as they end."""

    interval: int = 0
    prefix: str = "train"
    _target_: str = "maniskill_torchrl.trainer_hooks.LogEpisodeMetrics"

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class KeepRandomFramesConfig(HookConfig):
    """:class:`~maniskill_torchrl.trainer_hooks.KeepRandomFrames`: the ``init_random_frames`` batches
    into an off-policy trainer's replay buffer."""

    _target_: str = "maniskill_torchrl.trainer_hooks.KeepRandomFrames"

    def __post_init__(self) -> None:
        super().__post_init__()


def _register_configs() -> None:
    cs = ConfigStore.instance()
    # One node, the upstream one's name: the library's subclass replaces TorchRL's (if any) on purpose.
    cs.store(group="env", name="maniskill", node=ManiSkillEnvNodeConfig)
    cs.store(group="transform", name="action_repeat", node=ActionRepeatConfig)
    cs.store(group="transform", name="episode_metrics", node=EpisodeMetricsConfig)
    cs.store(group="transform", name="ignore_terminations", node=IgnoreTerminationsConfig)
    cs.store(group="transform", name="cpu_unbatch", node=CPUUnbatchConfig)
    cs.store(group="transform", name="sparse_reward", node=SparseRewardConfig)
    cs.store(group="transform", name="exclude_keys", node=ExcludeKeysConfig)
    cs.store(group="replay_buffer", name="maniskill", node=ManiSkillExperienceReplayConfig)
    cs.store(group="replay_buffer", name="offline_to_online", node=OfflineToOnlineReplayBufferConfig)
    cs.store(group="hook", name="success_rate_evaluation", node=SuccessRateEvaluationConfig)
    cs.store(group="hook", name="log_episode_metrics", node=LogEpisodeMetricsConfig)
    cs.store(group="hook", name="keep_random_frames", node=KeepRandomFramesConfig)
    cs.store(group="network", name="ppo_mlp", node=PPOMLPConfig)
    cs.store(group="loss", name="sac_backup_entropy", node=SACBackupEntropyLossConfig)


_register_configs()
