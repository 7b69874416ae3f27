"""The scenarios ``bench_env.py`` times: ``ManiSkillEnv`` against a raw ManiSkill loop (CPU sim).

Each ``scenario_*`` builds its own env and contenders and returns their times
(:func:`common.interleave`; ``scenario_paired``: per-step CPU times); ``bench_env.py``'s
docstring describes each scenario, and its ``main`` prints the tables.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch

from benchmarks.common import Contender, interleave, make_actions

SEED = 0
#: Extra ``ManiSkillEnv`` keywords for every scenario (``bench_env.py --grad-mode``: ``inference_mode=False``).
ENV_KWARGS: dict = {}


def make_env(**kwargs):
    """The scenarios' ``ManiSkillEnv("PickCube-v1", obs_mode="state", ...)``."""
    from maniskill_torchrl import ManiSkillEnv

    return ManiSkillEnv("PickCube-v1", obs_mode="state", **kwargs, **ENV_KWARGS)


def raw_mode(env):
    """The grad mode the raw loop runs in: ``ManiSkillEnv``'s own (inference mode by default on the
    CPU sim), so that both sides do the same torch work and only the wrapper's cost differs (and
    the shared gym env's tensors stay usable by both)."""
    return torch.inference_mode if env.inference_mode else contextlib.nullcontext


def env_actions(env, n: int, seed: int = 0) -> list[torch.Tensor]:
    """``n`` uniform actions, each ``[1, *action_shape]`` float32, from the env's action bounds."""
    return make_actions(env.unwrapped.single_action_space, n, batch=(1,), seed=seed)


def step_contenders(env, actions, state) -> list[Contender]:
    """``ManiSkillEnv.step`` (td reused, ``td["action"]`` set each step) and ``step_and_maybe_reset``."""

    def setup_td():
        state["td"] = env.reset(seed=SEED)

    def run_step():
        td, step = state["td"], env.step
        for a in actions:
            td.set("action", a)
            step(td)
        return len(actions)

    def run_smr():
        td, smr = state["td"], env.step_and_maybe_reset
        for a in actions:
            td.set("action", a)
            _, td = smr(td)
        return len(actions)

    return [
        Contender("ManiSkillEnv.step", run_step, setup_td),
        Contender("step_and_maybe_reset", run_smr, setup_td),
    ]


def scenario_step(steps: int, rounds: int, warmup: int, verbose: bool, clock: str = "cpu"):
    env = make_env(max_episode_steps=10 * steps + 100)
    raw = env._env  # the gym env ManiSkillEnv made: same instance, same physics work
    actions = env_actions(raw, steps)
    state = {}

    mode = raw_mode(env)

    def setup_raw():
        with mode():
            raw.reset(seed=SEED)

    def run_raw():
        step = raw.step
        with mode():
            for a in actions:
                step(a)
        return len(actions)

    results = interleave(
        [
            Contender("raw", run_raw, setup_raw),
            *step_contenders(env, actions, state),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock=clock,
    )
    env.close()
    return results


def scenario_episodes(steps: int, rounds: int, warmup: int, verbose: bool, clock: str = "cpu"):
    env = make_env()  # 50-step episodes
    raw = env._env
    mode = raw_mode(env)
    actions = env_actions(raw, steps, seed=1)
    state = {}

    def setup_raw():
        state["rng"] = np.random.RandomState(SEED)
        state["rng"].randint(2**31)  # ManiSkillEnv uses the seed itself first, then draws
        with mode():
            raw.reset(seed=SEED)

    def run_raw():
        step, reset, rng = raw.step, raw.reset, state["rng"]
        with mode():
            for a in actions:
                _, _, term, trunc, _ = step(a)
                if (term | trunc).any():
                    reset(seed=int(rng.randint(2**31)))
        return len(actions)

    def setup_td():
        env.set_seed(SEED)
        state["td"] = env.reset()

    def run_smr():
        td, smr = state["td"], env.step_and_maybe_reset
        for a in actions:
            td.set("action", a)
            _, td = smr(td)
        return len(actions)

    results = interleave(
        [
            Contender("raw+reset", run_raw, setup_raw),
            Contender("step_and_maybe_reset", run_smr, setup_td),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock=clock,
    )
    env.close()
    return results


class _ReplayStub:
    """Stands in for the gym env: returns one recorded step output, does no work."""

    def __init__(self, env, out):
        self.unwrapped = env.unwrapped
        self._out = out

    def step(self, action):
        return self._out

    def reset(self, *, seed=None, options=None):
        return self._out[0], self._out[4]

    def render(self):
        raise NotImplementedError

    def close(self):
        pass


def scenario_overhead(steps: int, rounds: int, warmup: int, verbose: bool, clock: str = "cpu"):
    env = make_env(max_episode_steps=10 * steps + 100)
    real = env._env
    actions = env_actions(real, steps)
    real.reset(seed=SEED)
    stub = _ReplayStub(real, real.step(actions[0]))
    env._env = stub
    state = {}

    def run_raw():
        step = stub.step
        for a in actions:
            step(a)
        return len(actions)

    results = interleave(
        [
            Contender("stub", run_raw),
            *step_contenders(env, actions, state),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock=clock,
    )
    env._env = real
    env.close()
    return results


def scenario_worker(steps: int, rounds: int, warmup: int, verbose: bool, clock: str = "cpu"):
    """A ``ParallelEnv`` worker's ``step_and_maybe_reset`` on a stub (no physics), three ways:
    the batch-``[1]`` env, ``TransformedEnv(env, CPUUnbatch())`` and ``ManiSkillEnv(batch_size=[])``."""
    from torchrl.envs import TransformedEnv

    from maniskill_torchrl import CPUUnbatch

    limit = 10 * steps + 100
    builds = {
        "batch [1]": lambda: make_env(max_episode_steps=limit),
        "+ CPUUnbatch": lambda: TransformedEnv(make_env(max_episode_steps=limit), CPUUnbatch()),
        "batch_size=[]": lambda: make_env(max_episode_steps=limit, batch_size=[]),
    }
    contenders, closers = [], []
    for name, build in builds.items():
        env = build()
        wrapper = env.base_env if isinstance(env, TransformedEnv) else env
        real = wrapper._env
        actions = env_actions(real, steps)
        with raw_mode(wrapper)():
            real.reset(seed=SEED)
            stub = _ReplayStub(real, real.step(actions[0]))
        wrapper._env = stub
        if env.batch_size == ():
            actions = [a[0] for a in actions]
        state: dict = {}

        def setup(env=env, state=state):
            state["td"] = env.reset(seed=SEED)

        def run(env=env, actions=actions, state=state):
            td, smr = state["td"], env.step_and_maybe_reset
            for a in actions:
                td.set("action", a)
                _, td = smr(td)
            return len(actions)

        contenders.append(Contender(name, run, setup))
        closers.append((wrapper, real, env))
    results = interleave(contenders, rounds=rounds, warmup=warmup, verbose=verbose, clock=clock)
    for wrapper, real, env in closers:
        wrapper._env = real
        env.close()
    return results


def scenario_paired(steps: int, rounds: int, warmup: int):
    """Per-step alternation of raw / step / step_and_maybe_reset on one env, CPU time per step."""
    import statistics
    import time

    env = make_env(max_episode_steps=10 * steps + 100)
    raw = env._env
    actions = env_actions(raw, steps, seed=2)
    names = ["raw", "ManiSkillEnv.step", "step_and_maybe_reset"]
    mode = raw_mode(env)
    times = {n: [] for n in names}
    clock = time.process_time
    for r in range(warmup + rounds):
        td_step = env.reset(seed=SEED)
        td_smr = td_step.clone()
        for i, a in enumerate(actions):
            k = (i + r) % 3
            if k == 0:
                with mode():
                    t0 = clock()
                    raw.step(a)
                    dt = clock() - t0
            elif k == 1:
                td_step.set("action", a)
                t0 = clock()
                env.step(td_step)
                dt = clock() - t0
            else:
                td_smr.set("action", a)
                t0 = clock()
                _, td_smr = env.step_and_maybe_reset(td_smr)
                dt = clock() - t0
            if r >= warmup:
                times[names[k]].append(dt)
    env.close()
    return {
        n: {"median_s": statistics.median(v), "mean_s": statistics.fmean(v), "steps": len(v)} for n, v in times.items()
    }
