"""TorchRL's trainers on ManiSkill tasks, configured by YAML: pytorch/rl's ``sota-implementations``
``train.py`` (``sac_trainer``, ``ppo_trainer``), with this library's configs registered beside
TorchRL's (``env: maniskill``, its transforms, its demonstrations, its trainer hooks).

Usage (``docs/guides/trainers.md``)::

    python examples/trainers/train.py --config-name sac_pushcube
    python examples/trainers/train.py --config-name ppo_pullcube
    python examples/trainers/train.py --config-name rlpd_pickcube demos=demos/PickCube-v1/motionplanning

Any field is a Hydra override (``trainer.total_frames=100000``, ``logger=tensorboard``...); a run writes under
``outputs/<date>/<time>/`` (``hydra.job.chdir``), which it prints first: the logger's files, and at the end
(Ctrl-C and SIGTERM included, exit 130 / 143) ``policy.pt``: the trained actor's state dict with its task,
its config as the YAML and the overrides composed it, and its observation / action sizes, which
``examples/evaluate_gym.py --checkpoint <run folder>/policy.pt`` reads (it rebuilds the actor from that config).
"""

import sys
import warnings
from pathlib import Path

from maniskill_torchrl._internal.extras import require

hydra = require("hydra", "examples/trainers/train.py")  # the hydra extra, named when missing

import torch  # noqa: E402
from torchrl.trainers.algorithms.configs import *  # noqa: E402, F401, F403

from maniskill_torchrl.configs import *  # noqa: E402, F401, F403

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the examples' shared modules, wherever run from
import stopping  # noqa: E402
from ppo_checkpoint import TRAINER_FORMAT, actor_sizes  # noqa: E402

POLICY_FORMAT = TRAINER_FORMAT

# TorchRL 0.14.1's trainers warn on every run that they are a prototype and that the hook stages they register
# themselves ("optimizer", "post_loss") will move: nothing a user of this script can act on. This script's filters
# only; importing the library filters nothing.
warnings.filterwarnings("ignore", message=r".*is an experimental/prototype feature", category=UserWarning)
warnings.filterwarnings(
    "ignore", message=r"The '\w+' hook stage will be replaced by OptimizationStepper", category=FutureWarning
)


def _repeat(env_cfg) -> int:
    """Sim steps per agent step of the training env: its ``frame_skip`` times its ``ActionRepeat`` transforms'."""
    repeat = env_cfg.base_env.get("frame_skip") or 1
    for t in (env_cfg.get("transform") or {}).get("transforms") or []:
        if str(t.get("_target_", "")).endswith(".ActionRepeat"):
            repeat *= int(t.repeat)
    return int(repeat)


@hydra.main(config_path="config", config_name="sac_pushcube", version_base="1.3")
def main(cfg):
    from hydra.core.hydra_config import HydraConfig

    from maniskill_torchrl._internal.rendering import quiet_maniskill

    quiet_maniskill()  # ManiSkill's notes that say nothing actionable here (no CUDA to render with, task builders')
    out = Path(HydraConfig.get().runtime.output_dir)
    print(f"output folder: {out}", flush=True)
    trainer = hydra.utils.instantiate(cfg.trainer)
    stopped = None
    with stopping.interruptible():  # SIGTERM as Ctrl-C: the policy so far is saved, then exit 143 (130)
        try:
            trainer.train()
        except KeyboardInterrupt as err:
            stopped = err
            print(f"{stopping.said(err)}: saving the policy so far", flush=True)
    from omegaconf import OmegaConf

    base = cfg.training_env.base_env
    actor = trainer.loss_module.actor_network
    obs_dim, act_dim = actor_sizes(actor)
    with stopping.uninterrupted():
        torch.save(
            {
                "format": POLICY_FORMAT,
                "config_name": HydraConfig.get().job.config_name,
                "env_id": base.env_name,
                "obs_mode": base.obs_mode,
                "control_mode": base.control_mode,
                "obs_dim": obs_dim,
                "act_dim": act_dim,
                "repeat": _repeat(cfg.training_env),
                "actor": OmegaConf.to_yaml(cfg.loss.actor_network, resolve=True),  # rebuilt by evaluate_gym.py
                "frames": int(getattr(trainer, "collected_frames", 0)),
                "policy": actor.state_dict(),
            },
            out / "policy.pt",
        )
    print(f"saved {out / 'policy.pt'}; logs under {out}", flush=True)
    print(f"evaluate it: python examples/evaluate_gym.py --checkpoint {out / 'policy.pt'}", flush=True)
    if stopped is not None:
        sys.exit(stopping.exit_status(stopped))


if __name__ == "__main__":  # the CPU sim's worker processes start by spawn/forkserver
    main()
