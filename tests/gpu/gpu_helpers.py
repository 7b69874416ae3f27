"""Shared pieces of the GPU checks (``tests/gpu``): ManiSkill GPU-sim envs, a recorder and a
replayer of a gym env's calls, exact comparisons, and a host-sync counter.

Why record and replay: ManiSkill's GPU sim does not promise bit-for-bit reproducible runs
(its own test suite skips seeded-reproducibility checks on the GPU), so comparing two
pipelines that each drive their own simulation could fail for reasons that are not ours.
Instead:

- :class:`Recorder` sits between a pipeline and the real ManiSkill env and keeps a clone of
  every ``reset`` / ``step`` call (arguments and outputs): ManiSkillEnv's output is compared
  with exactly what ManiSkill returned to it, call by call (lockstep);
- :class:`Replay` stands in for the ManiSkill env under a :class:`ManiSkillWrapper` and hands
  back recorded outputs, checking that the calls (actions, seeds, ``env_idx``) are the same:
  ManiSkill's own wrappers (``ActionRepeatWrapper``, ``ManiSkillVectorEnv``) run on the real
  GPU sim, and the library's transforms then see the very same per-step data.

Where two independent instances are compared (``test_gpu_env.py``), the test first checks that
two raw ManiSkill instances agree with each other, and skips (saying so) if they do not.

Set ``MANISKILL_TORCHRL_GPU_TESTS_ON_CPU=N`` to run these tests on the CPU sim with N envs (a
check of the test code itself, nothing about the GPU path; with N > 1 the tests that need one
ManiSkill gym env under ManiSkill's wrappers skip, and partial resets are seeded, as the
library's batched CPU env does).
"""

from __future__ import annotations

import contextlib
import os
import sysconfig
import traceback
import warnings
from collections import Counter

import gymnasium as gym
import mani_skill.envs  # noqa: F401  (registers the tasks)
import numpy as np
import pytest
import torch

from support.helpers import assert_same, clone_tree

CUDA = torch.cuda.is_available()
# A check of the test code itself on the CPU sim (nothing about the GPU path): N > 1 envs run as
# the library's batched CPU env (one process per env, sub-env 0 in this one), where the tests allow it.
CPU_ENVS = 0 if CUDA else int(os.environ.get("MANISKILL_TORCHRL_GPU_TESTS_ON_CPU", "0") or 0)
ON_CPU = CPU_ENVS > 0
RUN = CUDA or ON_CPU
SKIP_REASON = (
    "needs CUDA (ManiSkill's GPU sim): run `python3 scripts/gpu_check.py` on an accelerator machine "
    "(benchmarks/README.md, 'GPU kit')"
)
# Module marker for every test module here: skipped, not failed, without CUDA.
requires_gpu = pytest.mark.skipif(not RUN, reason=SKIP_REASON)

NUM_ENVS = 512 if CUDA else max(CPU_ENVS, 1)
SIM_BACKEND = "gpu" if CUDA else "physx_cpu"
SEED = 123
# Task -> episode limit: above 8 steps (numpy's pairwise sum switches to blocks of 8 there) and
# no multiple of 2 or 3 (ActionRepeat(2/3) ends episodes mid-repeat). Random actions make
# MS-CartpoleBalance-v1 fail (terminate) at different steps in different envs: partial resets.
TASKS = {"PushCube-v1": 11, "MS-CartpoleBalance-v1": 25}


def maniskill_kwargs(task: str) -> dict:
    return dict(obs_mode="state", sim_backend=SIM_BACKEND, max_episode_steps=TASKS[task])


def needs_one_gym_env() -> None:
    """Skips where the test needs one ManiSkill gym env of NUM_ENVS envs, which the CPU sim only
    makes for one env (the CPU check of the test code with N > 1)."""
    if not CUDA and NUM_ENVS > 1:
        pytest.skip("needs one ManiSkill gym env of several envs: the GPU sim")


def make_raw(task: str) -> gym.Env:
    """A ManiSkill env as users make it: ``gym.make(task, num_envs=NUM_ENVS, ...)``."""
    needs_one_gym_env()
    return gym.make(task, num_envs=NUM_ENVS, **maniskill_kwargs(task))


def make_env(task: str):
    """``ManiSkillEnv(task, num_envs=NUM_ENVS, sim_backend="gpu", obs_mode="state", ...)``."""
    from maniskill_torchrl import ManiSkillEnv

    return ManiSkillEnv(task, num_envs=NUM_ENVS, **maniskill_kwargs(task))


_SHARED: dict = {}


def shared_env(task: str):
    """One ManiSkillEnv per task for the whole session (a 512-env GPU scene takes seconds to
    build); every test seeds its resets and restores whatever it swaps in."""
    if task not in _SHARED:
        _SHARED[task] = make_env(task)
    return _SHARED[task]


def actions(space: gym.spaces.Box, device, n: int, seed: int) -> list[torch.Tensor]:
    """``n`` reproducible uniform actions ``[NUM_ENVS, *space.shape]`` float32 on ``device``
    (``space``: the task's ``single_action_space``)."""
    g = torch.Generator().manual_seed(seed)
    low = torch.as_tensor(space.low, dtype=torch.float32)
    high = torch.as_tensor(space.high, dtype=torch.float32)
    return [(low + (high - low) * torch.rand((NUM_ENVS, *space.shape), generator=g)).to(device) for _ in range(n)]


def seeds_after_set_seed(seed: int, n: int) -> list[int]:
    """The seeds of the first ``n`` full resets after ``env.set_seed(seed)``, as documented:
    ``seed`` itself, then draws of ``numpy.random.RandomState(seed).randint(2**31)``."""
    rng = np.random.RandomState(seed)
    return [seed] + [int(rng.randint(2**31)) for _ in range(n - 1)]


# ----------------------------------------------------------------------------- data


def info_key(env, key: str) -> str:
    """Where ManiSkillEnv stores info ``key`` (``info_<key>`` if it collides with an observation)."""
    return dict(env._info_map).get(key, key)


def env_idx_of(options) -> torch.Tensor | None:
    return (options or {}).get("env_idx")


# ----------------------------------------------------------------------------- record / replay
class Recorder(gym.Wrapper):
    """Passes every call through to ManiSkill and keeps a clone of it:
    ``("reset", {"seed", "options"}, (obs, info))`` or ``("step", action, (obs, reward,
    terminated, truncated, info))``. The caller gets ManiSkill's own objects, unchanged."""

    def __init__(self, env: gym.Env):
        if isinstance(env, gym.Env):
            super().__init__(env)
        else:  # the library's batched CPU env (CPU check of the test code): same API, no gym.Env
            self.env = env
            self._action_space = self._observation_space = self._metadata = self._cached_spec = None
        self.calls: list[tuple] = []

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.calls.append(("reset", {"seed": seed, "options": clone_tree(options)}, clone_tree((obs, info))))
        return obs, info

    def step(self, action):
        out = self.env.step(action)
        self.calls.append(("step", clone_tree(action), clone_tree(out)))
        return out


class Replay:
    """Stands in for the ManiSkill gym env under a ManiSkillWrapper (``env._env``): returns the
    recorded outputs, in order, as fresh clones. ``strict`` also checks each call's arguments
    (actions bit for bit, reset seeds and ``env_idx``); ``strict=False`` checks the call kind only."""

    def __init__(self, env: gym.Env, calls: list[tuple], strict: bool = True):
        self.unwrapped = env.unwrapped
        self._env = env
        self._calls = list(calls)
        self._i = 0
        self.strict = strict

    def _next(self, kind: str):
        assert self._i < len(self._calls), f"{kind} call #{self._i}: beyond the {len(self._calls)} recorded calls"
        got_kind, arg, out = self._calls[self._i]
        assert got_kind == kind, f"call #{self._i}: {kind}, but ManiSkill's pipeline made a {got_kind} call here"
        self._i += 1
        return arg, out

    def step(self, action):
        arg, out = self._next("step")
        if self.strict:
            assert_same(action, arg, f"action of call #{self._i - 1}")
        return clone_tree(out)

    def reset(self, *, seed=None, options=None):
        arg, out = self._next("reset")
        if self.strict:
            assert seed == arg["seed"], f"reset call #{self._i - 1}: seed {seed} != recorded {arg['seed']}"
            ours, theirs = env_idx_of(options), env_idx_of(arg["options"])
            assert (ours is None) == (theirs is None), f"reset call #{self._i - 1}: env_idx {ours} vs {theirs}"
            if ours is not None:
                assert_same(torch.as_tensor(ours), torch.as_tensor(theirs), f"env_idx of reset call #{self._i - 1}")
        return clone_tree(out)

    @property
    def consumed(self) -> bool:
        return self._i == len(self._calls)

    def get_wrapper_attr(self, name):
        return self._env.get_wrapper_attr(name)

    def render(self):
        raise NotImplementedError("Replay does not render")

    def close(self):
        pass


@contextlib.contextmanager
def swapped(env, stand_in):
    """Puts ``stand_in`` in place of the gym env under a ManiSkillWrapper, and back."""
    old = env._env
    env._env = stand_in
    try:
        yield stand_in
    finally:
        env._env = old


# ----------------------------------------------------------------------------- host syncs
def _prefix(module) -> str:
    return os.path.dirname(os.path.abspath(module.__file__)) + os.sep


def attribute_sync(stack: list[traceback.FrameSummary]) -> tuple[str, traceback.FrameSummary | None]:
    """Who made a host sync, and where: the innermost frame outside torch / tensordict / torchrl /
    the standard library decides: ``maniskill_torchrl`` (this library), ``mani_skill`` (ManiSkill
    or SAPIEN), else ``torchrl`` (TorchRL or tensordict code that the user's loop called; the
    deciding frame is then TorchRL's innermost one) or ``user`` (the example or test code)."""
    import mani_skill
    import sapien
    import tensordict
    import torchrl

    import maniskill_torchrl

    lib, ms = _prefix(maniskill_torchrl), (_prefix(mani_skill), _prefix(sapien))
    rl = (_prefix(torchrl), _prefix(tensordict))
    skip = (_prefix(torch), sysconfig.get_paths()["stdlib"] + os.sep)
    first_rl = None
    for frame in reversed(stack):
        f = frame.filename if frame.filename.startswith("<") else os.path.abspath(frame.filename)
        if f.startswith(lib):
            return "maniskill_torchrl", frame
        if f.startswith(ms):
            return "mani_skill", frame
        if f.startswith(rl):
            first_rl = first_rl or frame
            continue
        if f.startswith(skip) or f.startswith("<"):
            continue
        return ("torchrl", first_rl) if first_rl is not None else ("user", frame)
    return ("torchrl", first_rl) if first_rl is not None else ("user", None)


@contextlib.contextmanager
def count_host_syncs():
    """Counts the CUDA host syncs that torch sees (``torch.cuda.set_sync_debug_mode("warn")``:
    ``.item()``, ``bool(tensor)``, ``nonzero``, device-to-host copies...), each with the Python
    stack that made it. Yields a list of stacks; :func:`sync_counts` groups them by culprit.
    Syncs inside SAPIEN/PhysX's own CUDA code are invisible to torch and are not counted."""
    stacks: list[list[traceback.FrameSummary]] = []
    if not CUDA:
        yield stacks
        return
    previous = torch.cuda.get_sync_debug_mode()
    with warnings.catch_warnings():
        warnings.simplefilter("always")

        def hook(message, category, filename, lineno, file=None, line=None):
            if "synchroniz" in str(message):
                stacks.append(traceback.extract_stack()[:-1])

        warnings.showwarning = hook
        torch.cuda.set_sync_debug_mode("warn")
        try:
            yield stacks
        finally:
            torch.cuda.set_sync_debug_mode(previous)


def sync_counts(stacks) -> Counter:
    """Host syncs per culprit (see :func:`attribute_sync`)."""
    return Counter(attribute_sync(s)[0] for s in stacks)


def sync_sites(stacks, who: str, n: int = 5) -> list[str]:
    """The ``n`` most frequent call sites of the syncs attributed to ``who``."""
    sites = Counter()
    for s in stacks:
        culprit, frame = attribute_sync(s)
        if culprit == who and frame is not None:
            sites[f"{frame.filename}:{frame.lineno} {frame.line}"] += 1
    return [f"{c} x {site}" for site, c in sites.most_common(n)]
