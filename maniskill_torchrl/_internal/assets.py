"""ManiSkill's registry and assets: task ids (and "did you mean"), and downloads a task needs,
refused with the command to run instead of ManiSkill's ``(y|n)`` prompt on stdin. No TorchRL
import."""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["check_assets", "missing_assets", "no_asset_prompt", "registered_env_ids", "similar_env_ids"]


def registered_env_ids() -> Any:
    """ManiSkill's task registry (``env_id -> EnvSpec``), after registering the tasks."""
    import mani_skill.envs  # noqa: F401  (registers the tasks)
    from mani_skill.utils.registration import REGISTERED_ENVS

    return REGISTERED_ENVS


def similar_env_ids(env_id: str, limit: int = 5) -> list[str]:
    """Registered task ids that contain ``env_id``'s name before the first ``-`` (the "did you mean")."""
    stem = env_id.split("-")[0].lower()
    if not stem:
        return []
    return [e for e in sorted(registered_env_ids()) if stem in e.lower()][:limit]


def _robot_uids(env_id: str, maniskill_kwargs: dict) -> list[str]:
    """The robots a task is made with: ``robot_uids`` if given, else the task's default."""
    spec = registered_env_ids()[env_id]
    uids = maniskill_kwargs.get("robot_uids", spec.default_kwargs.get("robot_uids"))
    if uids is None:
        param = inspect.signature(spec.cls.__init__).parameters.get("robot_uids")
        uids = param.default if param is not None and param.default is not param.empty else None
    uids = [uids] if isinstance(uids, str) else list(uids or [])
    return [u for u in uids if isinstance(u, str)]


def missing_assets(env_id: str, maniskill_kwargs: dict | None = None) -> dict[str, list[str]]:
    """The assets that ManiSkill declares for a task and that are not downloaded, by the name that
    fetches them (``python -m mani_skill.utils.download_asset <name>``): the task id for its own
    assets, a robot uid for a robot's. Empty when all are there. Reads files only: no env is made."""
    from mani_skill.utils import assets

    missing: dict[str, list[str]] = {}
    for group in [env_id, *_robot_uids(env_id, maniskill_kwargs or {})]:
        if group not in assets.DATA_GROUPS:
            continue
        ids = assets.expand_data_group_into_individual_data_source_ids(group)
        absent = [i for i in ids if not assets.is_data_source_downloaded(i)]
        if absent:
            missing[group] = absent
    return missing


def missing_assets_message(env_id: str, missing: dict[str, list[str]], asset: str | None = None) -> str:
    """What to tell a user whose task lacks assets: which, and the commands that fetch them.

    ``missing`` maps ``download_asset`` ids to what is absent; empty when ManiSkill asked for an
    asset (``asset``) that belongs to no known id."""
    if missing:
        what = "; ".join(
            f"{group}: {', '.join(ids[:3])}" + (f" and {len(ids) - 3} more" if len(ids) > 3 else "")
            for group, ids in missing.items()
        )
        how = " && ".join(f"python -m mani_skill.utils.download_asset {group}" for group in missing)
        how = f"`{how}`"
    else:
        what = asset or "an asset"
        how = (
            "`python -m mani_skill.utils.download_asset <id>` (`... download_asset -l robot`, `-l scene`, "
            "`-l task_assets` or `-l objects` lists the ids)"
        )
    return (
        f"ManiSkill task {env_id!r} needs assets that are not downloaded ({what}). Fetch them once "
        f"with {how} (into $MS_ASSET_DIR, default ~/.maniskill/data), then make the env again."
    )


def check_assets(env_id: str, maniskill_kwargs: dict | None = None) -> None:
    """Raises a :class:`FileNotFoundError` naming the task, its missing assets and the commands
    that fetch them, when ManiSkill declares assets for it that are not downloaded."""
    missing = missing_assets(env_id, maniskill_kwargs)
    if missing:
        raise FileNotFoundError(missing_assets_message(env_id, missing))


def _data_source_of(path: Path) -> str | None:
    """The ManiSkill data source (a ``download_asset`` id) whose folder holds ``path``, if any."""
    from mani_skill.utils import assets

    for uid, source in assets.DATA_SOURCES.items():
        folder = (Path(source.output_dir) / source.target_path).resolve()
        if path.is_relative_to(folder):
            return uid
    return None


@contextlib.contextmanager
def no_asset_prompt(env_id: str) -> Iterator[None]:
    """While making a ManiSkill env: ManiSkill's ``(y|n)`` download prompt raises a
    :class:`FileNotFoundError` that says what to run, instead of reading standard input (which
    blocks a script, or fails with a bare ``EOFError`` without a terminal); so does a file missing
    under ManiSkill's asset folder."""
    from mani_skill.utils import download_asset

    def refuse(message: str) -> bool:
        from mani_skill.utils import assets

        asset = message.split(" has assets")[0]  # "Robot <uid>", ManiSkill's only prompt in 3.0.1
        uid = asset.split()[-1] if asset else ""
        known = uid in assets.DATA_GROUPS or uid in assets.DATA_SOURCES
        raise FileNotFoundError(missing_assets_message(env_id, {uid: [asset]} if known else {}, asset=asset))

    prompt = download_asset.prompt_yes_no
    download_asset.prompt_yes_no = refuse
    try:
        yield
    except RuntimeError as e:
        # Some tasks check their dataset themselves and say which download_asset id fetches it.
        if "mani_skill.utils.download_asset" not in str(e):
            raise
        raise FileNotFoundError(f"ManiSkill task {env_id!r} needs assets that are not downloaded: {e}") from e
    except FileNotFoundError as e:
        # A task whose assets ManiSkill did not declare (scene datasets): a file missing under its
        # asset folder is a missing download, whatever error the task raises for it.
        from mani_skill import ASSET_DIR

        path = Path(str(e.filename or "")).resolve()
        if e.filename and path.is_relative_to(Path(ASSET_DIR).resolve()):
            source = _data_source_of(path)
            missing = {source: [str(path)]} if source else {}
            raise FileNotFoundError(missing_assets_message(env_id, missing, asset=str(path))) from e
        raise
    finally:
        download_asset.prompt_yes_no = prompt
