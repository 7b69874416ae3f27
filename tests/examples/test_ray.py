"""TorchRL's Ray collectors over this library's envs (``examples/distributed_ray.py``'s code).

One local Ray instance (``ray.init(num_cpus=2)``) is shared by the module. Checked: frames and
layout of synchronous batches from 2 remote collectors, the library's entries (reward, done
flags, ``("next", "episode", ...)`` from ``EpisodeMetrics``), weights pushed between batches
reaching the remote side (policy version and actions), a remote collector that crashes (its
env factory raises, or its process exits) raising a Ray error within a time limit, and no
process of the test (Ray's head processes, its workers, the env workers under them) left
after ``collector.shutdown()`` and ``ray.shutdown()``. The last test shuts Ray down: keep it
last. About 2 minutes on 2 cores, mostly actor start-up (each imports torch, TorchRL, ManiSkill); before
them, the script itself stopped by Ctrl-C and by SIGTERM (each with its own Ray), about 1.5 minutes more.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from support.helpers import terminal_sigint

ray = pytest.importorskip("ray", reason="ray is not installed (pip install -e '.[distributed]')")

ROOT = Path(__file__).resolve().parents[2]
EPISODE = 10  # max_episode_steps: episodes end inside one batch
TIME_LIMIT_S = 120  # a crash must surface as an error well before this


def _load_example():
    spec = importlib.util.spec_from_file_location("distributed_ray_example", ROOT / "examples" / "distributed_ray.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    # Ray ships the env factory and the policy by pickle: by value, as the module is not importable there.
    ray.cloudpickle.register_pickle_by_value(mod)
    return mod


# ------------------------------------------------------------------------------- processes
def _proc_table() -> dict[int, tuple[int, str, int, str]]:
    """pid -> (ppid, state, start time in clock ticks, cmdline) of every live process (/proc)."""
    out = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                stat = f.read()
            with open(f"/proc/{name}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
        out[int(name)] = (int(fields[1]), fields[0], int(fields[19]), cmd)
    return out


def _descendants(root: int, table) -> set[tuple[int, int]]:
    """(pid, start time) of the live, non-zombie descendants of ``root``."""
    children: dict[int, list[int]] = {}
    for pid, (ppid, *_rest) in table.items():
        children.setdefault(ppid, []).append(pid)
    found, todo = set(), [root]
    while todo:
        for child in children.get(todo.pop(), []):
            todo.append(child)
            if table[child][1] != "Z":
                found.add((child, table[child][2]))
    return found


def _ray_named(table) -> set[tuple[int, int]]:
    """(pid, start time) of live processes that look like Ray's (head, workers)."""
    marks = ("raylet", "gcs_server", "ray::", "ray/_private", "ray/dashboard", "default_worker.py")
    return {(pid, t[2]) for pid, t in table.items() if t[1] != "Z" and any(m in t[3] for m in marks)}


def _still_alive(procs: set[tuple[int, int]]) -> dict[int, str]:
    table = _proc_table()
    return {
        pid: table[pid][3][:120]
        for pid, start in procs
        if pid in table and table[pid][2] == start and table[pid][1] != "Z"
    }


# ------------------------------------------------------------------ Ctrl-C and SIGTERM (the script)
@pytest.mark.parametrize(("sig", "whom"), [(signal.SIGINT, "group"), (signal.SIGTERM, "process")])
def test_a_stopped_script_prints_its_frames_shuts_ray_down_and_exits_conventionally(tmp_path, sig, whom) -> None:
    """``examples/distributed_ray.py`` as a user starts it, in its own session, stopped after its second
    batch: Ctrl-C reaches the whole process group (as from a terminal), SIGTERM the script alone (``kill PID``;
    ``ray.init`` had replaced its handler). It prints the frames so far, leaves no process (its group, Ray's
    head and workers) and exits 130 / 143 without a traceback. Runs before the module's own Ray instance."""
    before = _ray_named(_proc_table())
    cmd = [sys.executable, str(ROOT / "examples" / "distributed_ray.py"), "--batches", "1000"]
    cmd += ["--frames-per-batch", "100", "--max-episode-steps", str(EPISODE)]
    log = tmp_path / "log.txt"
    with log.open("w") as out:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            cmd,
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=tmp_path,
            env=env,
            start_new_session=True,
            preexec_fn=terminal_sigint,
        )
    try:
        deadline = time.monotonic() + 240
        while "batch 1:" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.3)
        assert "batch 1:" in log.read_text(), log.read_text()[-3000:]
        os.killpg(proc.pid, sig) if whom == "group" else proc.send_signal(sig)
        rc = proc.wait(timeout=TIME_LIMIT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = log.read_text()
    assert rc == 128 + sig, f"exit {rc}\n{text[-3000:]}"
    said = "Ctrl-C" if sig == signal.SIGINT else "SIGTERM"
    found = re.search(rf"{said} after (\d+) frames \((\d+) episodes finished", text)
    assert found and int(found.group(1)) >= 200, text[-3000:]
    assert "Traceback" not in text and "leaked" not in text, text[-3000:]
    end, left = time.monotonic() + 30, None
    while time.monotonic() < end:
        left = _still_alive(_ray_named(_proc_table()) - before)
        try:
            os.killpg(proc.pid, 0)
            group = True
        except ProcessLookupError:
            group = False
        if not left and not group:
            break
        time.sleep(0.5)
    assert not left and not group, f"left running: {left}, its group: {group}\n{text[-3000:]}"


# ------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def cluster():
    """One local Ray instance for the module; yields the processes that were there before it:
    Ray's, and this pytest's children (earlier tests may leave a multiprocessing forkserver or
    resource tracker alive until pytest exits)."""
    table = _proc_table()
    before = _ray_named(table) | _descendants(os.getpid(), table)
    ray.init(num_cpus=2, log_to_driver=False, include_dashboard=False)
    yield before
    if ray.is_initialized():
        ray.shutdown()


@pytest.fixture(scope="module")
def ex():
    torch.set_num_threads(1)
    return _load_example()


def _collector(ex, policy, env_fn, collectors: int, frames_per_batch: int, total_frames: int):
    # Ray is already initialised (cluster): TorchRL uses that instance and does not shut it down.
    return ex.make_collector(
        policy, collectors=collectors, frames_per_batch=frames_per_batch, total_frames=total_frames, env_fn=env_fn
    )


def _bounded(fn, limit: float = TIME_LIMIT_S):
    """Runs ``fn()`` in a thread; its exception (or None), and the seconds it took. A hang fails."""
    box: dict = {}

    def target():
        try:
            fn()
        except BaseException as err:  # noqa: BLE001 - handed to the test
            box["err"] = err

    t0 = time.perf_counter()
    th = threading.Thread(target=target, daemon=True)
    th.start()
    th.join(limit)
    assert not th.is_alive(), f"hung: no result or error after {limit} s"
    return box.get("err"), time.perf_counter() - t0


# ------------------------------------------------------------------------------- tests
def test_two_remote_collectors_frames_entries_and_weights(cluster, ex) -> None:
    obs_dim, act_dim = ex.env_dims("PushCube-v1")
    policy = ex.make_policy(obs_dim, act_dim, seed=0)
    env_fn = functools.partial(ex.make_env, "PushCube-v1", 1, EPISODE)
    fpb = 40
    collector = _collector(ex, policy, env_fn, collectors=2, frames_per_batch=fpb, total_frames=3 * fpb)
    try:
        collector.set_seed(0)
        collector.update_policy_weights_()
        batches = 0
        for i, batch in enumerate(collector):
            batches += 1
            assert batch.shape == torch.Size([2, fpb // 2])  # sync: one slice per remote collector
            assert batch.numel() == fpb
            for key in (
                "observation",
                "action",
                "policy_version",
                ("next", "observation"),
                ("next", "reward"),
                ("next", "done"),
                ("next", "terminated"),
                ("next", "truncated"),
                ("collector", "traj_ids"),
            ):
                assert key in batch.keys(True), key
            assert batch["next", "reward"].shape == (2, fpb // 2, 1)
            assert batch["next", "done"].dtype == torch.bool
            ep = batch["next", "episode"]
            assert set(ep.keys()) >= {"return", "episode_len", "reward", "success_once", "success_at_end"}
            assert ep["success_once"].dtype == torch.bool and ep["episode_len"].dtype == torch.int64
            assert ep["episode_len"].max() <= EPISODE
            done = batch["next", "done"].squeeze(-1)
            # the time limit ends every episode after EPISODE steps: 2 collectors x 20 steps
            assert int(done.sum()) == 2 * (fpb // 2) // EPISODE
            assert (ep["episode_len"][done] == EPISODE).all()
            # returns: the sum of the episode's rewards, per collector
            rewards = batch["next", "reward"].squeeze(-1)
            for c in range(2):
                ends = done[c].nonzero().flatten().tolist()
                starts = [0] + [e + 1 for e in ends[:-1]]
                for s, e in zip(starts, ends):
                    if i == 0 or s > 0:  # a whole episode inside this batch
                        torch.testing.assert_close(
                            ep["return"][c, e], rewards[c, s : e + 1].sum(), rtol=1e-5, atol=1e-5
                        )
            # the remote side ran the weights pushed before this batch
            assert batch["policy_version"].unique().tolist() == [i]
            with torch.no_grad():
                local = policy(batch.select("observation").clone())["action"]
            torch.testing.assert_close(batch["action"], local, rtol=1e-5, atol=1e-5)
            ex.new_weights(policy, version=i + 1)
            collector.update_policy_weights_()
        assert batches == 3
    finally:
        collector.shutdown()
    assert ray.is_initialized()  # the module's instance: not TorchRL's to shut down


def test_env_factory_that_raises_gives_an_error_not_a_hang(cluster, ex) -> None:
    policy = ex.make_policy(*ex.env_dims("PushCube-v1"))
    holder = {}

    def run():
        holder["c"] = _collector(ex, policy, ex.failing_env, collectors=1, frames_per_batch=10, total_frames=20)
        for _ in holder["c"]:
            pass

    err, took = _bounded(run)
    if "c" in holder:
        holder["c"].shutdown()
    assert err is not None, "a remote collector whose env factory raises must not yield data"
    # raised by the Collector(...) call itself (TorchRL waits for the actor there); the factory's
    # exception is in the message
    assert isinstance(err, ray.exceptions.ActorDiedError), repr(err)
    assert "env factory failed on purpose" in str(err)
    assert "c" not in holder


def test_remote_process_exit_gives_an_error_not_a_hang(cluster, ex) -> None:
    policy = ex.make_policy(*ex.env_dims("PushCube-v1"))
    env_fn = functools.partial(ex.make_env, "PushCube-v1", 1, EPISODE, crash_after=5)
    collector = _collector(ex, policy, env_fn, collectors=1, frames_per_batch=20, total_frames=40)
    try:
        collector.update_policy_weights_()
        err, took = _bounded(lambda: [None for _ in collector])
    finally:
        collector.shutdown()
    assert isinstance(err, ray.exceptions.ActorDiedError), repr(err)


def test_shutdown_leaves_no_processes(cluster, ex) -> None:
    """Last test: a batched env of 2 under the actor (sub-env 0 in the actor, one worker process),
    then shutdown + ray.shutdown."""
    me = os.getpid()
    policy = ex.make_policy(*ex.env_dims("PushCube-v1"))
    env_fn = functools.partial(ex.make_env, "PushCube-v1", 2, EPISODE)
    collector = _collector(ex, policy, env_fn, collectors=1, frames_per_batch=20, total_frames=40)
    try:
        collector.update_policy_weights_()
        batch = next(iter(collector))
        assert batch.numel() == 20 and ("next", "episode", "success_once") in batch.keys(True)
        table = _proc_table()
        started = (_descendants(me, table) | _ray_named(table)) - cluster
        cmds = [table[pid][3] for pid, _ in started]
        assert any("ray::" in c or "default_worker" in c for c in cmds), cmds  # the actor is seen
        assert len([c for c in cmds if "raylet" in c]) >= 1, cmds
        # the env workers: the actor's forkserver and the worker of sub-env 1 under it
        assert sum("multiprocessing.forkserver" in c for c in cmds) >= 2, cmds
    finally:
        collector.shutdown()
    ray.shutdown()
    deadline = time.monotonic() + 20
    while (left := _still_alive(started)) and time.monotonic() < deadline:
        time.sleep(0.25)
    assert not left, f"processes left after shutdown: {left}"
    stray = _descendants(me, _proc_table()) - cluster
    assert not stray, f"child processes left: {_still_alive(stray)}"
