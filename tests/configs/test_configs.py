"""The library in TorchRL's config system (``maniskill_torchrl/configs.py``): every node is registered in
TorchRL's ``ConfigStore`` groups, and what a node builds is what the same arguments build by hand, on real tasks
(seeded rollouts compared bit for bit, demonstrations read from a file ManiSkill's ``RecordEpisode`` wrote)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
from pathlib import Path

import pytest
from hydra.core.config_store import ConfigStore
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torchrl.envs import TransformedEnv
from torchrl.trainers.algorithms.configs import ComposeConfig, TransformedEnvConfig

import maniskill_torchrl.configs as configs
from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.data import ManiSkillExperienceReplay
from maniskill_torchrl.testing import assert_tensordict_equal
from maniskill_torchrl.transforms import ActionRepeat, EpisodeMetrics, IgnoreTerminations
from support.helpers import make_gym_env, record_episodes, seeded_rollout

ROOT = Path(__file__).resolve().parents[2]
TASK = "PickCube-v1"
REGISTERED = {
    ("env", "maniskill"): configs.ManiSkillEnvNodeConfig,
    ("transform", "action_repeat"): configs.ActionRepeatConfig,
    ("transform", "episode_metrics"): configs.EpisodeMetricsConfig,
    ("transform", "ignore_terminations"): configs.IgnoreTerminationsConfig,
    ("transform", "cpu_unbatch"): configs.CPUUnbatchConfig,
    ("replay_buffer", "maniskill"): configs.ManiSkillExperienceReplayConfig,
    ("replay_buffer", "offline_to_online"): configs.OfflineToOnlineReplayBufferConfig,
    ("loss", "sac_backup_entropy"): configs.SACBackupEntropyLossConfig,
}


def _build(node):
    return instantiate(OmegaConf.structured(node))


def _rollout(env):
    return seeded_rollout(env, 6, seed=3)


@pytest.mark.parametrize(("group", "name"), sorted(REGISTERED))
def test_registered_in_torchrls_groups(group, name):
    node = ConfigStore.instance().repo[group][f"{name}.yaml"].node
    assert OmegaConf.get_type(node) is REGISTERED[group, name]
    assert node._target_ == REGISTERED[group, name]._target_


def test_every_keyword_argument_of_the_adapter_is_a_config_field():
    """TorchRL's contributor rule: each constructor argument is a field of the env's config."""
    import dataclasses
    import inspect

    from maniskill_torchrl.envs import maniskill as adapter

    wanted = {"num_workers"}  # the metaclass's, in front of ManiSkillEnv's own
    for cls in (adapter.ManiSkillWrapper, adapter.ManiSkillEnv):
        for name, param in inspect.signature(cls.__init__).parameters.items():
            if param.kind in (param.KEYWORD_ONLY, param.POSITIONAL_OR_KEYWORD) and name not in ("self", "env"):
                wanted.add(name)
    wanted.add("frame_skip")  # read from **kwargs by TorchRL's _EnvWrapper
    fields = {field.name for field in dataclasses.fields(configs.ManiSkillEnvConfig)}
    assert wanted <= fields, sorted(wanted - fields)


def test_env_config_builds_the_library_env():
    node = configs.ManiSkillEnvConfig(env_name=TASK, obs_mode="state", max_episode_steps=4)
    env = _build(node)
    assert type(env) is ManiSkillEnv
    want = _rollout(ManiSkillEnv(TASK, obs_mode="state", max_episode_steps=4))
    assert_tensordict_equal(_rollout(env), want)


def test_transform_configs_build_the_transforms():
    """A TransformedEnv node of TorchRL's, the library's transforms in TorchRL's Compose node: the same
    rollout as the stack built by hand (episodes end at 3 steps, repeat 2: metrics and repeats both show)."""
    base = configs.ManiSkillEnvConfig(env_name=TASK, obs_mode="state", max_episode_steps=3)
    transforms = ComposeConfig(
        transforms=[
            configs.IgnoreTerminationsConfig(),
            configs.ActionRepeatConfig(repeat=2),
            configs.EpisodeMetricsConfig(),
        ]
    )
    env = _build(TransformedEnvConfig(base_env=base, transform=transforms))
    assert [type(t) for t in env.transform] == [IgnoreTerminations, ActionRepeat, EpisodeMetrics]
    by_hand = TransformedEnv(
        ManiSkillEnv(TASK, obs_mode="state", max_episode_steps=3),
        IgnoreTerminations(),
    )
    by_hand.append_transform(ActionRepeat(2))
    by_hand.append_transform(EpisodeMetrics())
    got, want = _rollout(env), _rollout(by_hand)
    assert got["next", "episode", "episode_len"].max() > 0  # an episode ended, its metrics are there
    assert_tensordict_equal(got, want)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """ManiSkill's RecordEpisode file of two seeded episodes (nothing can be downloaded)."""
    env = make_gym_env(TASK, obs_mode="state", max_episode_steps=4)
    return record_episodes(env, tmp_path_factory.mktemp("demo"), seeds=range(2), lengths=4)


def test_demonstration_configs(demo, tmp_path):
    node = configs.ManiSkillExperienceReplayConfig(path=str(demo), batch_size=4, root=str(tmp_path))
    buffer = _build(node)
    want = ManiSkillExperienceReplay(demo, 4, root=tmp_path / "direct")
    assert_tensordict_equal(buffer.storage[:], want.storage[:])
    mixed = _build(
        configs.OfflineToOnlineReplayBufferConfig(
            offline_dataset=f"maniskill:{demo}",
            online_capacity=16,
            batch_size=4,
            offline_fraction=0.5,
            dataset_kwargs={"root": str(tmp_path / "prefix")},
        )
    )
    mixed.extend(want.storage[:3].clone())
    batch = mixed.sample()
    assert batch.shape == (4,) and set(batch.keys(True, True)) == set(want.storage[:1].keys(True, True))


def test_upstream_config_is_this_class():
    """upstream/apply.py adds this very class to TorchRL, its _target_ TorchRL's ManiSkillEnv."""
    spec = importlib.util.spec_from_file_location("apply", ROOT / "upstream" / "apply.py")
    apply = importlib.util.module_from_spec(spec)
    sys.modules["apply"] = apply
    try:
        spec.loader.exec_module(apply)
        text = apply._config_class()
    finally:
        del sys.modules["apply"]
    (cls,) = ast.parse(text).body
    assert cls.name == "ManiSkillEnvConfig"
    here = ast.parse(Path(configs.__file__).read_text())
    (ours,) = [n for n in here.body if isinstance(n, ast.ClassDef) and n.name == "ManiSkillEnvConfig"]
    targets = {
        ast.unparse(a.value)
        for c in (cls, ours)
        for a in c.body
        if isinstance(a, ast.AnnAssign) and a.target.id == "_target_"
    }
    assert targets == {"'torchrl.envs.libs.maniskill.ManiSkillEnv'", "'maniskill_torchrl.ManiSkillEnv'"}

    def rest(c):
        return [ast.dump(a) for a in c.body if not (isinstance(a, ast.AnnAssign) and a.target.id == "_target_")]

    assert rest(cls) == rest(ours)


def test_ppo_mlp_parameters_on_the_networks_device():
    """The state-independent scale lives where the MLP does (``device: cuda`` on a GPU learner);
    the meta device stands in for one here."""
    node = configs.PPOMLPConfig(
        in_features=5, out_features=3, num_cells=[8], device="meta", state_independent_scale=-0.5
    )
    net = _build(node)
    assert {p.device.type for p in net.parameters()} == {"meta"}
    assert len(list(net.parameters())) == 5  # two layers' weights and biases, and the scale


def test_without_hydra_the_error_names_the_extra(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "hydra" else real(name, *a))
    monkeypatch.delitem(sys.modules, "maniskill_torchrl.configs")
    with pytest.raises(ImportError, match=r"maniskill-torchrl\[hydra\]"):
        importlib.import_module("maniskill_torchrl.configs")


# ----------------------------------------------------------------------------- the env node (issue 62)
def test_env_node_is_the_upstream_config_with_the_librarys_defaults():
    """One ``env/maniskill`` node: a subclass of the upstream ``ManiSkillEnvConfig`` (every YAML written for it
    composes), with TorchRL's gym node's default (one unbatched env) and the library's render device."""
    node = configs.ManiSkillEnvNodeConfig
    assert issubclass(node, configs.ManiSkillEnvConfig)
    defaults = OmegaConf.structured(node(env_name=TASK))
    assert defaults.num_envs == 0 and defaults.render_backend is None
    # TorchRL's own gym node is unbatched by default the same way.
    from torchrl.trainers.algorithms.configs import GymEnvConfig

    assert OmegaConf.structured(GymEnvConfig(env_name="Pendulum-v1")).num_envs == 0
    OmegaConf.structured(node(env_name=TASK, render_backend=None, num_envs=4))  # null is valid


def test_env_node_builds_one_unbatched_env_without_the_render_warning(capfd):
    capfd.readouterr()
    env = _build(configs.ManiSkillEnvNodeConfig(env_name=TASK, obs_mode="state", max_episode_steps=4))
    assert type(env) is ManiSkillEnv and env.batch_size == ()
    # ManiSkill's "Requested to use render device "sapien_cuda", but CUDA device was not found" (its own handler).
    assert "sapien_cuda" not in "".join(capfd.readouterr())
    want = ManiSkillEnv(TASK, obs_mode="state", max_episode_steps=4, batch_size=[])
    assert_tensordict_equal(_rollout(env), _rollout(want))
    batched = _build(configs.ManiSkillEnvNodeConfig(env_name=TASK, obs_mode="state", num_envs=1))
    assert batched.batch_size == (1,)
    with pytest.raises(ValueError, match="num_envs=0 is one unbatched env"):
        configs.make_maniskill_env(TASK, num_envs=0, batch_size=[2])
    with pytest.raises(ValueError, match="num_envs must be 0"):
        configs.make_maniskill_env(TASK, num_envs=-1)


def test_env_pickles_as_its_constructor():
    """A pickled ManiSkillEnv unpickles as a new env built from the same arguments (what a Hydra ``_partial_``
    node holding a live env needs in a collector's workers); a stepped env's state is not carried over."""
    import pickle

    env = ManiSkillEnv(TASK, obs_mode="state", max_episode_steps=4, batch_size=[])
    env.rand_step(env.reset(seed=1))
    copy = pickle.loads(pickle.dumps(env))
    assert type(copy) is ManiSkillEnv and copy is not env and copy.batch_size == ()
    assert copy.max_episode_steps == 4
    assert_tensordict_equal(_rollout(copy), _rollout(env))


def test_a_wrapper_of_a_users_env_refuses_pickling_as_python_words_it():
    """A ManiSkillWrapper around the user's own gym env cannot be rebuilt elsewhere: the TypeError says "cannot
    pickle '...' object", the words TorchRL 0.14.1's multi-process collectors re-raise at a worker's start
    (another TypeError there is swallowed and the worker dies unseen)."""
    import pickle

    from maniskill_torchrl import ManiSkillWrapper

    env = ManiSkillWrapper(make_gym_env(TASK, obs_mode="state"))
    with pytest.raises(TypeError, match="^cannot pickle 'ManiSkillWrapper' object: it holds a live ManiSkill sim"):
        pickle.dumps(env)


_PLUGIN_SCAN = """
import sys
{imports}
from hydra.core.config_store import ConfigStore
from hydra.core.plugins import Plugins
Plugins.instance()  # Hydra's plugin discovery, as @hydra.main runs it
print("hydra_plugins.maniskill_torchrl" in sys.modules, "maniskill_torchrl.configs" in sys.modules,
      "maniskill.yaml" in ConfigStore.instance().repo.get("env", {{}}))
"""


@pytest.mark.parametrize(
    ("imports", "registered"),
    [("", False), ("from torchrl.trainers.algorithms.configs import *  # noqa", True)],
    ids=["unrelated-app", "torchrl-configs-imported"],
)
def test_hydra_plugin_registers_the_nodes_only_beside_torchrls_configs(imports, registered):
    """``hydra_plugins/maniskill_torchrl`` (shipped with the library) runs at Hydra's plugin discovery: it registers
    the nodes where TorchRL's configs are imported (TorchRL's sota ``train.py`` files import them before
    ``hydra.main`` runs), and an unrelated Hydra app imports nothing of the library's."""
    import subprocess

    code = _PLUGIN_SCAN.format(imports=imports)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["True", str(registered), str(registered)], out.stderr[-3000:]


def test_rlpd_yaml_takes_maniskills_target_entropy_and_backup():
    """ManiSkill's RLPD sets the target entropy to -act_dim / 2 (TorchRL's "auto": -act_dim): PickCube-v1's
    pd_joint_delta_pos has 8 action dims; and its critic's target leaves out the entropy term (backup_entropy)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(ROOT / "examples" / "trainers" / "config"), version_base="1.3"):
        cfg = compose("rlpd_pickcube", overrides=["demos=/any/file.h5"])
    GlobalHydra.instance().clear()
    assert cfg.training_env.base_env.control_mode == "pd_joint_delta_pos"
    env = ManiSkillEnv(TASK, obs_mode="state", control_mode="pd_joint_delta_pos", batch_size=[])
    assert cfg.loss.target_entropy == -env.action_spec.shape[-1] / 2 == -4.0
    assert cfg.loss.backup_entropy is False
    assert cfg.loss._target_ == configs.SACBackupEntropyLossConfig._target_
