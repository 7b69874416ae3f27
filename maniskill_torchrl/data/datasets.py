"""The ``maniskill:`` prefix of TorchRL's :func:`~torchrl.data.datasets.load_dataset`.

``import maniskill_torchrl.data`` registers it (TorchRL's ``register_dataset``), so that
``load_dataset("maniskill:<id>", batch_size=...)`` and
``OfflineToOnlineReplayBuffer("maniskill:<id>", ...)`` build a
:class:`~maniskill_torchrl.data.ManiSkillExperienceReplay`. Nothing is downloaded.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path, PurePosixPath
from typing import Any

from maniskill_torchrl.data.experience_replay import ManiSkillExperienceReplay

__all__ = ["load_maniskill_dataset"]


def load_maniskill_dataset(
    dataset_id: str,
    batch_size: int,
    *,
    obs_mode: str | None = None,
    control_mode: str | None = None,
    **kwargs: Any,
) -> ManiSkillExperienceReplay:
    """The ManiSkill trajectory file ``dataset_id`` names, as a replay buffer.

    What ``load_dataset("maniskill:<dataset_id>", ...)`` calls. ``dataset_id`` is one of:

    - a path to a trajectory ``.h5`` file (absolute, relative or starting with ``~``), or to a
      folder of them;
    - ``<task>/<source>``: ManiSkill's demo folder ``<task>/<source>`` under ``mani_skill.DEMO_DIR``
      (``$MS_ASSET_DIR/demos``, by default ``~/.maniskill/demos``), as ManiSkill's
      ``download_demo``, motion planners and ``replay_trajectory`` lay it out, e.g.
      ``"PickCube-v1/motionplanning"``; the file must hold ``<task>`` (``env_id=<task>``);
    - ``<task>/<source>/<file name>``: one file of that folder.

    A path that exists (from the working directory) is taken as a path first. In a folder, the
    only ``.h5`` file is taken. Where there are several (``replay_trajectory`` writes
    ``<name>.<obs_mode>.<control_mode>.<sim_backend>.h5`` beside the file it replays),
    ``obs_mode`` and ``control_mode`` choose one, read from the file's name as ManiSkill names
    them, or else from its ``.json`` (``env_info.env_kwargs``); a choice that leaves none or
    several is an error listing the files. Given for one file, they are checked against it.

    Args:
        dataset_id: the file, as above.
        batch_size: the sample size of ``sample()``.

    Keyword Args:
        obs_mode (str, optional): the observation mode of the file to take.
        control_mode (str, optional): the control mode of the file to take.
        **kwargs: :class:`~maniskill_torchrl.data.ManiSkillExperienceReplay`'s (``env_id``,
            ``success_only``, ``num_episodes``, ``root``, ``download``, ``split_trajs``,
            ``sampler``...).

    Raises:
        FileNotFoundError: no such file or folder, or no file in the folder of the modes asked
            for; the message says where it looked and how to make demonstrations.
        ValueError: several files and no way to choose, or a file of other modes than those asked
            for, or an ``env_id`` other than ``<task>``.

    Examples:
        >>> import maniskill_torchrl.data  # registers the prefix
        >>> from torchrl.data.datasets import load_dataset
        >>> demos = load_dataset(  # doctest: +SKIP
        ...     "maniskill:PickCube-v1/motionplanning",
        ...     batch_size=256,
        ...     obs_mode="state",
        ...     control_mode="pd_ee_delta_pos",
        ... )
    """
    path, task = _resolve(dataset_id, obs_mode, control_mode)
    if task is not None:
        env_id = kwargs.setdefault("env_id", task)
        if env_id != task:
            raise ValueError(f"maniskill:{dataset_id} is a demonstration of {task!r}, but env_id={env_id!r}.")
    return ManiSkillExperienceReplay(path, batch_size, **kwargs)


def _demo_dir() -> Path:
    """ManiSkill's own demo folder (read at each call, so that a patched one is seen)."""
    import mani_skill

    return Path(mani_skill.DEMO_DIR)


def _resolve(dataset_id: str, obs_mode: str | None, control_mode: str | None) -> tuple[Path, str | None]:
    """(the ``.h5`` file, the task it must hold or ``None`` for a path)."""
    if not isinstance(dataset_id, str) or not dataset_id.strip():
        raise ValueError(f"A maniskill: dataset id is a trajectory file or <task>/<source>, got {dataset_id!r}.")
    given = _user_path(dataset_id)
    parts = PurePosixPath(dataset_id).parts
    explicit = dataset_id.startswith(("~", ".")) or given.is_absolute()
    if given.exists() or explicit or len(parts) not in (2, 3):
        target, task = given, None
    else:
        target, task = _demo_dir().joinpath(*parts), parts[0]
    if not target.exists():
        raise FileNotFoundError(_missing(dataset_id, target, task))
    if target.is_dir():
        return _choose(dataset_id, target, obs_mode, control_mode, task), task
    if not _matches(target, obs_mode, control_mode):
        raise ValueError(
            f"{target} holds {_describe(target)}, not {_asked(obs_mode, control_mode)}: name another file, "
            "or make one in these modes with ManiSkill's replay_trajectory (-o OBS_MODE -c CONTROL_MODE)."
        )
    return target, task


def _user_path(dataset_id: str) -> Path:
    """The path ``dataset_id`` names: a relative one, while a Hydra app runs, from the directory it started in
    (``hydra.utils.to_absolute_path``): its ``hydra.job.chdir`` (TorchRL's sota configs set it) moves the working
    directory into the run's output folder, where the user's ``demos=demos/x.h5`` is not."""
    path = Path(dataset_id).expanduser()
    hydra_config = sys.modules.get("hydra.core.hydra_config")  # never imported here: only a running app has it
    if path.is_absolute() or hydra_config is None or not hydra_config.HydraConfig.initialized():
        return path
    from hydra.utils import to_absolute_path

    return Path(to_absolute_path(str(path)))


def _unknown_task(task: str) -> str:
    """The env's own error for a task id that is no registered task (its did-you-mean), else ``""``."""
    from maniskill_torchrl.envs import maniskill

    if task in maniskill.ManiSkillWrapper.available_envs:
        return ""
    try:
        maniskill._task_kwargs(task, 1, False, None, {})  # raises the env's "Unknown ManiSkill env ..." error
    except ValueError as err:
        return f"{err} "
    return ""


def _modes(path: Path) -> tuple[str | None, str | None]:
    """(obs_mode, control_mode) of a trajectory file: from its name where ManiSkill put them there
    (``<name>.<obs_mode>.<control_mode>[.<sim_backend>].h5``), else from its ``.json``."""
    parts = path.name[: -len(path.suffix)].split(".")
    if len(parts) >= 3:
        return parts[1], parts[2]
    try:
        kwargs = json.loads(path.with_suffix(".json").read_text())["env_info"]["env_kwargs"]
        return kwargs.get("obs_mode"), kwargs.get("control_mode")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None, None


def _matches(path: Path, obs_mode: str | None, control_mode: str | None) -> bool:
    if obs_mode is None and control_mode is None:
        return True
    have_obs, have_control = _modes(path)
    return (obs_mode is None or have_obs == obs_mode) and (control_mode is None or have_control == control_mode)


def _describe(path: Path) -> str:
    obs_mode, control_mode = _modes(path)
    return f"obs_mode={obs_mode!r}, control_mode={control_mode!r}"


def _asked(obs_mode: str | None, control_mode: str | None) -> str:
    asked = {"obs_mode": obs_mode, "control_mode": control_mode}
    return ", ".join(f"{k}={v!r}" for k, v in asked.items() if v is not None)


def _choose(dataset_id: str, folder: Path, obs_mode: str | None, control_mode: str | None, task: str | None) -> Path:
    """The one trajectory file of ``folder`` (of the modes asked for, if any)."""
    files = sorted(p for p in folder.glob("*.h5") if p.is_file())
    if not files:
        raise FileNotFoundError(_missing(dataset_id, folder, task, empty=True))
    chosen = [p for p in files if _matches(p, obs_mode, control_mode)]
    if len(chosen) == 1:
        return chosen[0]
    listing = "\n".join(f"  {p.name}  ({_describe(p)})" for p in files)
    if not chosen:
        raise FileNotFoundError(
            f"No trajectory file of {_asked(obs_mode, control_mode)} in {folder}; it holds:\n{listing}\n"
            "Make one with ManiSkill's replay_trajectory: python -m mani_skill.trajectory.replay_trajectory "
            f"--traj-path {folder}/<file>.h5 -o OBS_MODE -c CONTROL_MODE --save-traj"
        )
    candidates = "\n".join(f"  {p.name}  ({_describe(p)})" for p in chosen)
    raise ValueError(
        f"{len(chosen)} trajectory files in {folder} fit maniskill:{dataset_id}"
        + (f" with {_asked(obs_mode, control_mode)}" if chosen != files else "")
        + f":\n{candidates}\nChoose one with obs_mode= and control_mode= (e.g. "
        f'load_dataset("maniskill:{dataset_id}", batch_size=..., obs_mode="state", '
        f'control_mode="pd_ee_delta_pos")), or name the file: "maniskill:{dataset_id.rstrip("/")}/<file name>".'
    )


def _missing(dataset_id: str, where: Path, task: str | None, empty: bool = False) -> str:
    """Where ``maniskill:<dataset_id>`` was looked for, and how to make demonstrations."""
    found = f"No trajectory file (.h5) in {where}" if empty else f"No such file or folder: {where}"
    if task is not None:
        how = (
            f"maniskill:{dataset_id} is <task>/<source>[/<file>] under ManiSkill's demo folder {_demo_dir()} "
            "($MS_ASSET_DIR/demos, by default ~/.maniskill/demos)"
        )
    else:
        how = (
            f"maniskill:{dataset_id} was read as a path (a trajectory .h5 or a folder of them); "
            "<task>/<source>[/<file>] names one under ManiSkill's demo folder ($MS_ASSET_DIR/demos, "
            "by default ~/.maniskill/demos)"
        )
    name = task or "<task>"
    return (
        (_unknown_task(task) if task is not None else "")
        + f"{found}. {how}. Nothing is downloaded. Make demonstrations with ManiSkill's tools: "
        f"`python -m mani_skill.utils.download_demo {name}` (published demos, without observations), "
        f"or its motion planners, `python -m mani_skill.examples.motionplanning.panda.run -e {name} "
        f"--record-dir <demo folder> --traj-name trajectory`; then add observations in your modes with "
        f"`python -m mani_skill.trajectory.replay_trajectory --traj-path <demo folder>/{name}/<source>/"
        "trajectory.h5 -o state -c pd_ee_delta_pos --save-traj`."
    )
