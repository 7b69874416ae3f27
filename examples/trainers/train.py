"""TorchRL's trainers on ManiSkill tasks, configured by YAML: pytorch/rl's ``sota-implementations``
``train.py`` (``sac_trainer``, ``ppo_trainer``), with this library's configs registered beside
TorchRL's (``env: maniskill``, its transforms, its demonstrations, its trainer hooks).

Usage (``docs/guides/trainers.md``)::

    python examples/trainers/train.py --config-name sac_pushcube
    python examples/trainers/train.py --config-name ppo_pullcube
    python examples/trainers/train.py --config-name rlpd_pickcube demos=demos/PickCube-v1/motionplanning

Any field is a Hydra override (``trainer.total_frames=100000``, ``logger=tensorboard``...); runs
write under ``outputs/<date>/<time>/`` (``hydra.job.chdir``).
"""

from maniskill_torchrl._internal.extras import require

hydra = require("hydra", "examples/trainers/train.py")  # the hydra extra, named when missing

from torchrl.trainers.algorithms.configs import *  # noqa: E402, F401, F403

from maniskill_torchrl.configs import *  # noqa: E402, F401, F403


@hydra.main(config_path="config", config_name="sac_pushcube", version_base="1.3")
def main(cfg):
    trainer = hydra.utils.instantiate(cfg.trainer)
    trainer.train()


if __name__ == "__main__":  # the CPU sim's worker processes start by spawn/forkserver
    main()
