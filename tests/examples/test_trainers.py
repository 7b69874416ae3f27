"""TorchRL's own trainers on ManiSkill (``examples/trainers``): each YAML composes, trains a few
hundred frames through ``train.py`` as a user starts it, and builds the env it names, bit for bit;
the library's trainer hooks log what they should.

``train.py`` runs in this process as ``python train.py`` runs it (``runpy``, with ``sys.argv`` as on
the command line): a subprocess would import torch, TorchRL and ManiSkill again, most of its cost.
Each run is cut to a few hundred frames, small networks and 2-episode evaluations by overrides; the
CSV logger writes under the run's folder (``hydra.run.dir``), and the test reads it back.
"""

from __future__ import annotations

import csv
import math
import re
import runpy
import sys
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs import Compose, ExcludeTransform, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger
from torchrl.trainers import Trainer

import evaluate_gym
import maniskill_torchrl.configs as configs
import ppo_checkpoint
from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.evaluation import evaluate_policy
from maniskill_torchrl.pipeline import make_env
from maniskill_torchrl.testing import assert_tensordict_equal
from maniskill_torchrl.trainer_hooks import KeepRandomFrames, LogEpisodeMetrics, SuccessRateEvaluation
from maniskill_torchrl.transforms import EpisodeMetrics, IgnoreTerminations
from support.helpers import EXAMPLES, make_gym_env, record_episodes, seeded_rollout, start

ROOT = Path(__file__).resolve().parents[2]
TRAINERS = ROOT / "examples" / "trainers"
CONFIGS = TRAINERS / "config"

# What each YAML must build: its trainer (TorchRL's factory of SACTrainer, PPOTrainer,
# OfflineToOnlineTrainer), and the env kwargs of ManiSkillEnv(...) by hand.
EXPECTED = {
    "sac_pushcube": (
        "_make_sac_trainer",
        dict(env_name="PushCube-v1", num_envs=4, obs_mode="state", control_mode="pd_ee_delta_pos"),
    ),
    "ppo_pullcube": (
        "_make_ppo_trainer",
        dict(env_name="PullCube-v1", num_envs=2, obs_mode="state", control_mode="pd_ee_delta_pos"),
    ),
    "rlpd_pickcube": (
        "_make_offline_to_online_trainer",
        dict(
            env_name="PickCube-v1",
            num_envs=8,
            obs_mode="state",
            control_mode="pd_joint_delta_pos",
            reward_mode="sparse",
        ),
    ),
}
# A few hundred frames, small networks, 2-episode evaluations of 5 steps, every metric logged.
SMALL = [
    "trainer.progress_bar=false",
    "trainer.log_interval=0",
    "hooks.evaluation.episodes=2",
    "eval_env.base_env.max_episode_steps=5",
    "training_env.base_env.max_episode_steps=20",
    "networks.policy_network.num_cells=[32,32]",
]
OVERRIDES = {
    "sac_pushcube": [
        *SMALL,
        "networks.qvalue_network.num_cells=[32,32]",
        "networks.qvalue_network.norm_class.normalized_shape=32",
        "replay_buffer.batch_size=32",
        "collector.total_frames=256",
        "collector.init_random_frames=96",  # 3 batches of random actions
        "hooks.evaluation.interval=128",
    ],
    "ppo_pullcube": [
        *SMALL,
        "networks.value_network.num_cells=[32,32]",
        "collector.total_frames=400",
        "trainer.num_epochs=2",
        "hooks.evaluation.interval=200",
    ],
    "rlpd_pickcube": [
        *SMALL,
        "networks.qvalue_network.num_cells=[32,32]",
        "networks.qvalue_network.norm_class.normalized_shape=32",
        "training_env.base_env.num_envs=2",
        "replay_buffer.batch_size=32",
        "trainer.batch_size=32",
        "collector.total_frames=256",
        "collector.init_random_frames=64",
        "hooks.evaluation.interval=128",
    ],
}


def _compose(name: str, overrides: list[str] = (), hydra: bool = False):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides), return_hydra_config=hydra)


def _scalars(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar the CSV logger wrote under ``folder``: {name: [(frames, value), ...]}."""
    out = {}
    for path in sorted(folder.rglob("*.csv")):
        name = path.relative_to(folder).with_suffix("").as_posix()
        out[name] = [(int(step), float(value)) for step, value in csv.reader(path.open())]
    return out


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A ManiSkill trajectory file of PickCube-v1 in the RLPD config's modes (RecordEpisode, three
    seeded episodes of 8 random steps), recorded with the dense reward: the config must train on
    the sparse one (nothing can be downloaded)."""
    env = make_gym_env("PickCube-v1", obs_mode="state", control_mode="pd_joint_delta_pos", max_episode_steps=8)
    return record_episodes(env, tmp_path_factory.mktemp("demo"), seeds=range(3), lengths=8)


# ------------------------------------------------------------------------------ the YAMLs
def test_hook_and_transform_configs_are_registered():
    repo = ConfigStore.instance().repo
    for group, name, node in [
        ("hook", "success_rate_evaluation", configs.SuccessRateEvaluationConfig),
        ("hook", "log_episode_metrics", configs.LogEpisodeMetricsConfig),
        ("hook", "keep_random_frames", configs.KeepRandomFramesConfig),
        ("transform", "sparse_reward", configs.SparseRewardConfig),
        ("transform", "exclude_keys", configs.ExcludeKeysConfig),
    ]:
        assert OmegaConf.get_type(repo[group][f"{name}.yaml"].node) is node


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_config_composes(name):
    """The YAML composes in TorchRL's ConfigStore: its trainer, ManiSkill as the env, the library's
    transforms through TorchRL's nodes, a logger that needs no account, the run in its own folder."""
    cfg = _compose(name, ["demos=/any/file.h5"] if name == "rlpd_pickcube" else [], hydra=True)
    target, env_kwargs = EXPECTED[name]
    assert cfg.trainer._target_ == f"torchrl.trainers.algorithms.configs.trainers.{target}"
    for which in ("training_env", "eval_env"):
        env = cfg[which]
        assert env._target_ == "torchrl.envs.TransformedEnv"
        # The env/maniskill node (ManiSkillEnvNodeConfig) builds the library's ManiSkillEnv through its factory.
        assert env.base_env._target_ == "maniskill_torchrl.configs.make_maniskill_env"
        assert [t._target_ for t in env.transform.transforms] == [
            "maniskill_torchrl.transforms.IgnoreTerminations",
            "maniskill_torchrl.transforms.EpisodeMetrics",
        ]
        # PPO's training episodes end at success, as truncations (ManiSkill's PPO baseline); the
        # evaluations and the off-policy trainers run every episode to the time limit.
        as_truncations = which == "training_env" and name == "ppo_pullcube"
        assert env.transform.transforms[0].as_truncations is as_truncations
        for key in ("env_name", "obs_mode", "control_mode", "reward_mode"):
            assert env.base_env[key] == env_kwargs.get(key), key
    assert cfg.training_env.base_env.num_envs == env_kwargs["num_envs"]
    assert cfg.logger._target_ == "torchrl.record.loggers.csv.CSVLogger"
    assert cfg.hydra.job.chdir is True
    hooks = {h._target_.rsplit(".", 1)[1] for h in cfg.trainer.hooks}
    assert {"SuccessRateEvaluation", "LogEpisodeMetrics"} <= hooks
    assert ("KeepRandomFrames" in hooks) == (name != "ppo_pullcube")  # the off-policy ones


def test_rlpd_needs_its_demonstrations():
    cfg = _compose("rlpd_pickcube")
    with pytest.raises(Exception, match="demos"):
        OmegaConf.to_container(cfg.replay_buffer, resolve=True)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_config_env_is_maniskill_env(name):
    """The training env a YAML builds is ``ManiSkillEnv(...)`` + IgnoreTerminations + EpisodeMetrics
    (PPO's: ``IgnoreTerminations(as_truncations=True)``), bit for bit on a seeded rollout (episodes of
    3 steps: the metrics and the time limit show)."""
    _, env_kwargs = EXPECTED[name]
    env_kwargs = dict(env_kwargs)
    overrides = ["training_env.base_env.max_episode_steps=3"]
    if name == "rlpd_pickcube":  # 2 of its 8 processes: the same env otherwise
        overrides.append("training_env.base_env.num_envs=2")
        env_kwargs["num_envs"] = 2
    cfg = _compose(name, overrides)
    env = instantiate(cfg.training_env)()
    by_hand = TransformedEnv(
        ManiSkillEnv(env_kwargs.pop("env_name"), **env_kwargs, sim_backend="physx_cpu", max_episode_steps=3),
        Compose(IgnoreTerminations(as_truncations=name == "ppo_pullcube"), EpisodeMetrics()),
    )
    got, want = seeded_rollout(env, 7, seed=3), seeded_rollout(by_hand, 7, seed=3)
    assert got["next", "episode", "episode_len"].max() == 3  # episodes ended at the time limit
    assert_tensordict_equal(got, want)


def test_ppo_models_are_the_scripts():
    """The PPO YAML's actor and critic (the library's ``ppo_mlp`` network) are
    ``examples/ppo_torchrl.py``'s, ManiSkill's PPO baseline: initialised as the script does (a
    learnt state-independent log std of -0.5, last layers orthogonal with gain 0.01 / 1.0 and zero
    bias), and with the script's parameters loaded they compute its actions, log-probabilities and
    values bit for bit."""
    from tensordict.nn import AddStateIndependentNormalScale
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    cfg = _compose("ppo_pullcube")
    policy, value = instantiate(cfg.models.policy_model), instantiate(cfg.models.value_model)
    for module, gain in ((policy, 0.01), (value, 1.0)):
        last = [m for m in module.modules() if isinstance(m, torch.nn.Linear)][-1]
        eye = torch.eye(last.weight.shape[0])
        torch.testing.assert_close(last.weight @ last.weight.T, gain**2 * eye, rtol=0, atol=1e-5)
        assert not last.bias.any()
    (scale,) = [m for m in policy.modules() if isinstance(m, AddStateIndependentNormalScale)]
    assert scale.state_independent_scale.eq(-0.5).all()

    make_models = runpy.run_path(str(ROOT / "examples" / "ppo_torchrl.py"))["make_models"]
    env = ManiSkillEnv("PullCube-v1", obs_mode="state", control_mode="pd_ee_delta_pos")
    try:
        theirs = make_models(env, 256, torch.device("cpu"))
        td = env.reset(seed=0)
    finally:
        env.close()
    with torch.no_grad():
        for mine, script in ((policy, theirs[0]), (value, theirs[1])):
            for p, q in zip(mine.parameters(), script.parameters(), strict=True):
                p.copy_(q)
    outputs = []
    for actor, critic in ((policy, value), theirs):
        torch.manual_seed(0)  # the same sampled action
        out = critic(actor(td.clone()))
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            out["mode"] = actor(td.clone())["action"]
        outputs.append(out.select("action", "action_log_prob", "state_value", "mode"))
    assert outputs[0]["action"].ne(outputs[0]["mode"]).any()  # a sample, not the mode
    # TanhNormal's bounds: scalars here (the model's default, [-1, 1]), the action spec's tensors
    # there; its log-probability then differs in the last bits (float32 rounding), nothing else does.
    mine, script = (out.pop("action_log_prob") for out in outputs)
    torch.testing.assert_close(mine, script, rtol=1e-6, atol=0)
    assert_tensordict_equal(*outputs)


# ----------------------------------------------------------------------------- training
def _run_train_py(name, overrides, run_dir, monkeypatch):
    """``python examples/trainers/train.py --config-name <name> <overrides>`` in this process; returns
    the trainer it built (trained) and the scalars its CSV logger wrote."""
    built = []
    real = instantiate

    def keep(config, *args, **kwargs):
        out = real(config, *args, **kwargs)
        built.append(out)
        return out

    import hydra.utils

    monkeypatch.setattr(hydra.utils, "instantiate", keep)
    monkeypatch.setattr(sys, "argv", ["train.py", "--config-name", name, *overrides, f"hydra.run.dir={run_dir}"])
    monkeypatch.chdir(run_dir.parent)
    threads = torch.get_num_threads()
    GlobalHydra.instance().clear()
    try:
        runpy.run_path(str(TRAINERS / "train.py"), run_name="__main__")  # python train.py ...
    finally:
        torch.set_num_threads(threads)
        GlobalHydra.instance().clear()
    trainer = built[-1]  # the outermost instantiate returns last (TorchRL's factories call it too)
    assert isinstance(trainer, Trainer), built
    return trainer, _scalars(run_dir / "csv_logs" / name / "scalars")


def _check_logs(scalars, total, interval, episode_len, envs):
    """The hooks' logs: evaluations every ``interval`` frames and at the end, 2 episodes each; the
    training episodes' metrics, each of ``episode_len`` steps (they end at the time limit)."""
    evals = scalars["eval/success_once"]
    assert [f for f, _ in evals] == list(range(interval, total + 1, interval))
    assert all(v == 2 for _, v in scalars["eval/episodes"])
    assert all(0 <= v <= 1 for _, v in evals + scalars["eval/success_at_end"])
    assert len(scalars["eval/return"]) == len(evals)
    logged = scalars["train/episode_len"]
    assert logged and all(v == episode_len for _, v in logged)
    # every training episode that ended is counted once
    assert sum(v for _, v in scalars["train/episodes"]) == envs * (total // envs // episode_len)
    for key in ("success_once", "success_at_end", "return"):
        assert len(scalars[f"train/{key}"]) == len(logged)


def test_sac_pushcube_trains(tmp_path, monkeypatch):
    trainer, scalars = _run_train_py("sac_pushcube", OVERRIDES["sac_pushcube"], tmp_path / "run", monkeypatch)
    assert trainer.collected_frames == 256
    # every collected frame is in the buffer, the 96 random ones too (KeepRandomFrames: TorchRL's
    # SACTrainer alone drops the 64 of the two batches before the one that reaches the threshold)
    assert len(trainer.replay_buffer) == 256
    assert scalars["optim_steps"][-1] == (256, (256 - 96) // 32 * 16 + 16)
    _check_logs(scalars, total=256, interval=128, episode_len=20, envs=4)
    assert "r_training" in scalars and "loss_qvalue" in scalars  # TorchRL's own logs still there
    saved = torch.load(tmp_path / "run" / "policy.pt", map_location="cpu", weights_only=True)  # train.py's checkpoint
    assert saved["format"] == "maniskill_torchrl.trainer.v1" and saved["env_id"] == "PushCube-v1"
    assert saved["frames"] == 256 and saved["policy"]
    assert (saved["obs_dim"], saved["act_dim"], saved["repeat"]) == (35, 4, 1)
    assert "_make_tanh_normal_model" in saved["actor"]  # the actor's config, rebuilt by evaluate_gym.py


@pytest.fixture(scope="module")
def ppo_run(tmp_path_factory):
    """The PPO YAML trained a few hundred frames by ``train.py``: (trainer, scalars, run folder)."""
    run_dir = tmp_path_factory.mktemp("ppo") / "run"
    run_dir.mkdir()
    with pytest.MonkeyPatch.context() as monkeypatch:
        trainer, scalars = _run_train_py("ppo_pullcube", OVERRIDES["ppo_pullcube"], run_dir, monkeypatch)
    return trainer, scalars, run_dir


def test_ppo_pullcube_trains(ppo_run):
    trainer, scalars, _ = ppo_run
    assert trainer.collected_frames == 400
    _check_logs(scalars, total=400, interval=200, episode_len=20, envs=2)
    assert "loss_objective" in scalars and "loss_critic" in scalars


def test_trainer_policy_evaluates(ppo_run, tmp_path, capsys):
    """A trainer run's ``policy.pt`` evaluated end to end: ``evaluate_gym.py --checkpoint <run>/policy.pt`` as a
    user runs it (a subprocess from another folder; gym's AsyncVectorEnv of CPUGymWrapper) and its TorchRL
    backend (in this process), on the same seeded episodes. The actor rebuilt from the config saved in the
    file (the YAML's ``ppo_mlp`` with the run's overrides: 2x32 cells) acts as the trained one, bit for bit."""
    trainer, _, run_dir = ppo_run
    args = ["--checkpoint", str(run_dir / "policy.pt"), "--num-envs", "2", "--episodes", "2"]
    args += ["--max-episode-steps", "6", "--seed", "4"]
    gym_run = start([sys.executable, str(EXAMPLES / "evaluate_gym.py"), *args], tmp_path)
    try:
        ckpt = ppo_checkpoint.load_checkpoint(run_dir)  # the run folder: its policy.pt
        assert ckpt["format"] == "maniskill_torchrl.trainer.v1" and ckpt["frames"] == 400
        assert (ckpt["env_id"], ckpt["control_mode"], ckpt["obs_dim"], ckpt["act_dim"], ckpt["repeat"]) == (
            "PullCube-v1",
            "pd_ee_delta_pos",
            35,
            4,
            1,
        )
        box = gym.spaces.Box
        specs = ppo_checkpoint.specs_from_spaces(box(-float("inf"), float("inf"), (35,)), box(-1.0, 1.0, (4,)))
        policy = ppo_checkpoint.policy_from_checkpoint(ckpt, specs)
        assert [m.out_features for m in policy.modules() if isinstance(m, torch.nn.Linear)] == [32, 32, 4]
        obs = TensorDict({"observation": torch.randn(5, 35)}, [5])
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            mine, trained = policy(obs.clone())["action"], trainer.loss_module.actor_network(obs.clone())["action"]
        assert torch.equal(mine, trained)
        with pytest.raises(ppo_checkpoint.CheckpointError, match="observation size mismatch"):
            ppo_checkpoint.policy_from_checkpoint(
                ckpt, ppo_checkpoint.specs_from_spaces(box(-1, 1, (36,)), box(-1, 1, (4,)))
            )

        capsys.readouterr()
        threads = torch.get_num_threads()
        try:
            code = evaluate_gym.main([*args, "--backend", "torchrl"])
        finally:
            torch.set_num_threads(threads)  # main sets one thread
        torchrl_out = capsys.readouterr().out
    finally:
        gym_proc = gym_run.result()
        gym_out = gym_proc.stdout
    assert code == 0, torchrl_out
    # ManiSkill's notes from gymnasium's worker processes (and its dummy env here) are quieted by the script
    for note in ("CUDA device was not found", "No initial pose set"):
        assert note not in gym_out + gym_proc.stderr, gym_proc.stderr
    assert "PullCube-v1, control mode pd_ee_delta_pos, repeat 1, 400 frames" in gym_out, gym_out
    assert len([line for line in gym_out.splitlines() if line.startswith("episode ")]) == 2, gym_out

    def averages(text: str) -> dict[str, str]:
        return dict(re.findall(r"^avg (\w+): (\S+)$", text, re.M))

    assert "episodes: 2" in gym_out and "episodes: 2" in torchrl_out, torchrl_out
    for key in ("success_once", "success_at_end", "return"):
        assert averages(gym_out)[key] == averages(torchrl_out)[key], (key, gym_out, torchrl_out)


def test_rlpd_pickcube_trains(tmp_path, monkeypatch, demo):
    overrides = [
        *OVERRIDES["rlpd_pickcube"],
        f"demos={demo}",
        f"+replay_buffer.dataset_kwargs.root={tmp_path / 'cache'}",
    ]
    trainer, scalars = _run_train_py("rlpd_pickcube", overrides, tmp_path / "run", monkeypatch)
    assert trainer.collected_frames == 256
    buffer = trainer.replay_buffer
    assert len(buffer.offline_buffer) == 24 and len(buffer.online_buffer) == 256  # 3 demos x 8 steps
    assert buffer.offline_fraction == 0.5  # RLPD's symmetric sampling, not annealed
    assert trainer.loss_module.backup_entropy is False  # ManiSkill's RLPD: no entropy term in the critic's target
    batch = buffer.sample(64)
    assert "env_states" not in batch.keys() and "index" not in batch.keys()
    # ManiSkill's sparse reward on both halves (the demos were recorded with the dense one)
    success = batch["next", "success"].float().unsqueeze(-1)
    assert torch.equal(batch["next", "reward"], success)
    assert not batch["next", "terminated"].any()  # episodes to the time limit on both halves
    _check_logs(scalars, total=256, interval=128, episode_len=20, envs=2)
    assert "loss_qvalue" in scalars


# --------------------------------------------------------------------------------- hooks
class _Logger(Logger):
    """Records ``log_scalar`` calls."""

    def __init__(self) -> None:
        self.scalars: list[tuple[str, float, int]] = []
        super().__init__(exp_name="test", log_dir="unused")

    def _create_experiment(self):
        return None

    def log_scalar(self, name, value, step=None):
        self.scalars.append((name, float(value), step))

    def log_video(self, *a, **k):
        pass

    def log_hparams(self, *a, **k):
        pass

    def log_histogram(self, *a, **k):
        pass

    def __repr__(self):
        return "_Logger()"


class _Trainer:
    """What the hooks read of a TorchRL trainer."""

    def __init__(self, total_frames=1000):
        self.collected_frames, self.total_frames, self.frame_skip = 0, total_frames, 1
        self.logger = _Logger()
        self.ops: list[tuple[str, object]] = []

    def register_op(self, dest, op, **kwargs):
        self.ops.append((dest, op))

    def register_module(self, name, module):
        pass


def _batch(done, success, ret, length):
    """A collected batch [envs, steps] with EpisodeMetrics' entries (only read where done)."""
    done = torch.tensor(done)
    shape = done.shape
    episode = {
        "success_once": torch.tensor(success).expand(shape),
        "success_at_end": torch.tensor(success).expand(shape),
        "return": torch.tensor(ret, dtype=torch.float32).expand(shape),
        "episode_len": torch.tensor(length).expand(shape),
    }
    return TensorDict({"next": {"done": done.unsqueeze(-1), "episode": episode}}, shape)


def test_log_episode_metrics_logs_finished_episodes():
    trainer = _Trainer()
    hook = LogEpisodeMetrics(interval=100)
    hook.register(trainer)
    assert trainer.ops == [("pre_steps_log", hook)]
    log = trainer.logger.scalars
    # 2 envs x 3 steps: env 0 ends an episode (success, return 2, 3 steps); the rest is not read
    trainer.collected_frames = 6
    hook(_batch([[False, False, True], [False, False, False]], [[True], [False]], [[2.0], [9.0]], [[3], [7]]))
    assert sorted(log) == [
        ("train/episode_len", 3.0, 6),
        ("train/episodes", 1.0, 6),
        ("train/return", 2.0, 6),
        ("train/success_at_end", 1.0, 6),
        ("train/success_once", 1.0, 6),
    ]
    log.clear()
    # within the interval: kept; then both episodes logged together, as their mean
    trainer.collected_frames = 50
    hook(_batch([[False, False, False], [False, True, False]], [[True], [False]], [[2.0], [4.0]], [[3], [5]]))
    assert log == []
    trainer.collected_frames = 110
    hook(_batch([[True, False, False], [False, False, False]], [[True], [False]], [[6.0], [0.0]], [[9], [1]]))
    assert dict((n, v) for n, v, _ in log) == {
        "train/return": 5.0,
        "train/episode_len": 7.0,
        "train/success_once": 0.5,
        "train/success_at_end": 0.5,
        "train/episodes": 2.0,
    }
    assert {s for _, _, s in log} == {110}
    with pytest.raises(KeyError, match="EpisodeMetrics"):
        hook(TensorDict({"next": {"done": torch.zeros(2, 1, dtype=torch.bool)}}, [2]))


def test_success_rate_evaluation_runs_seeded_episodes():
    """Every ``interval`` frames and at the end, the seeded evaluation of ``evaluate_policy`` (the same
    numbers on each call: seeded, deterministic), logged at the trainer's frame count."""
    env = make_env("PushCube-v1", num_envs=2, ignore_terminations=True, obs_mode="state", max_episode_steps=4)
    torch.manual_seed(0)
    policy = instantiate(
        OmegaConf.create(
            {
                "_target_": "torchrl.trainers.algorithms.configs.modules._make_tanh_normal_model",
                "network": {"_target_": "torchrl.modules.MLP", "in_features": 35, "out_features": 16, "num_cells": [8]},
                "in_keys": ["observation"],
                "param_keys": ["loc", "scale"],
                "out_keys": ["action"],
            }
        )
    )
    trainer = _Trainer(total_frames=250)
    hook = SuccessRateEvaluation(env, interval=100, episodes=3, seed=7, policy=policy)
    hook.register(trainer)
    assert ("post_steps_log", hook) in trainer.ops and ("shutdown", hook.close) in trainer.ops
    for frames in (50, 100, 150, 230, 250):
        trainer.collected_frames = frames
        hook()
    assert [r["frames"] for r in hook.results] == [100, 230, 250]  # interval, interval, the end
    want = evaluate_policy(env, policy, 3, 7, 4)
    for record in hook.results:
        assert {k: record[k] for k in want} == want
    names = {n for n, _, _ in trainer.logger.scalars}
    assert {"eval/success_once", "eval/success_at_end", "eval/return", "eval/episodes"} <= names
    assert [s for n, _, s in trainer.logger.scalars if n == "eval/return"] == [100, 230, 250]
    hook.close()
    assert not env.is_closed  # an env handed over is the caller's
    at_start, first = _Trainer(), SuccessRateEvaluation(env, at_start=True)
    first.register(at_start)
    assert at_start.ops[-1] == ("setup", first.evaluate)  # once more before training
    env.close()


def test_success_rate_evaluation_needs_episode_metrics():
    env = make_env("PushCube-v1", num_envs=2, obs_mode="state", metrics=False, max_episode_steps=4)
    hook = SuccessRateEvaluation(lambda: env, interval=0, episodes=2)
    hook.register(_Trainer())
    try:
        with pytest.raises(ValueError, match="EpisodeMetrics"):
            hook.evaluate()
    finally:
        env.close()


def test_success_rate_evaluation_max_steps_counts_agent_steps():
    """The episode length is the base env's time limit divided by an ActionRepeat's repeat."""
    env = make_env("PushCube-v1", num_envs=2, ignore_terminations=True, repeat=3, obs_mode="state")
    try:
        assert SuccessRateEvaluation(env)._max_steps(env) == math.ceil(50 / 3)
        assert SuccessRateEvaluation(env, max_steps=4)._max_steps(env) == 4
    finally:
        env.close()


def test_keep_random_frames_without_a_buffer_op_says_so():
    with pytest.raises(ValueError, match="extend"):
        KeepRandomFrames().register(type("T", (), {"_pre_epoch_ops": []})())


def test_exclude_keys_config_takes_nested_keys():
    transform = instantiate(OmegaConf.structured(configs.ExcludeKeysConfig(exclude_keys=["a", ["next", "a"]])))
    assert isinstance(transform, ExcludeTransform)
    data = TensorDict({"a": 0, "b": 1, "next": {"a": 0, "b": 1}}, [])
    assert set(transform(data).keys(True, True)) == {"b", ("next", "b")}
