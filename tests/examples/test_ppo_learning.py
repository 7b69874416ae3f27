"""A learning smoke that can fail: the PPO example's objective, optimised on one fixed batch of
real PushCube-v1 transitions, must lower both its critic loss and its clipped surrogate loss.
A wrong sign, a detached graph, a key the loss does not read or a dead optimiser breaks it.
Learning itself (success against frames) is a benchmark: benchmarks/RESULTS.md, "PPO"."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs import Compose
from torchrl.modules import ValueOperator

import ppo_torchrl
from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.transforms import IgnoreTerminations


def test_ppo_objective_falls_on_a_fixed_batch() -> None:
    args = ppo_torchrl.parse_args(["--device", "cpu", "--hidden", "64", "--lr", "1e-3"])
    torch.manual_seed(0)
    env = ManiSkillEnv("PushCube-v1", obs_mode="state", control_mode="pd_ee_delta_pos", max_episode_steps=25)
    try:
        policy, value = ppo_torchrl.make_models(env, args.hidden, torch.device("cpu"))
        env.set_seed(0)
        with torch.no_grad():
            batch = env.rollout(100, policy, break_when_any_done=False)  # 4 episodes, auto-reset
    finally:
        env.close()
    advantage, loss_module, optim = ppo_torchrl.make_objective(args, policy, value)
    with torch.no_grad():
        advantage(batch)  # fixed targets: the updates move the critic and ratio

    def losses() -> tuple[float, float]:
        out = loss_module(batch)
        return out["loss_objective"].item(), out["loss_critic"].item()

    objective0, critic0 = losses()
    for _ in range(40):
        out = loss_module(batch)
        optim.zero_grad()
        (out["loss_objective"] + out["loss_critic"]).backward()
        optim.step()
    objective1, critic1 = losses()
    assert critic1 < 0.5 * critic0, (critic0, critic1)
    # From ~0 (ratio 1, normalised advantages) towards -(1 + clip) * E|A|-ish: clearly lower.
    assert objective1 < objective0 - 0.05, (objective0, objective1)


def test_bootstrap_at_done_follows_maniskills_baseline() -> None:
    """``always`` (ManiSkill's PPO baseline): the training env ends with
    ``IgnoreTerminations(as_truncations=True)``, so a terminated step still bootstraps from the value
    of its final observation, delta = r + gamma * V(s_final) - V(s); ``never``: no such transform,
    delta = r - V(s). Steps that did not end an episode, and the lambda chain cut at the done, are the
    same either way."""
    torch.manual_seed(0)
    value = ValueOperator(nn.Linear(3, 1), in_keys=["observation"])
    ended = torch.tensor([[False], [True], [False], [False]])  # a success termination at step 1
    batch = TensorDict(
        {
            "observation": torch.randn(4, 3),
            "next": {
                "observation": torch.randn(4, 3),
                "reward": torch.rand(4, 1),
                "done": ended,
                "terminated": ended,
                "truncated": torch.zeros_like(ended),
            },
        },
        [4],
    )
    out = {}
    for mode in ("always", "never"):
        args = ppo_torchrl.parse_args(
            ["--device", "cpu", "--sim-backend", "cpu", "--num-envs", "1", "--bootstrap-at-done", mode]
        )
        env = ppo_torchrl.make_env(args)
        try:
            last = env.transform[-1] if isinstance(env.transform, Compose) else env.transform
            assert isinstance(last, IgnoreTerminations) == (mode == "always")
            # What the env hands over: the batch through its last transform, on stored data.
            b = last(batch.clone()) if isinstance(last, IgnoreTerminations) else batch.clone()
        finally:
            env.close()
        advantage, _, _ = ppo_torchrl.make_objective(args, value, value)  # only GAE is used: any actor will do
        with torch.no_grad():
            advantage(b)
        out[mode] = b
    assert torch.equal(out["always"]["next", "done"], ended)  # the episode still ends there
    with torch.no_grad():
        v_final = value.module(batch["next", "observation"][1])
    diff = out["always"]["advantage"] - out["never"]["advantage"]
    torch.testing.assert_close(diff[1], args.gamma * v_final)
    # Step 0 sees step 1's advantage through the lambda chain: it changes by gamma * lambda times as much.
    torch.testing.assert_close(diff[0], args.gamma * args.lmbda * args.gamma * v_final)
    torch.testing.assert_close(diff[2:], torch.zeros_like(diff[2:]))
