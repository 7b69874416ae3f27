"""Evaluating a PPO checkpoint: ``examples/evaluate_gym.py --checkpoint`` and ``examples/ppo_checkpoint.py``.

The checkpoint is a tiny one (hidden 32) written in ``ppo_torchrl.py``'s format
from ``ppo_torchrl.make_models``, with a last layer that gives large actions, so
that episodes differ; training one with ``ppo_torchrl.py`` would cost ~30 s more
(``test_examples.py::test_ppo_smoke`` runs the trainer). The two backends run side by
side: gym's as a subprocess, TorchRL's in this process (2 sim envs each); the checks of
bad checkpoints run in-process, where nothing builds a simulator.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from torch import nn

import evaluate_gym
import ppo_checkpoint
from ppo_checkpoint import CheckpointError, check_sizes, load_checkpoint, policy_from_checkpoint
from ppo_torchrl import CHECKPOINT_FORMAT, make_models
from support.helpers import EXAMPLES, start

ENV_ID, CONTROL_MODE, OBS_DIM, ACT_DIM, HIDDEN = "PushCube-v1", "pd_joint_delta_pos", 35, 8, 32


def specs(obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM):
    box = gym.spaces.Box
    return ppo_checkpoint.specs_from_spaces(box(-float("inf"), float("inf"), (obs_dim,)), box(-1.0, 1.0, (act_dim,)))


def checkpoint_dict(**overrides) -> dict:
    """What ``ppo_torchrl.train`` saves, for PushCube-v1 state / pd_joint_delta_pos."""
    torch.manual_seed(0)
    policy, value = make_models(specs(), HIDDEN, torch.device("cpu"))
    last = [m for m in policy.modules() if isinstance(m, nn.Linear)][-1]
    nn.init.normal_(last.weight, std=0.5)  # large actions: episodes that differ from seed to seed
    ckpt = {
        "format": CHECKPOINT_FORMAT,
        "env_id": ENV_ID,
        "obs_mode": "state",
        "control_mode": CONTROL_MODE,
        "obs_dim": OBS_DIM,
        "act_dim": ACT_DIM,
        "hidden": HIDDEN,
        "repeat": 1,
        "policy": policy.state_dict(),
        "value": value.state_dict(),
        "args": {"env_id": ENV_ID, "hidden": HIDDEN},
        "frames": 0,
    }
    ckpt.update(overrides)
    return ckpt


@pytest.fixture(scope="module")
def ckpt_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ckpt") / "ppo_checkpoint.pt"
    torch.save(checkpoint_dict(), path)
    return path


# --------------------------------------------------------------------- end to end
def test_gym_and_torchrl_backends_agree_and_video(ckpt_path: Path, tmp_path: Path, capsys) -> None:
    """3 seeded episodes (2 envs: a full round and a partial one) through both backends at once: gym's
    as a user runs it (a subprocess, with a video), TorchRL's in this process meanwhile (its ``main``)."""
    args = ["--checkpoint", str(ckpt_path), "--num-envs", "2", "--episodes", "3", "--max-episode-steps", "8"]
    args += ["--seed", "5"]
    video = tmp_path / "eval.mp4"
    gym_cmd = [sys.executable, str(EXAMPLES / "evaluate_gym.py"), *args, "--video", str(video), "--video-episodes", "2"]
    gym_run = start(gym_cmd, tmp_path)
    capsys.readouterr()
    threads = torch.get_num_threads()
    try:
        code = evaluate_gym.main([*args, "--backend", "torchrl"])
    finally:
        torch.set_num_threads(threads)  # main sets one thread
        gym_out = gym_run.result().stdout
    torchrl_out = capsys.readouterr().out
    assert code == 0, torchrl_out

    assert f"{ENV_ID}, control mode {CONTROL_MODE}, repeat 1" in gym_out
    lines = [line for line in gym_out.splitlines() if line.startswith("episode ")]
    assert len(lines) == 3, gym_out
    for line, (env, seed) in zip(lines, [(0, 5), (1, 6), (0, 7)]):
        assert f"(env {env}, seed {seed})" in line
        assert "success_once=" in line and "success_at_end=" in line and "return=" in line
        assert "episode_len=8" in line  # terminations ignored: to the time limit
    returns = [float(re.search(r"return=(\S+)", line).group(1)) for line in lines]
    assert len(set(returns)) == 3, returns  # really different episodes

    def averages(text: str) -> dict[str, str]:
        return dict(re.findall(r"^avg (\w+): (\S+)$", text, re.M))

    gym_avg, torchrl_avg = averages(gym_out), averages(torchrl_out)
    assert "episodes: 3" in gym_out and "episodes: 3" in torchrl_out, torchrl_out
    # Same seeds, observations and network at the same batch size: the same numbers, to the printed digit.
    for key in ("success_once", "success_at_end", "return"):
        assert gym_avg[key] == torchrl_avg[key], (key, gym_out, torchrl_out)

    assert "video: " in gym_out and "(2 episodes, 18 frames, 20 fps)" in gym_out, gym_out
    import imageio.v2 as imageio

    reader = imageio.get_reader(video)
    frames = list(reader.iter_data())  # not list(reader): its len() is inf for ffmpeg streams
    reader.close()
    assert len(frames) == 2 * (8 + 1)  # per episode: the reset frame + one per step
    assert frames[0].ndim == 3 and frames[0].shape[-1] == 3 and frames[0].std() > 0


# ----------------------------------------------------------------- bad checkpoints
def _write(tmp_path: Path, obj) -> Path:
    path = tmp_path / "ppo_checkpoint.pt"
    torch.save(obj, path)
    return path


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: d / "nope.pt", "not found: pass the ppo_checkpoint.pt"),
        (lambda d: d, "has no ppo_checkpoint.pt"),  # a folder without one
        (lambda d: (d / "x.pt").write_text("not a checkpoint") and d / "x.pt", "is not a PyTorch checkpoint"),
        (lambda d: _write(d, torch.zeros(3)), "is not a maniskill_torchrl PPO checkpoint (a Tensor"),
        (lambda d: _write(d, checkpoint_dict()["policy"]), "a dict without a 'format' key"),
        (lambda d: _write(d, checkpoint_dict(format="other.v3")), "has checkpoint format 'other.v3'"),
        (lambda d: _write(d, {k: v for k, v in checkpoint_dict().items() if k != "hidden"}), "missing hidden"),
        (lambda d: _write(d, checkpoint_dict(obs_mode="rgb")), "obs_mode 'rgb'"),
    ],
    ids=["missing", "folder", "not-torch", "tensor", "no-format", "other-format", "incomplete", "rgb"],
)
def test_bad_checkpoint_messages(tmp_path: Path, make, message: str) -> None:
    path = make(tmp_path)
    with pytest.raises(CheckpointError) as exc:
        load_checkpoint(path)
    assert message in str(exc.value)


def test_folder_and_env_id(ckpt_path: Path) -> None:
    assert load_checkpoint(ckpt_path.parent)["path"] == str(ckpt_path)  # the --out folder works too
    assert load_checkpoint(ckpt_path, ENV_ID)["env_id"] == ENV_ID
    with pytest.raises(
        CheckpointError,
        match="was trained on PushCube-v1, not on --env-id PickCube-v1: "
        "a policy only acts on its own task. Drop --env-id",
    ):
        load_checkpoint(ckpt_path, "PickCube-v1")


def test_size_mismatches(ckpt_path: Path) -> None:
    ckpt = load_checkpoint(ckpt_path)
    with pytest.raises(CheckpointError, match=r"observation size mismatch: .* expects 35 state values .* gives 42"):
        policy_from_checkpoint(ckpt, specs(obs_dim=42))
    with pytest.raises(
        CheckpointError,
        match=r"action size mismatch: .* outputs 8 actions \(control mode "
        r"pd_joint_delta_pos\), the env built takes 4 \(control mode "
        r"pd_ee_delta_pos\). .* --control-mode pd_joint_delta_pos",
    ):
        policy_from_checkpoint(ckpt, specs(act_dim=4), "pd_ee_delta_pos")
    check_sizes(ckpt, OBS_DIM, ACT_DIM)  # matching sizes pass
    wrong_hidden = dict(ckpt, hidden=HIDDEN * 2)  # metadata that does not fit the weights
    with pytest.raises(CheckpointError, match="policy weights in .* do not fit the actor"):
        policy_from_checkpoint(wrong_hidden, specs())


def test_policy_is_deterministic_tanh_of_loc(ckpt_path: Path) -> None:
    """The gym backend's actions: the TanhNormal's tanh(loc) (bounds [-1, 1]), the same on every call."""
    policy = policy_from_checkpoint(load_checkpoint(ckpt_path), specs())
    act = ppo_checkpoint.numpy_policy(policy)
    obs = torch.randn(2, OBS_DIM).numpy()
    a = act(obs)
    assert a.shape == (2, ACT_DIM) and a.dtype == obs.dtype
    assert (act(obs) == a).all()
    loc = policy.module[0].module[0](torch.as_tensor(obs))
    assert torch.allclose(torch.as_tensor(a), torch.tanh(loc), atol=1e-6)


def test_cli_reports_bad_checkpoint(tmp_path: Path, capsys) -> None:
    """The script prints the message (exit 2) instead of a trace; no simulator is built."""
    assert evaluate_gym.main(["--checkpoint", str(tmp_path / "missing.pt")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evaluate_gym.py: error: checkpoint ") and "not found" in err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--backend", "torchrl"], "--backend torchrl evaluates a checkpoint: pass --checkpoint PATH"),
        (["--video", "v.mp4"], "--video records a checkpoint's policy: pass --checkpoint PATH"),
        (["--checkpoint", "c.pt", "--backend", "torchrl", "--video", "v.mp4"], "drop --backend torchrl"),
        (["--checkpoint", "c.pt", "--video-episodes", "0"], "--video-episodes must be >= 1"),
    ],
)
def test_bad_flags(argv: list[str], message: str, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        evaluate_gym.parse_args(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


# ----------------------------------------------------------------- SAC checkpoints
def test_sac_checkpoint_evaluates(tmp_path: Path, capsys) -> None:
    """``sac_torchrl.save_checkpoint``'s file: found in its folder, rebuilt as SAC's actor (state-dependent
    scale) with the saved weights, deterministic tanh(loc); the CLI's ``main`` evaluates it on seeded
    episodes (in this process: the subprocess runs are above)."""
    import sac_torchrl

    torch.manual_seed(0)
    env = specs()
    actor, qnet = sac_torchrl.make_models(OBS_DIM, env.action_spec_unbatched, HIDDEN, torch.device("cpu"))
    loss, _, _ = sac_torchrl.make_objective(sac_torchrl.parse_args(["--device", "cpu"]), actor, qnet)
    args = sac_torchrl.parse_args(["--device", "cpu", "--env-id", ENV_ID, "--hidden", str(HIDDEN)])
    sac_torchrl.save_checkpoint(tmp_path / "sac_checkpoint.pt", args, env, actor, loss, frames=0)

    ckpt = load_checkpoint(tmp_path)  # the --out folder
    policy = policy_from_checkpoint(ckpt, specs())
    obs = torch.randn(3, OBS_DIM)
    a = ppo_checkpoint.numpy_policy(policy)(obs.numpy())
    loc = actor.module[0].module[0](obs).chunk(2, -1)[0]  # the saved actor's mean, before the tanh
    assert torch.allclose(torch.as_tensor(a), torch.tanh(loc), atol=1e-6)

    capsys.readouterr()
    threads = torch.get_num_threads()
    try:
        code = evaluate_gym.main(
            ["--checkpoint", str(tmp_path), "--num-envs", "1", "--episodes", "2", "--max-episode-steps", "5"]
            + ["--seed", "3"]
        )
    finally:
        torch.set_num_threads(threads)  # main sets one thread
    out = capsys.readouterr().out
    assert code == 0, out
    assert "episodes: 2" in out and re.search(r"^avg success_once: \S+$", out, re.M), out
