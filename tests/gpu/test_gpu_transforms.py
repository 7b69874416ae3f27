"""ActionRepeat and EpisodeMetrics on ManiSkill's GPU sim (num_envs=512) against ManiSkill's own
GPU wrappers, per env.

Both run ManiSkill's wrapper on the real GPU sim over a :class:`~gpu_helpers.Recorder`, then
the library's transform over a :class:`~gpu_helpers.Replay` of the very same inner steps
(see gpu_helpers: ManiSkill's GPU sim does not promise reproducible runs).

- ``ActionRepeat(k)`` vs ``mani_skill.utils.wrappers.ActionRepeatWrapper(env, k)``, with the
  resets ManiSkillEnv makes (full seeded / partial ``env_idx``), k in 2, 3: observations,
  reward, terminated / truncated / done and every info, per env, ``torch.equal``; both also
  equal a per-env reference built from the recorded inner steps (reward summed over the
  steps the env really took, flags OR'ed, everything else from its last real step). The replay
  checks that ours made the same inner-step and reset calls (same count, actions, seeds, env_idx).

  ManiSkill's known ``elapsed_steps`` aliasing: on the CPU sim ``get_info()`` returns the env's
  in-place step counter itself, so the info dict of ``ActionRepeatWrapper`` holds a reference
  to that counter: after the call it reads the counter's current value (every inner step
  taken, also past an env's end), and it keeps changing with later steps (callers must clone).
  On the GPU sim ``get_info()`` returns a clone and the wrapper's value is the one at the env's
  last real step, like ours. The test accepts ManiSkill's value where it equals the live
  counter instead of that reference (and reports how often); ours must equal the reference.

- ``IgnoreTerminations() + EpisodeMetrics()`` vs ``ManiSkillVectorEnv(env,
  ignore_terminations=True, record_metrics=True)``: at every step, ``info["episode"]`` (or
  ``info["final_info"]["episode"]`` where an episode ended) against ours:
  ``success_once`` / ``success_at_end`` / ``fail_once`` / ``fail_at_end`` and ``episode_len``
  equal; ``return`` and ``reward`` (= return / length) equal bit for bit: on the GPU sim
  EpisodeMetrics keeps ManiSkillVectorEnv's running float32 sum (``summation="running"``, its
  default off the CPU). On the CPU check of the test code it sums in numpy's order instead, and
  must equal ``numpy.sum`` of the recorded rewards exactly.

Skipped without CUDA (``python3 scripts/gpu_check.py`` runs them on an accelerator machine).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from mani_skill.utils.wrappers import ActionRepeatWrapper
from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv
from torchrl.envs import Compose, TransformedEnv

from gpu_helpers import (
    NUM_ENVS,
    SEED,
    TASKS,
    Recorder,
    Replay,
    actions,
    info_key,
    needs_one_gym_env,
    requires_gpu,
    seeds_after_set_seed,
    shared_env,
    swapped,
)
from maniskill_torchrl import ActionRepeat, EpisodeMetrics, IgnoreTerminations
from support.helpers import assert_same, clone_tree, tensor_infos

pytestmark = requires_gpu


def _where(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b)


def _reference(inner: list[tuple]) -> dict:
    """Per env, from the recorded inner steps of one outer step: what an action repeat must report."""
    obs, reward, terminated, truncated, info = clone_tree(inner[0][2])
    info = tensor_infos(info)
    running = ~(terminated | truncated)
    for _, _, (o, r, te, tr, inf) in inner[1:]:
        obs = _where(running, o, obs)
        reward = torch.where(running, reward + r, reward)
        terminated = torch.where(running, terminated | te, terminated)
        truncated = torch.where(running, truncated | tr, truncated)
        info = {k: _where(running, v, info[k]) for k, v in tensor_infos(inf).items()}
        running = running & ~(te | tr)
    return dict(obs=obs, reward=reward, terminated=terminated, truncated=truncated, info=info)


@pytest.mark.parametrize(
    "task, repeat", [("PushCube-v1", 3), ("MS-CartpoleBalance-v1", 2), ("MS-CartpoleBalance-v1", 3)]
)
def test_action_repeat_equals_maniskill_wrapper(task, repeat):
    needs_one_gym_env()
    env = shared_env(task)
    raw = env._env
    n_outer = 2 * TASKS[task] // repeat + 2  # two episodes at least
    acts = actions(env.unwrapped.single_action_space, env.device, n_outer, seed=10 + repeat)

    # 1. ManiSkill's ActionRepeatWrapper on the GPU sim, with ManiSkillEnv's reset rule.
    recorder = Recorder(raw)
    oracle = ActionRepeatWrapper(recorder, repeat)
    seeds = iter(seeds_after_set_seed(SEED, n_outer + 2))
    oracle.reset(seed=next(seeds))
    theirs, inner_steps = [], []
    for a in acts:
        i0 = len(recorder.calls)
        out = oracle.step(a.clone())
        counter = env.unwrapped.elapsed_steps.clone()  # the live counter after this outer step
        theirs.append((clone_tree(out), counter))
        inner_steps.append(recorder.calls[i0:])
        _, _, terminated, truncated, _ = out
        done = terminated | truncated
        if done.all():
            oracle.reset(seed=next(seeds))
        elif done.any():
            oracle.reset(options={"env_idx": done.nonzero().squeeze(-1)})

    # 2. Ours on a replay of the same calls.
    ours = TransformedEnv(env, ActionRepeat(repeat))
    replay = Replay(raw, recorder.calls, strict=True)
    with swapped(env, replay):
        ours.set_seed(SEED)
        td = ours.reset()
        got = []
        for a in acts:
            td.set("action", a)
            td, td_next = ours.step_and_maybe_reset(td)
            got.append(td["next"])
            td = td_next
    assert replay.consumed, "ours made fewer inner steps or resets than ManiSkill's wrapper"

    aliased = early_ends = short_steps = 0
    for t, (nxt, ((obs, reward, terminated, truncated, info), counter), inner) in enumerate(
        zip(got, theirs, inner_steps)
    ):
        ref = _reference(inner)
        k = len([c for c in inner if c[0] == "step"])
        assert k == len(inner), f"outer step {t}: a reset inside the action repeat"
        # Theirs equals the per-env reference...
        assert_same(obs, ref["obs"], f"outer step {t}: ManiSkill's observation vs reference")
        assert_same(reward, ref["reward"], f"outer step {t}: ManiSkill's reward vs reference")
        assert_same(terminated, ref["terminated"], f"outer step {t}: ManiSkill's terminated")
        assert_same(truncated, ref["truncated"], f"outer step {t}: ManiSkill's truncated")
        for key, want in ref["info"].items():
            have = tensor_infos(info)[key]
            if key == "elapsed_steps" and not torch.equal(have, want):
                # The CPU sim's aliasing (module docstring): ManiSkill's value is the live counter.
                off = have != want
                assert_same(have[off], counter[off], f"outer step {t}: ManiSkill's elapsed_steps")
                aliased += int(off.sum())
                continue
            assert_same(have, want, f"outer step {t}: ManiSkill's info {key} vs reference")
        # ...and so does ours, every entry, per env.
        assert_same(nxt["observation"], ref["obs"], f"outer step {t}: observation")
        assert_same(nxt["reward"], ref["reward"].unsqueeze(-1), f"outer step {t}: reward")
        assert_same(nxt["terminated"], ref["terminated"].unsqueeze(-1), f"outer step {t}: terminated")
        assert_same(nxt["truncated"], ref["truncated"].unsqueeze(-1), f"outer step {t}: truncated")
        assert_same(nxt["done"], (ref["terminated"] | ref["truncated"]).unsqueeze(-1), f"outer step {t}: done")
        for key, want in ref["info"].items():
            assert_same(nxt[info_key(env, key)], want, f"outer step {t}: info {key}")
        # Envs whose episode ended before the batch's last inner step of this outer step (their
        # later inner steps are discarded), and outer steps cut short (every env ended).
        ended = torch.zeros_like(ref["terminated"])
        for _, _, (_, _, te, tr, _) in inner[:-1]:
            ended = ended | te | tr
        early_ends += int(ended.sum())
        short_steps += k < repeat
    print(
        f"{task} repeat={repeat}: {len(got)} outer steps, {sum(map(len, inner_steps))} inner steps, "
        f"{early_ends} env episodes ended before the batch's last inner step, {short_steps} outer "
        f"steps cut short, {aliased} elapsed_steps values aliased to ManiSkill's live counter"
    )
    if task == "PushCube-v1":  # the 11-step limit ends episodes mid-repeat
        assert short_steps + early_ends > 0, "episodes should end mid-repeat (the limit is no multiple of the repeat)"
    elif NUM_ENVS > 1:
        assert early_ends > 0, "Cartpole envs should fail at different inner steps (masked merge)"


@pytest.mark.parametrize("task", list(TASKS))
def test_episode_metrics_equal_maniskill_vector_env(task):
    needs_one_gym_env()
    env = shared_env(task)
    raw = env._env
    limit = TASKS[task]
    n_steps = 2 * limit + 3  # two full episodes and the start of a third
    acts = actions(env.unwrapped.single_action_space, env.device, n_steps, seed=20)

    # 1. ManiSkillVectorEnv's metrics on the GPU sim (it auto-resets ended episodes).
    recorder = Recorder(raw)
    vec = ManiSkillVectorEnv(recorder, ignore_terminations=True, record_metrics=True)
    try:
        vec.reset(seed=SEED)
        theirs = []
        for a in acts:
            _, _, _, _, info = vec.step(a)
            theirs.append(clone_tree(info["final_info"]["episode"] if "final_info" in info else info["episode"]))
    finally:
        vec.closed = True  # the env is shared: never let the vector env close it
    steps = [out for kind, _, out in recorder.calls if kind == "step"]
    assert len(steps) == n_steps

    # 2. Ours on a replay of the same steps (and of its resets: the same data, other reset arguments).
    ours = TransformedEnv(env, Compose(IgnoreTerminations(), EpisodeMetrics()))
    replay = Replay(raw, recorder.calls, strict=False)
    with swapped(env, replay):
        ours.set_seed(SEED)
        td = ours.reset()
        assert not any(v.any() for v in td["episode"].values())
        got = []
        for a in acts:
            td.set("action", a)
            td, td_next = ours.step_and_maybe_reset(td)
            got.append(td["next", "episode"].clone())
            td = td_next
    assert replay.consumed, "ours reset at other steps than ManiSkillVectorEnv"

    # numpy.sum of each env's rewards since its reset, 1-D float32 per env (CPUGymWrapper's sum).
    rewards = torch.stack([r for _, r, *_ in steps]).cpu().numpy().astype(np.float32)  # [T, N]
    start = np.zeros(rewards.shape[1], dtype=np.int64)
    longest = 0
    for t, (mine, ms) in enumerate(zip(got, theirs)):
        assert set(mine.keys()) == set(ms.keys()), (set(mine.keys()), set(ms.keys()))
        length = ms["episode_len"].to(torch.int64)
        assert_same(mine["episode_len"], length, f"step {t}: episode_len")
        for key in ("success_once", "success_at_end", "fail_once", "fail_at_end"):
            if key in ms.keys():
                assert_same(mine[key], ms[key], f"step {t}: {key}")
        expected = np.array(
            [np.sum(np.ascontiguousarray(rewards[start[i] : t + 1, i])) for i in range(rewards.shape[1])],
            dtype=np.float32,
        )
        if env.device.type == "cuda":  # the running float32 sum: ManiSkillVectorEnv's, bit for bit
            assert_same(mine["return"], ms["return"], f"step {t}: return")
            assert_same(mine["reward"], ms["reward"], f"step {t}: reward")
        else:  # the CPU check of this test's code: numpy's order, CPUGymWrapper's
            assert_same(mine["return"].cpu(), torch.from_numpy(expected), f"step {t}: return vs numpy.sum")
            torch.testing.assert_close(mine["return"], ms["return"], rtol=1e-5, atol=1e-5, msg=f"step {t}: return")
        longest = max(longest, int(length.max()))
        ended = (length == limit).cpu().numpy()
        start[ended] = t + 1
    assert longest == limit  # episodes ran to the time limit (terminations ignored)
    if task == "MS-CartpoleBalance-v1":
        assert any(bool(ep["fail_once"].any()) for ep in theirs), "Cartpole should fail in some envs"
