"""Every task of ManiSkill's registry through the library (``make test-registry``; CI runs it).

For each registered task whose assets are here, :func:`maniskill_torchrl.testing.check_maniskill_env`:
20 seeded steps (resets included) of ``ManiSkillEnv`` equal to raw ManiSkill, then
``check_env_specs`` on the same env, and the gym shim's ``CPUGymWrapper`` equal to ManiSkill's.
A sample of tasks, one per robot family, runs the batched CPU env (``num_envs=2``, one process
per sub-env) the same way. A task whose assets are absent is
skipped, and the reason is the library's own error: the asset and the command that fetches it.
"""

from __future__ import annotations

import pytest

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl._internal.assets import check_assets
from maniskill_torchrl.testing import check_maniskill_env

STEPS = 20
# One task per robot family (and per kind of reward dtype) for the batched CPU env.
BATCHED_SAMPLE = [
    "PickCube-v1",  # panda
    "StackCube-v1",  # panda_wristcam
    "PushT-v1",  # panda_stick
    "DrawTriangle-v1",  # panda_stick, bool reward
    "PickCubeSO100-v1",  # so100
    "RotateSingleObjectInHandLevel0-v1",  # allegro hand
    "TwoRobotPickCube-v1",  # two pandas: Dict actions
    "MS-AntWalk-v1",  # MJCF ant
    "UnitreeG1Stand-v1",  # unitree g1, bool reward
    "RotateValveLevel0-v1",  # dclaw, float64 reward
    "TriFingerRotateCubeLevel0-v1",  # trifinger
    "MS-HumanoidStand-v1",  # MJCF humanoid
    "MS-CartpoleBalance-v1",  # MJCF cartpole
]


def _skip_if_assets_absent(env_id: str) -> None:
    try:
        check_assets(env_id)
    except FileNotFoundError as e:
        pytest.skip(str(e))


def _check(env_id: str, **kwargs) -> None:
    try:
        check_maniskill_env(env_id, steps=STEPS, seed=0, obs_mode="state", **kwargs)
    except FileNotFoundError as e:  # assets ManiSkill does not declare (scene datasets)
        if "needs assets that are not downloaded" in str(e):
            pytest.skip(str(e))
        raise


@pytest.mark.parametrize("env_id", sorted(ManiSkillEnv.available_envs))
def test_task(env_id):
    _skip_if_assets_absent(env_id)
    _check(env_id)


@pytest.mark.parametrize("env_id", BATCHED_SAMPLE)
def test_task_batched_cpu_env(env_id):
    _skip_if_assets_absent(env_id)
    _check(env_id, num_envs=2, sim_backend="cpu")
