"""The SAC example's bootstrap targets on a batch from the library's env, against targets computed
from a raw ManiSkill loop: ``y = r + gamma * (1 - cut) * V(final observation)``.

The batch comes from ``make_env(num_envs=2, repeat=2)`` on MS-CartpoleBalance-v1 (the batched CPU
env, ``ActionRepeat``, TorchRL's partial resets): env 0 pushes the cart hard and its pole falls
every few steps (terminated), env 1 holds still and reaches the time limit (truncated). The raw
loop steps one ManiSkill env per sub-env with the same seeds and actions, repeating each action
and summing rewards until a done, and keeps the observation at the done.

- ``always`` (the example's setting: ``IgnoreTerminations``, ManiSkill's ``bootstrap_at_done``
  "always"): every target bootstraps, truncations and ignored terminations included.
- ``never`` (terminations kept): a termination cuts the bootstrap, a truncation does not.

``V`` is a fixed function of the observation (its sum), so a target computed from the reset
observation instead of the final one, or a truncation read as a termination, changes it.

Both sides pin the CPU sim: with CUDA there, ``sim_backend="auto"`` would make the library's
two-env batch a GPU-sim env, which a CPU loop does not reproduce bit for bit."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import sac_torchrl
from maniskill_torchrl.pipeline import make_env

TASK = "MS-CartpoleBalance-v1"
LIMIT = 12  # inner steps: with repeat 2, a truncation every 6 agent steps
REPEAT = 2
STEPS = 14
SEED = 5
ACTIONS = torch.stack([torch.full((STEPS, 1), 1.0), torch.zeros(STEPS, 1)])  # (env, step, act)


def value(obs: torch.Tensor) -> torch.Tensor:
    return obs.sum(-1, keepdim=True)


def raw_loop(actions: torch.Tensor, ignore_terminations: bool) -> list[dict[str, torch.Tensor]]:
    """One ManiSkill env per sub-env, stepped side by side: per agent step the summed reward, the
    flags and the observation at the step's end. Resets are seeded as the library documents
    (``ManiSkillWrapper``): ``SEED + i`` first, then each reset call draws ``d`` from
    ``numpy.random.RandomState(SEED)`` and sub-env ``i`` restarts with ``d + i``."""
    import mani_skill.envs  # noqa: F401  (registers the tasks)

    envs = [
        gym.make(TASK, num_envs=1, obs_mode="state", max_episode_steps=LIMIT, sim_backend="physx_cpu") for _ in actions
    ]
    rng = np.random.RandomState(SEED)
    out: list[dict[str, list]] = [
        {"reward": [], "terminated": [], "truncated": [], "next_obs": [], "obs": []} for _ in envs
    ]
    try:
        obs = [env.reset(seed=SEED + i)[0] for i, env in enumerate(envs)]
        for t in range(actions.shape[1]):
            done = []
            for i, env in enumerate(envs):
                out[i]["obs"].append(obs[i][0])
                reward = torch.zeros(1)
                for _ in range(REPEAT):
                    obs[i], r, term, trunc, _ = env.step(actions[i, t][None])
                    reward = reward + r.float()
                    term = term & ~torch.tensor(ignore_terminations)
                    if bool(term | trunc):
                        break
                out[i]["reward"].append(reward)
                out[i]["terminated"].append(term.reshape(1))
                out[i]["truncated"].append(trunc.reshape(1))
                out[i]["next_obs"].append(obs[i][0])
                done.append(bool(term | trunc))
            if any(done):
                d = int(rng.randint(2**31))
                for i, env in enumerate(envs):
                    if done[i]:
                        obs[i] = env.reset(seed=d + i)[0]
    finally:
        for env in envs:
            env.close()
    return [{k: torch.stack(v) for k, v in o.items()} for o in out]


class Replay:
    """Hands out ``ACTIONS[:, t]`` at the t-th call."""

    def __init__(self) -> None:
        self.t = 0

    def __call__(self, td):
        td.set("action", ACTIONS[:, self.t].clone())
        self.t += 1
        return td


@pytest.mark.parametrize("bootstrap", ["always", "never"])
def test_sac_targets_match_a_raw_maniskill_loop(bootstrap):
    always = bootstrap == "always"
    env = make_env(
        TASK,
        num_envs=2,
        repeat=REPEAT,
        ignore_terminations=always,
        metrics=False,
        sim_backend="cpu",  # not "auto": the GPU sim where CUDA is
        obs_mode="state",
        max_episode_steps=LIMIT,
    )
    try:
        env.set_seed(SEED)  # sub-env i: seed SEED + i
        batch = env.rollout(STEPS, Replay(), break_when_any_done=False)
        args = sac_torchrl.parse_args(["--device", "cpu"])
        actor, qnet = sac_torchrl.make_models(
            env.observation_spec["observation"].shape[-1], env.action_spec_unbatched, 32, torch.device("cpu")
        )
    finally:
        env.close()
    loss, _, _ = sac_torchrl.make_objective(args, actor, qnet)
    raw = raw_loop(ACTIONS, ignore_terminations=always)

    # The batch holds what the raw loop saw, final observations at the dones included.
    for i, r in enumerate(raw):
        torch.testing.assert_close(batch["observation"][i], r["obs"], rtol=0, atol=0)
        torch.testing.assert_close(batch["next", "observation"][i], r["next_obs"], rtol=0, atol=0)
        torch.testing.assert_close(batch["next", "reward"][i], r["reward"], rtol=0, atol=0)
        assert torch.equal(batch["next", "terminated"][i], r["terminated"])
        assert torch.equal(batch["next", "truncated"][i], r["truncated"])
    terminated = batch["next", "terminated"].squeeze(-1)
    truncated = batch["next", "truncated"].squeeze(-1)
    done = terminated | truncated
    assert truncated.any() and (~done).any()
    assert terminated.any() != always  # terminations only where they are kept
    if not always:
        assert (done[0] != done[1]).any()  # partial resets: one env resets while the other goes on

    # The example's value estimator (TD0, gamma 0.8) against y computed from the raw loop.
    batch.set(("next", loss.value_estimator.tensor_keys.value), value(batch["next", "observation"]))
    target = loss.value_estimator.value_estimate(batch)
    gamma = args.gamma
    for i, r in enumerate(raw):
        cut = r["terminated"].float()
        expected = r["reward"] + gamma * (1 - cut) * value(r["next_obs"])
        torch.testing.assert_close(target[i], expected)
    # A target from the reset observation at a done would differ: the check above can fail.
    reset_obs = batch["observation"][:, 1:][done[:, :-1]]
    assert not torch.allclose(value(reset_obs), value(batch["next", "observation"][:, :-1][done[:, :-1]]))
