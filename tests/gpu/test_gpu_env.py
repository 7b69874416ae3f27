"""ManiSkillEnv on ManiSkill's GPU sim (num_envs=512): equal to a raw ManiSkill GPU loop with the
same seeds and actions, and partial resets through ``"_reset"`` touch only the masked envs.

Tasks: PushCube-v1 (episodes end together at the time limit: full, seeded resets) and
MS-CartpoleBalance-v1 (random actions make envs fail at different steps: partial resets).

- lockstep: ManiSkillEnv over a :class:`~gpu_helpers.Recorder`; every step's tensordict (root
  and ``"next"``) equals, with ``torch.equal``, what ManiSkill returned for that very call, the
  env received exactly our actions, and every reset is the one a raw loop makes (the next seed
  drawn from ``set_seed``'s, with ``options={"env_idx": done envs}`` for partial ones);
- independent instances: a fresh ``gym.make`` env driven by a plain loop and a fresh
  ManiSkillEnv, same seeds, same actions, same global torch seed: equal with ``torch.equal``.
  Should they differ, a second raw instance tells whether ManiSkill reproduces its own run; if it
  does not, the test says so and skips (ManiSkill does not promise reproducible GPU runs), else it fails;
- partial reset: after 4 steps, ``env.reset(td.set("_reset", mask))`` calls ManiSkill with
  exactly the masked ``env_idx``, leaves every entry of the other envs bit for bit, gives the
  masked envs ManiSkill's reset data, and the next step counts on from 4 for the others.

Skipped without CUDA (``python3 scripts/gpu_check.py`` runs them on an accelerator machine).
"""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import step_mdp

from gpu_helpers import (
    CUDA,
    NUM_ENVS,
    SEED,
    TASKS,
    Recorder,
    actions,
    env_idx_of,
    info_key,
    make_env,
    make_raw,
    requires_gpu,
    seeds_after_set_seed,
    shared_env,
    swapped,
)
from support.helpers import assert_same, clone_tree, tensor_infos

pytestmark = requires_gpu

# Steps per task: several PushCube episodes (11-step limit), several Cartpole failures.
N_STEPS = {"PushCube-v1": 3 * TASKS["PushCube-v1"] + 2, "MS-CartpoleBalance-v1": 40}
TORCH_SEED = 7  # the global torch RNG, set alike in both runs


def _merge(done: torch.Tensor, new, old):
    """Per env: ``new`` where done else ``old`` (what TorchRL's partial reset keeps)."""
    return torch.where(done.reshape(done.shape + (1,) * (new.ndim - 1)), new, old)


def _check_step(env, td, prev_obs, prev_info, out, t: int) -> None:
    """``td`` (one step of ManiSkillEnv: root = before, "next" = after) against ManiSkill's data."""
    obs, reward, terminated, truncated, info = out
    assert_same(td["observation"], prev_obs, f"step {t}: root observation")
    for key, value in tensor_infos(prev_info).items():
        assert_same(td[info_key(env, key)], value, f"step {t}: root info {key}")
    nxt = td["next"]
    assert_same(nxt["observation"], obs, f"step {t}: next observation")
    assert_same(nxt["reward"], reward.unsqueeze(-1), f"step {t}: reward")
    assert_same(nxt["terminated"], terminated.unsqueeze(-1), f"step {t}: terminated")
    assert_same(nxt["truncated"], truncated.unsqueeze(-1), f"step {t}: truncated")
    assert_same(nxt["done"], (terminated | truncated).unsqueeze(-1), f"step {t}: done")
    infos = tensor_infos(info)
    assert {"elapsed_steps"} <= set(infos)
    for key, value in infos.items():
        assert_same(nxt[info_key(env, key)], value, f"step {t}: info {key}")


def _run_torchrl(env, acts, seed: int) -> list:
    """ManiSkillEnv as a collector drives it: set_seed, reset, step_and_maybe_reset."""
    env.set_seed(seed)
    td = env.reset()
    steps = []
    for a in acts:
        td.set("action", a)
        td, td_next = env.step_and_maybe_reset(td)
        steps.append(td)  # kept as is: later steps must not change it (no aliasing)
        td = td_next
    return steps


@pytest.mark.parametrize("task", list(TASKS))
def test_lockstep_equal_to_maniskill_calls(task):
    env = shared_env(task)
    acts = actions(env.unwrapped.single_action_space, env.device, N_STEPS[task], seed=1)
    recorder = Recorder(env._env)
    with swapped(env, recorder):
        steps = _run_torchrl(env, acts, SEED)
    calls = recorder.calls

    kind, arg, (prev_obs, prev_info) = calls[0]
    assert kind == "reset" and arg["seed"] == SEED and env_idx_of(arg["options"]) is None
    seeds = iter(seeds_after_set_seed(SEED, len(acts) + 2)[1:])
    i, n_full, n_partial = 1, 0, 0
    for t, (td, a) in enumerate(zip(steps, acts)):
        kind, action, out = calls[i]
        i += 1
        assert kind == "step", f"step {t}: ManiSkill got a {kind} call"
        assert_same(action, a, f"step {t}: the action ManiSkill received")
        assert_same(td["action"], a, f"step {t}: td action")
        _check_step(env, td, prev_obs, prev_info, out, t)
        obs, _, terminated, truncated, info = out
        done = terminated | truncated
        prev_obs, prev_info = obs, tensor_infos(info)
        if not done.any():
            continue
        kind, arg, (reset_obs, reset_info) = calls[i]
        i += 1
        assert kind == "reset", f"step {t}: envs {done.nonzero().reshape(-1).tolist()[:8]} done, no reset"
        if done.all():
            assert arg["seed"] == next(seeds) and env_idx_of(arg["options"]) is None, f"step {t}: full reset {arg}"
            prev_obs, prev_info = reset_obs, tensor_infos(reset_info)
            n_full += 1
        else:
            # Seeded as full resets are (ManiSkill seeds torch's RNG only in a seeded reset).
            assert arg["seed"] == next(seeds), f"step {t}: partial reset seed {arg['seed']}"
            assert_same(env_idx_of(arg["options"]), done.nonzero().squeeze(-1), f"step {t}: env_idx")
            prev_obs = _merge(done, reset_obs, obs)
            prev_info = {k: _merge(done, v, prev_info[k]) for k, v in tensor_infos(reset_info).items()}
            n_partial += 1
    assert i == len(calls), f"{len(calls) - i} ManiSkill calls after the last step"
    print(f"{task}: {len(acts)} steps, {n_full} full (seeded) resets, {n_partial} partial resets")
    assert n_full + n_partial >= 2, "the rollout should span several episodes"
    if task == "MS-CartpoleBalance-v1" and NUM_ENVS > 1:
        assert n_partial >= 1, "Cartpole envs should fail at different steps (partial resets)"


def _raw_loop(genv, acts, seeds: list[int]) -> list[dict]:
    """A plain ManiSkill GPU loop with ManiSkillEnv's reset rule: all envs done -> reset(seed=next
    seed), some -> reset(seed=next seed, options={"env_idx": done}), keeping the others' observations."""
    seeds = iter(seeds)
    obs, info = genv.reset(seed=next(seeds))
    prev, prev_info = obs.clone(), clone_tree(tensor_infos(info))
    records = []
    for a in acts:
        obs, reward, terminated, truncated, info = genv.step(a)
        records.append(dict(prev=prev, prev_info=prev_info, out=clone_tree((obs, reward, terminated, truncated, info))))
        done = terminated | truncated
        prev, prev_info = obs.clone(), clone_tree(tensor_infos(info))
        if done.all():
            prev, reset_info = genv.reset(seed=next(seeds))
            prev, prev_info = prev.clone(), clone_tree(tensor_infos(reset_info))
        elif done.any():
            reset_obs, reset_info = genv.reset(seed=next(seeds), options={"env_idx": done.nonzero().squeeze(-1)})
            prev = _merge(done, reset_obs, prev)
            prev_info = {k: _merge(done, v, prev_info[k]) for k, v in tensor_infos(reset_info).items()}
    return records


def _first_difference(a: list[dict], b: list[dict]) -> str | None:
    for t, (ra, rb) in enumerate(zip(a, b)):
        for name, x, y in (
            ("obs", ra["out"][0], rb["out"][0]),
            ("reward", ra["out"][1], rb["out"][1]),
            ("prev", ra["prev"], rb["prev"]),
        ):
            if not torch.equal(x, y):
                n = int((x != y).reshape(x.shape[0], -1).any(-1).sum()) if x.ndim else 1
                return f"step {t} {name}: {n} envs differ (max abs diff {float((x - y).abs().max()):.3g})"
    return None


def _raw_run(task: str, n: int, seeds: list[int]):
    genv = make_raw(task)
    try:
        acts = actions(genv.unwrapped.single_action_space, genv.unwrapped.device, n, seed=2)
        torch.manual_seed(TORCH_SEED)
        return acts, _raw_loop(genv, acts, seeds)
    finally:
        genv.close()


@pytest.mark.parametrize("task", list(TASKS))
def test_equal_to_independent_raw_loop(task):
    n = N_STEPS[task]
    seeds = seeds_after_set_seed(SEED, n + 2)
    acts, raw_a = _raw_run(task, n, seeds)
    env = make_env(task)
    try:
        torch.manual_seed(TORCH_SEED)
        steps = _run_torchrl(env, acts, SEED)
        try:
            for t, (td, rec) in enumerate(zip(steps, raw_a)):
                _check_step(env, td, rec["prev"], rec["prev_info"], rec["out"], t)
            return
        except AssertionError as e:
            failure = e
    finally:
        env.close()
    # Ours differs from the raw run: is it ours, or does ManiSkill not reproduce its own run?
    _, raw_b = _raw_run(task, n, seeds)
    diff = _first_difference(raw_a, raw_b)
    if diff is not None:
        pytest.skip(
            f"ManiSkill's {'GPU' if CUDA else 'CPU'} sim did not reproduce its own run across two "
            f"instances ({diff}); test_lockstep_equal_to_maniskill_calls checks the wrapper instead"
        )
    raise failure


@pytest.mark.parametrize("task", list(TASKS))
def test_partial_reset_touches_only_masked_envs(task):
    if NUM_ENVS < 2:
        pytest.skip("a partial reset needs several envs (GPU sim)")
    env = shared_env(task)
    acts = actions(env.unwrapped.single_action_space, env.device, 5, seed=3)
    g = torch.Generator().manual_seed(0)
    mask = torch.rand(NUM_ENVS, generator=g) < 0.3
    mask[0], mask[-1] = True, False
    mask = mask.to(env.device)
    keep = ~mask
    recorder = Recorder(env._env)
    with swapped(env, recorder):
        td = env.reset(seed=5)
        for a in acts[:4]:
            td = step_mdp(env.step(td.set("action", a)))
        if td["done"].any():  # a Cartpole env may already have failed: reset those first
            td = env.reset(td.set("_reset", td["done"].clone()))
        before = td.clone()
        steps_before = before["elapsed_steps"].clone()
        n_calls = len(recorder.calls)
        out = env.reset(td.clone().set("_reset", mask.unsqueeze(-1)))
        after = out.clone()
        nxt = env.step(out.set("action", acts[4]))["next"]

    assert len(recorder.calls) == n_calls + 2  # one reset, one step
    kind, arg, (reset_obs, reset_info) = recorder.calls[n_calls]
    assert kind == "reset" and arg["seed"] is not None  # seeded from set_seed's draws
    assert_same(env_idx_of(arg["options"]), mask.nonzero().squeeze(-1), "env_idx passed to ManiSkill")

    assert "_reset" not in after.keys()
    # The envs not reset: every entry bit for bit as before the reset.
    for key in before.keys(True, True):
        assert_same(after[key][keep], before[key][keep], f"not-reset envs: {key}")
    # The reset envs: ManiSkill's reset data, fresh episodes.
    assert_same(after["observation"][mask], reset_obs[mask], "reset envs: observation")
    for key, value in tensor_infos(reset_info).items():
        assert_same(after[info_key(env, key)][mask], value[mask], f"reset envs: info {key}")
    assert (after["elapsed_steps"][mask] == 0).all()
    for key in ("done", "terminated", "truncated"):
        assert not after[key][mask].any(), key
    # ManiSkill left the other envs' simulation alone (its own partial-reset test allows 1e-4).
    assert torch.allclose(reset_obs[keep], before["observation"][keep], atol=1e-4)
    # And the batch steps on: the reset envs from 0, the others from where they were.
    assert_same(nxt["elapsed_steps"][mask], torch.ones_like(nxt["elapsed_steps"][mask]), "reset envs: steps")
    assert_same(nxt["elapsed_steps"][keep], steps_before[keep] + 1, "other envs: steps")
