"""What users run: the ``maniskill-torchrl demo`` CLI and the examples, end to end.

The console script (``maniskill-torchrl demo``) and ``python -m maniskill_torchrl`` run as
subprocesses, the way a user starts them, overlapping (:func:`runs`). The examples run their
``main(argv)`` in this process in a small configuration (:func:`in_process`): a subprocess each
would import torch, TorchRL and ManiSkill again, most of its cost. Each test checks the exit
code, the printed lines and the files written. Flag validation runs in-process (no simulator is
built); nothing here is skipped.
"""

from __future__ import annotations

import json
import re
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import bc_torchrl
import evaluate_gym
import evaluation
import migrate_from_maniskill
import ppo_torchrl
import sac_torchrl
import sim_device
from maniskill_torchrl import cli
from support.helpers import TIMEOUT_S, Started, start

BIN = Path(sys.executable).parent


def in_process(module, argv: list[str], cwd: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> str:
    """``module.main(argv)`` run in ``cwd`` in this process, as ``python module.py *argv`` would run
    it: its exit code checked, what it printed returned. The torch threads it sets are restored."""
    import torch

    threads = torch.get_num_threads()
    monkeypatch.chdir(cwd)
    capsys.readouterr()
    try:
        code = module.main(argv)
    finally:
        torch.set_num_threads(threads)
    out, err = capsys.readouterr()
    assert code == 0, f"{module.__name__}.main({argv}) returned {code}\n{out[-4000:]}\n{err[-4000:]}"
    return out


def _smoke(example: str, cwd: Path) -> list[str]:
    """``<example>_torchrl.py --smoke``'s arguments with the simulator and the learner's device
    pinned: on a machine with CUDA too, the CPU sim and a CPU learner."""
    return ["--smoke", "--sim-backend", "cpu", "--device", "cpu", "--out", str(cwd / example)]


# test name -> the command it runs, given its working folder
COMMANDS: dict[str, Callable[[Path], list[str]]] = {
    "test_demo_console_script_end_to_end": lambda cwd: [
        str(BIN / "maniskill-torchrl"),
        "demo",
        "--frames",
        "200",
        "--workers",
        "2",
        "--video-steps",
        "4",
        "--video-size",
        "64",
        "--out",
        str(cwd / "demo"),
        "--no-progress",
    ],
    "test_python_dash_m_help": lambda cwd: [sys.executable, "-m", "maniskill_torchrl", "demo", "--help"],
}


@pytest.fixture(scope="module")
def runs(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable]:
    """``runs(name)`` -> (the finished run of test ``name``, checked as ``helpers.run`` checks it;
    its working folder). The runs of the selected tests start in their order, two at a time:
    while a test waits for its own, the next ones start as others end. Runs left are killed."""
    order = [item.name for item in request.session.items if item.module is request.module and item.name in COMMANDS]
    started: dict[str, tuple[Started, Path]] = {}

    def begin(name: str) -> None:
        if name not in started:
            cwd = tmp_path_factory.mktemp(name.removeprefix("test_"))
            started[name] = (start(COMMANDS[name](cwd), cwd=cwd), cwd)

    def fill() -> None:
        for name in order:
            if sum(handle.running() for handle, _ in started.values()) >= 2:
                return
            begin(name)

    def get(name: str):
        begin(name)
        handle, cwd = started[name]
        deadline = time.monotonic() + TIMEOUT_S
        while handle.running() and time.monotonic() < deadline:
            fill()
            time.sleep(0.2)
        return handle.result(), cwd

    yield get
    for handle, _ in started.values():
        handle.kill()


# ----------------------------------------------------------------------------- demo
def test_demo_console_script_end_to_end(runs) -> None:
    """``maniskill-torchrl demo`` (what ``make demo`` runs) with few frames and a tiny video."""
    script = BIN / "maniskill-torchrl"
    assert script.exists(), f"console script not installed at {script}: pip install -e . in this venv"
    proc, cwd = runs("test_demo_console_script_end_to_end")
    out = cwd / "demo"
    stdout = proc.stdout
    for line in (
        "maniskill-torchrl demo summary",
        "frames/s",
        "episodes finished",
        "mean return",
        "success rate",
        "ManiSkillEnv(num_envs=2) -> ActionRepeat(2) -> EpisodeMetrics",
    ):
        assert line in stdout, f"{line!r} missing from:\n{stdout}"

    png = (out / "returns.png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    import imageio.v2 as imageio

    reader = imageio.get_reader(out / "rollout.mp4")
    frames = list(reader.iter_data())  # not list(reader): its len() is inf for ffmpeg streams
    reader.close()
    assert len(frames) == 5  # the reset frame + one per agent step
    assert frames[0].shape == (64, 64, 3)

    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 200 and summary["workers"] == 2 and summary["repeat"] == 2
    assert summary["policy"] == "scripted"
    # ActionRepeat(2): up to 2 sim steps per agent step, fewer only where an episode ended mid-repeat.
    assert summary["frames"] < summary["sim_steps"] <= 2 * summary["frames"]
    # The scripted policy finishes a PickCube episode in ~15 agent steps: 200 frames end several.
    assert summary["episodes_finished"] >= 4
    episodes = summary["episodes"]
    assert len(episodes) == summary["episodes_finished"]
    assert {"return", "episode_len", "success_once", "success_at_end"} <= set(episodes[0])
    assert all(1 <= e["episode_len"] <= 25 for e in episodes)  # PickCube's 50-step limit / repeat 2
    assert sum(e["success_once"] for e in episodes) >= len(episodes) // 2


def test_demo_no_video_writes_no_video(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """``--no-video`` builds no render env; the plot and summary are still written (collection stubbed)."""
    episodes = [
        {"return": 1.5, "episode_len": 10, "success_once": True, "success_at_end": True, "terminated": True},
        {"return": 0.5, "episode_len": 25, "success_once": False, "success_at_end": False, "terminated": False},
    ]
    stats = {
        "frames": 100,
        "sim_steps": 190,
        "startup_s": 1.0,
        "frames_per_s": 50.0,
        "sim_steps_per_s": 95.0,
        "episodes_finished": 2,
    }
    monkeypatch.setattr(cli, "_collect", lambda *a: (list(episodes), None, dict(stats)))

    def no_video(*a, **k):
        raise AssertionError("record_video called with --no-video")

    monkeypatch.setattr(cli, "record_video", no_video)
    out = tmp_path / "o"
    assert cli.main(["demo", "--no-video", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["returns.png", "summary.json"]
    text = capsys.readouterr().out
    assert "success rate          50.0 %" in text
    assert "mean return           1.000" in text


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["demo", "--frames", "0"], "argument --frames: must be a positive integer, got 0"),
        (["demo", "--workers", "two"], "argument --workers: must be a positive integer, got 'two'"),
        (["demo", "--repeat", "-1"], "argument --repeat: must be a positive integer"),
        (["demo", "--seed", "x"], "argument --seed: must be an integer"),
        (["demo", "--frames", "1", "--workers", "2"], "--frames (1) must be at least --workers (2)"),
        (["demo", "--env-id", "PickCub-v1"], "unknown --env-id 'PickCub-v1'"),
        (["demo", "--env-id", "PushCube-v1", "--policy", "scripted"], "--policy scripted is a controller"),
        (["demo", "--policy", "greedy"], "argument --policy: invalid choice"),
        (["demo", "--bogus"], "unrecognized arguments: --bogus"),
        ([], "the following arguments are required: COMMAND"),
    ],
)
def test_demo_bad_flags(argv: list[str], message: str, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_demo_out_must_be_a_folder(tmp_path: Path, capsys) -> None:
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    with pytest.raises(SystemExit) as exc:
        cli.main(["demo", "--out", str(not_a_dir)])
    assert exc.value.code == 2
    assert "exists and is not a folder" in capsys.readouterr().err


def test_python_dash_m_help(runs) -> None:
    proc, _ = runs("test_python_dash_m_help")
    for flag in ("--env-id", "--repeat", "--frames", "--workers", "--out", "--seed", "--no-video"):
        assert flag in proc.stdout


def test_scripted_policy_is_batched_and_bounded() -> None:
    import torch

    pol = cli.PickCubeScriptedPolicy()
    # cube 5 cm away at gripper height / just below the gripper / in the gripper
    tcp_to_obj = torch.tensor([[0.05, 0.0, 0.0], [0.0, 0.0, -0.005], [0.0, 0.0, 0.0]])
    obj_to_goal = torch.tensor([[0.0, 0.0, 0.1]] * 3)
    grasped = torch.tensor([False, False, True])
    action = pol(tcp_to_obj, obj_to_goal, grasped)
    assert action.shape == (3, 4) and action.abs().max() <= 1
    assert action[:, 3].tolist() == [1.0, -1.0, -1.0]  # open far away, close at the cube or holding it
    assert action[0, 2] > 0 and action[0, 0] > 0  # not aligned yet: towards a point above the cube
    assert action[1, 2] < 0  # aligned: descend onto it
    assert action[2, :3].tolist() == pytest.approx([0.0, 0.0, 1.0])  # holding it: towards the goal


# ------------------------------------------------------------------------- examples
def test_ppo_smoke(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    stdout = in_process(ppo_torchrl, _smoke("ppo", tmp_path), tmp_path, monkeypatch, capsys)
    out = tmp_path / "ppo"
    assert "PPO on PushCube-v1 (CPU sim, 2 envs, ActionRepeat(1), learner on cpu)" in stdout
    iters = [line for line in stdout.splitlines() if line.startswith("iter")]
    assert len(iters) == 3, stdout

    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["frames"] for r in records] == [100, 200, 300]
    # 50-step PushCube episodes and 50-step rollouts: every iteration ends 2 episodes.
    assert all(r["episodes"] == 2 and r["episode_len"] == 50 for r in records)
    assert all({"return", "success_once", "loss_objective", "loss_critic"} <= set(r) for r in records)

    import torch

    ckpt = torch.load(out / "ppo_checkpoint.pt", weights_only=False)
    assert {"policy", "value", "args", "frames"} <= set(ckpt)
    assert ckpt["frames"] == 300 and ckpt["args"]["env_id"] == "PushCube-v1"
    assert any(k.endswith("weight") for k in ckpt["policy"]) and any(k.endswith("weight") for k in ckpt["value"])


def test_sac_smoke(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """``sac_torchrl.py --smoke --sim-backend cpu --device cpu``: random frames, updates, two evaluations
    (the random policy's and the trained one's) and both checkpoints."""
    stdout = in_process(sac_torchrl, _smoke("sac", tmp_path), tmp_path, monkeypatch, capsys)
    out = tmp_path / "sac"
    assert "SAC on PushCube-v1 (CPU sim, 2 envs, learner on cpu)" in stdout, stdout
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [(r["eval"], r["frames"]) for r in records] == [("random", 0), ("policy", 400)]
    assert all(r["episodes"] == 2 and {"success_once", "return"} <= set(r) for r in records)
    import torch

    ckpt = torch.load(out / "sac_checkpoint.pt", weights_only=False)
    assert ckpt["frames"] == 400 and ckpt["args"]["sim_backend"] == "cpu" and ckpt["args"]["device"] == "cpu"
    assert (out / "sac_checkpoint_best.pt").exists()


def test_evaluate_gym(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """The random policy without a checkpoint. One sub-env: its second episode starts with
    gymnasium's autoreset step (``tests/test_evaluate.py`` runs two sub-envs, with a checkpoint, as
    subprocesses)."""
    argv = ["--num-envs", "1", "--episodes", "2", "--max-episode-steps", "10", "--seed", "1"]
    stdout = in_process(evaluate_gym, argv, tmp_path, monkeypatch, capsys)
    lines = [line for line in stdout.splitlines() if line.startswith("episode ")]
    assert len(lines) == 2, stdout
    for line in lines:
        # ignore_terminations=True: every episode runs to the time limit.
        assert "success_once=" in line and "success_at_end=" in line and "return=" in line
        assert "episode_len=10" in line
    for avg in ("episodes: 2", "avg success_once:", "avg success_at_end:", "avg return:"):
        assert avg in stdout


def test_migrate_from_maniskill(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    argv = ["--steps", "12", "--max-episode-steps", "10", "--repeat", "2"]
    stdout = in_process(migrate_from_maniskill, argv, tmp_path, monkeypatch, capsys)
    assert "identical: True" in stdout, stdout
    assert stdout.count("reset") >= 2 * 3  # both columns: the first reset and two seeded resets


# ------------------------------------------------------------ --sim-backend / --device
EXAMPLE_MODULES = {"ppo": ppo_torchrl, "sac": sac_torchrl, "bc": bc_torchrl}


@pytest.mark.parametrize(
    ("sim_backend", "device", "smoke", "expected"),
    [
        ("auto", "cuda", False, ("gpu", "cuda")),  # what --device cuda meant before --sim-backend
        ("auto", "cuda:1", False, ("gpu", "cuda:1")),
        ("auto", "cpu", False, ("cpu", "cpu")),
        ("auto", "cuda", True, ("cpu", "cuda")),  # --smoke is a CPU-sim configuration
        ("cpu", "cuda", False, ("cpu", "cuda")),  # the CPU sim feeding a GPU learner
        ("cpu", "cpu", False, ("cpu", "cpu")),
        ("cpu", "cpu", True, ("cpu", "cpu")),
        ("gpu", "cuda", False, ("gpu", "cuda")),
        ("gpu", "cpu", False, "--sim-backend gpu needs --device cuda"),
        ("gpu", "cuda", True, "--smoke is a CPU-sim configuration"),
        ("physx_cuda", "cuda", False, "--sim-backend must be one of auto, cpu, gpu"),
        ("cpu", "mps", False, "--device must be cpu or cuda"),
    ],
)
def test_sim_backend_resolution(sim_backend, device, smoke, expected) -> None:
    """The one rule (``examples/sim_device.py``), pure: no CUDA is read, so every pair is checked here."""
    import torch

    if isinstance(expected, str):
        with pytest.raises(ValueError, match=re.escape(expected)):
            sim_device.resolve(sim_backend, device, smoke)
    else:
        backend, dev = sim_device.resolve(sim_backend, device, smoke)
        assert (backend, dev) == (expected[0], torch.device(expected[1]))


def _fake_cuda(monkeypatch: pytest.MonkeyPatch, available: bool) -> None:
    """The examples' flag checks read ``torch.cuda.is_available()`` and ``current_device()`` only:
    patched, the parsing of a machine with (or without) CUDA runs on any machine."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: available)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)


# (flags, CUDA there?) -> resolved (sim_backend, device) per example, or the refusal's message.
DEVICE_FLAGS = [
    ([], True, {"ppo": ("gpu", "cuda:0"), "sac": ("gpu", "cuda:0"), "bc": ("cpu", "cpu")}),
    ([], False, ("cpu", "cpu")),
    (["--device", "cuda"], True, ("gpu", "cuda:0")),
    (["--device", "cuda:0", "--sim-backend", "gpu"], True, ("gpu", "cuda:0")),
    (["--sim-backend", "cpu"], True, {"ppo": ("cpu", "cuda:0"), "sac": ("cpu", "cuda:0"), "bc": ("cpu", "cpu")}),
    (["--sim-backend", "cpu", "--device", "cuda"], True, ("cpu", "cuda:0")),
    (["--sim-backend", "cpu", "--device", "cpu"], True, ("cpu", "cpu")),
    (["--device", "cpu"], True, ("cpu", "cpu")),
    (["--smoke"], True, ("cpu", "cpu")),
    (["--smoke", "--device", "cuda"], True, ("cpu", "cuda:0")),
    (["--smoke", "--sim-backend", "cpu", "--device", "cuda"], True, ("cpu", "cuda:0")),
    (["--sim-backend", "gpu", "--device", "cpu"], True, "--sim-backend gpu needs --device cuda"),
    (["--sim-backend", "gpu"], False, "--sim-backend gpu needs --device cuda"),
    (["--device", "cuda"], False, "needs a CUDA GPU"),
    (["--sim-backend", "cpu", "--device", "cuda"], False, "needs a CUDA GPU"),
    (["--smoke", "--sim-backend", "gpu", "--device", "cuda"], True, "--smoke is a CPU-sim configuration"),
    (["--sim-backend", "physx_cuda"], True, "argument --sim-backend: invalid choice"),
]


@pytest.mark.parametrize("example", ["ppo", "sac", "bc"])
@pytest.mark.parametrize(("flags", "cuda", "expected"), DEVICE_FLAGS)
def test_device_flags(example, flags, cuda, expected, monkeypatch, capsys) -> None:
    """``--sim-backend`` x ``--device`` in PPO, SAC and BC, on a machine with CUDA and on one without
    (``torch.cuda`` patched either way: the result never depends on this machine)."""
    _fake_cuda(monkeypatch, cuda)
    module = EXAMPLE_MODULES[example]
    if isinstance(expected, dict):
        expected = expected[example]
    if isinstance(expected, str):
        with pytest.raises(SystemExit) as exc:
            module.parse_args(flags)
        assert exc.value.code == 2
        assert expected in capsys.readouterr().err
        return
    args = module.parse_args(flags)
    assert (args.sim_backend, args.device) == expected
    if example == "ppo":  # the defaults follow the simulator, not the learner's device
        assert args.num_envs == (512 if args.sim_backend == "gpu" else 2)
    if example == "sac":
        assert args.num_envs == (2 if args.smoke else 32 if args.sim_backend == "gpu" else 4)


class _Recorder:
    """Stands in for ``make_pipeline`` / ``ParallelEnv`` / ``SerialEnv``: records the call, builds nothing
    (PPO's ``--bootstrap-at-done never``: no env to wrap in its ``IgnoreTerminations``)."""

    def __init__(self) -> None:
        self.calls: list[tuple[tuple, dict]] = []

    def __call__(self, *args, **kwargs):
        self.calls.append((args, kwargs))
        return self


@pytest.mark.parametrize("example", ["ppo", "sac"])
@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        (["--sim-backend", "cpu", "--device", "cuda"], ("cpu", "cuda:0")),
        (["--device", "cuda"], ("gpu", "cuda:0")),
        (["--device", "cpu"], ("cpu", "cpu")),
    ],
)
def test_training_env_is_made_on_the_learners_device(example, flags, expected, monkeypatch) -> None:
    """The training env gets the resolved ``sim_backend`` and ``device=<--device>``: with the CPU sim and a
    GPU learner, batches arrive on the GPU (the env moves them, not the collector)."""
    import torch

    _fake_cuda(monkeypatch, True)
    module = EXAMPLE_MODULES[example]
    record = _Recorder()
    monkeypatch.setattr(module, "make_pipeline", record)
    module.make_env(module.parse_args(flags + (["--bootstrap-at-done", "never"] if example == "ppo" else [])))
    ((_, kwargs),) = record.calls
    assert (kwargs["sim_backend"], kwargs["device"]) == (expected[0], torch.device(expected[1]))


@pytest.mark.parametrize("vec", ["parallel", "serial"])
def test_ppo_cpu_workers_hand_over_on_the_learners_device(vec, monkeypatch) -> None:
    """``--vec parallel / serial`` with a GPU learner: the workers stay on the CPU sim, the batched env
    is on the learner's device."""
    _fake_cuda(monkeypatch, True)
    record = _Recorder()
    monkeypatch.setattr(ppo_torchrl, "ParallelEnv" if vec == "parallel" else "SerialEnv", record)
    flags = ["--sim-backend", "cpu", "--device", "cuda", "--vec", vec, "--bootstrap-at-done", "never"]
    ppo_torchrl.make_env(ppo_torchrl.parse_args(flags))
    ((args, kwargs),) = record.calls
    assert kwargs["device"] == "cuda:0"
    worker = args[1]  # functools.partial(make_cpu_env, ...): the CPU sim, on the CPU
    assert worker.func is ppo_torchrl.make_cpu_env


@pytest.mark.parametrize(
    ("sim_backend", "device", "expected"),
    [("auto", "cpu", ("cpu", "cpu")), ("auto", "cuda:0", ("gpu", "cuda:0")), ("cpu", "cuda:0", ("cpu", "cuda:0"))],
)
def test_eval_env_follows_the_same_rule(sim_backend, device, expected, monkeypatch) -> None:
    """``evaluation.make_eval_env`` (PPO's, SAC's, BC's and ``evaluate_gym.py``'s) resolves as the flags do."""
    import torch

    record = _Recorder()
    monkeypatch.setattr(evaluation, "make_pipeline", record)
    evaluation.make_eval_env("PushCube-v1", 2, torch.device(device), 1, sim_backend=sim_backend)
    ((_, kwargs),) = record.calls
    assert (kwargs["sim_backend"], kwargs["device"]) == (expected[0], torch.device(expected[1]))
    assert kwargs["ignore_terminations"] is True
