"""``ManiSkillExperienceReplay``'s cache and TorchRL's dataset arguments, on a file that ManiSkill's
own ``RecordEpisode`` writes here: several processes building the same cache at once, stale
copies of a changed file, ``delete()``, and ``root`` / ``download`` / ``split_trajs`` as TorchRL's
datasets take them."""

from __future__ import annotations

import os
import sys
import textwrap

import pytest
import torch
from tensordict import TensorDict

from maniskill_torchrl.data import ManiSkillExperienceReplay
from maniskill_torchrl.testing import assert_tensordict_equal
from support.helpers import make_gym_env, record_episodes, start

TASK = "PickCube-v1"
LIMIT = 4
LENGTHS = [LIMIT, 2]  # a truncated episode, then one cut short by close(): split_trajs pads it


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A RecordEpisode file of two seeded episodes of different lengths."""
    env = make_gym_env(TASK, obs_mode="state", max_episode_steps=LIMIT)
    return record_episodes(env, tmp_path_factory.mktemp("demo"), seeds=range(len(LENGTHS)), lengths=LENGTHS)


def _entries(root):
    """Every cache folder under ``root``: {file folder: sorted copies}."""
    return {d.name: sorted(c.name for c in d.iterdir()) for d in root.iterdir()}


# One process's load of the dataset, forced to overlap with the other's: each writes its copy of the
# cache, then waits until every process has written, so that all of them rename at once. The test
# process is one of the processes (``load`` here), a subprocess running this source the other.
_LOADER = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from tensordict import TensorDict
    from maniskill_torchrl.data import ManiSkillExperienceReplay

    def load(path, root, barrier, me, n, out):
        original, depth = TensorDict.memmap_, []

        def memmap_then_wait(self, *args, **kwargs):
            depth.append(1)
            try:
                result = original(self, *args, **kwargs)
            finally:
                depth.pop()
            if not depth:  # the whole copy is written
                Path(barrier, me).touch()
                deadline = time.monotonic() + 120  # a hang guard, not a timing
                while len(list(Path(barrier).iterdir())) < int(n) and time.monotonic() < deadline:
                    time.sleep(0.01)
            return result

        TensorDict.memmap_ = memmap_then_wait
        try:
            data = ManiSkillExperienceReplay(path, 4, root=root)[:]
        finally:
            TensorDict.memmap_ = original
        data.clone().memmap_(out)

    if __name__ == "__main__":
        load(*sys.argv[1:])
    """
)


@pytest.mark.parametrize("trial", range(2))
def test_processes_building_the_same_cache_at_once(demo, tmp_path, trial):
    """Two processes that load one file at once (this one and a subprocess) both end with the
    file's data, and the cache holds one complete copy (the loser's own temporary copy removed)."""
    root, barrier = tmp_path / "cache", tmp_path / "barrier"
    barrier.mkdir()
    script = tmp_path / "load.py"
    script.write_text(_LOADER)
    n = 2
    args = [[str(demo), str(root), str(barrier), str(i), str(n), str(tmp_path / f"out{i}")] for i in range(n)]
    other = start([sys.executable, str(script), *args[1]], tmp_path)
    here: dict = {"__name__": "loader"}
    exec(compile(_LOADER, str(script), "exec"), here)
    try:
        here["load"](*args[0])
    finally:
        other.result()
    assert len(list(barrier.iterdir())) == n  # both wrote a copy before either renamed it
    expected = ManiSkillExperienceReplay(demo, 4, root=tmp_path / "alone")[:]
    for i in range(n):
        assert_tensordict_equal(TensorDict.load_memmap(tmp_path / f"out{i}"), expected, msg=f"process {i}")
    (folder,) = root.iterdir()
    assert len(list(folder.iterdir())) == 1, f"not one complete copy: {_entries(root)}"
    again = ManiSkillExperienceReplay(demo, 4, root=root)
    assert again._is_downloaded()
    assert_tensordict_equal(again[:], expected)


def test_a_changed_file_replaces_its_stale_copies_and_delete_removes_all(demo, tmp_path):
    """A new modification time makes a new copy and removes the old file's copies (every
    selection of it), never those of the current version or of another file; ``delete()``
    removes every copy of the file, and only those."""
    path = tmp_path / "demo.h5"
    path.write_bytes(demo.read_bytes())
    path.with_suffix(".json").write_bytes(demo.with_suffix(".json").read_bytes())
    other = tmp_path / "other.h5"
    other.write_bytes(demo.read_bytes())
    other.with_suffix(".json").write_bytes(demo.with_suffix(".json").read_bytes())
    root = tmp_path / "cache"
    ManiSkillExperienceReplay(other, 4, root=root)
    first = ManiSkillExperienceReplay(path, 4, root=root)
    one = ManiSkillExperienceReplay(path, 4, num_episodes=1, root=root)
    old = {first.data_path, one.data_path}
    assert all(p.exists() for p in old)

    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # the file changed
    second = ManiSkillExperienceReplay(path, 4, root=root)
    assert second.data_path not in old and second.data_path.exists()
    assert not any(p.exists() for p in old), f"stale copies left: {_entries(root)}"
    assert_tensordict_equal(second[:], first[:])
    # Another selection of the current version stays.
    two = ManiSkillExperienceReplay(path, 4, num_episodes=1, root=root)
    assert two.data_path.exists() and second.data_path.exists()
    assert_tensordict_equal(first[:], second[:])  # loaded data stays readable after its copy is gone

    others = ManiSkillExperienceReplay(other, 4, root=root, download=False)
    second.delete()
    assert not second.data_path.exists() and not two.data_path.exists()
    assert not second.data_path_root.exists(), f"copies left after delete(): {_entries(root)}"
    assert others.data_path.exists(), "delete() removed another file's cache"


def test_download_argument(demo, tmp_path):
    """``download``: True builds the cache when missing, False only reads one, "force" rebuilds."""
    root = tmp_path / "cache"
    with pytest.raises(FileNotFoundError, match=r"No cache of .*demo.h5.*download=True"):
        ManiSkillExperienceReplay(demo, 4, root=root, download=False)
    built = ManiSkillExperienceReplay(demo, 4, root=str(root), download=True)
    assert built.root == root and built.data_path.parent.parent == root
    marker = built.data_path / "marker"
    marker.touch()
    read = ManiSkillExperienceReplay(demo, 4, root=root, download=False)
    assert read.data_path == built.data_path and marker.exists()
    assert_tensordict_equal(read[:], built[:])
    forced = ManiSkillExperienceReplay(demo, 4, root=root, download="force")
    assert forced.data_path == built.data_path and not marker.exists()
    assert_tensordict_equal(forced[:], built[:])
    assert len(list(built.data_path_root.iterdir())) == 1
    with pytest.raises(ValueError, match=r"download must be True .*'force'.* or False"):
        ManiSkillExperienceReplay(demo, 4, root=root, download="yes")


def test_split_trajs(demo, tmp_path):
    """``split_trajs=True``: one row per episode, padded to the longest, ``("collector", "mask")``
    marking the real steps, each row's real steps the episode's steps; sampling draws episodes."""
    steps = ManiSkillExperienceReplay(demo, 4, root=tmp_path)
    split = ManiSkillExperienceReplay(demo, 3, root=tmp_path, split_trajs=True)
    assert split.data_path != steps.data_path  # cached apart
    data = split[:]
    assert data.batch_size == torch.Size([len(LENGTHS), max(LENGTHS)])
    assert len(split) == len(LENGTHS)
    assert data["collector", "mask"].sum(-1).tolist() == LENGTHS
    flat = steps[:]
    for e in range(len(LENGTHS)):
        mask = data["collector", "mask"][e]
        assert_tensordict_equal(
            data[e][mask].exclude(("collector", "mask")),
            flat[flat["collector", "traj_ids"] == e],
            msg=f"episode {e}",
        )
    assert split.sample().batch_size == torch.Size([3, max(LENGTHS)])
    # A second load reads the split cache.
    assert_tensordict_equal(
        ManiSkillExperienceReplay(demo, 3, root=tmp_path, split_trajs=True, download=False)[:], data
    )
