"""A many-core emulator: PickCube-v1 replayed from a recording, each step *sleeping* its recorded time.

On a machine with few cores, ``N`` real CPU sims share those cores, so no pipeline can show how it
would run with one core per sim. A sleeping env needs no core while it "steps": ``N`` of them on 2
cores behave as ``N`` sims on ``N`` cores would, and what saturates is what really needs a core
(the main process, each worker's own overhead). This task is that sleeping env.

``ReplayPickCube-v1`` is a ManiSkill task (a subclass of ``BaseEnv`` registered with ManiSkill's
``register_env``) that never builds a SAPIEN scene. Its outputs are those of the real
PickCube-v1 (``obs_mode="state"``, CPU sim, ``max_episode_steps=50``), recorded once by
``python -m benchmarks.record_replay`` into :data:`DATA` (20 seeded episodes of 50 steps with
seeded random actions; ``step_s``: each sim step's wall time, 3 passes over them):

- ``reset(seed=s)`` replays the episode recorded with seed ``s % 20`` (seeds 0-19 are the real
  episodes, bit for bit); ``reset()`` without a seed replays the recorded episode after the one this
  env last played (``(e + 1) % 20``; an env that has played none draws it from torch's global RNG,
  where ManiSkill's unseeded reset draws its episode). So every env goes on from its own offset, and
  ``N <= 20`` envs seeded ``s, s + 1, ...`` (gymnasium's and the library's rule) replay ``N``
  distinct episodes after every reset, as real envs do: their episodes differ even when they reset
  alike, since their actions differ, while the replay ignores its actions. (Drawn from torch's RNG,
  the episodes of workers forked from one process were all the same after their first
  auto-reset: gym's lockstep then waited on ``N`` copies of one episode's step times.) Past 20 envs
  some replay one episode at once;
- ``step(action)`` ignores the action and returns the recorded step: the observation, reward and
  info with the task's keys, shapes and dtypes (``[1, ...]`` torch tensors, as a ``num_envs=1``
  CPU-sim env), ``terminated`` from ``success`` as ``BaseEnv.step`` computes it, ``truncated``
  from ManiSkill's time-limit wrapper (``gym.make``'s, 50 steps). Stepped past the 50 recorded
  steps it repeats the last one;
- each ``step`` and ``reset`` lasts its recorded time (for each step, one of the 3 recorded
  passes, drawn from an RNG of its own, not torch's), scaled so that the mean step time is the
  target's: ``step_ms`` (a ``gym.make`` keyword) or else ``$MANISKILL_REPLAY_STEP_MS`` (read where
  the env is made, in the worker), a number of milliseconds or a name of :data:`TARGETS`; default
  ``"h200"``: the mean time per step with the resets counted in (one per 50 steps), as a loop of
  steps and resets measures a machine's steps/s. The times are those of steps under
  :func:`torch.inference_mode` (the library's workers step so); a step taken with autograd's grad
  mode on (gymnasium's worker loop) lasts longer, as a real sim's does: ``grad_factor`` times, else
  ``$MANISKILL_REPLAY_GRAD_FACTOR``'s (read where the env is made), else :data:`GRAD_FACTOR`'s (the
  H200's); ``1`` drops it, and ``bench_many_cores`` measures it on its machine in the same run. The
  env's own work counts in that time: it sleeps what is left of it (:func:`time.sleep`, with
  Linux's timer slack at 1 ns in the sleeping thread).

Register it by importing this module; a process that has not can name it as
``"benchmarks.replay_task:ReplayPickCube-v1"`` (:data:`REPLAY_ID`), gymnasium's ``module:EnvId``
form: ``gym.make`` imports the module first, so a fresh worker process makes it as it makes a
ManiSkill task. That full string is registered too (for ``gym.spec`` and ManiSkill's registry).
All of these make it::

    gym.make(REPLAY_ID, num_envs=1, obs_mode="state")            # + CPUGymWrapper, AsyncVectorEnv
    ManiSkillEnv(REPLAY_ID, num_envs=16, obs_mode="state")        # the lockstep CPU engine
    ManiSkillAsyncEnvPool(REPLAY_ID, 16, repeat=2, obs_mode="state")

What it cannot model is in ``benchmarks/bench_many_cores.py``'s docstring.
"""

from __future__ import annotations

import copy
import ctypes
import json
import os
import sys
import threading
import time
from functools import cached_property
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector.utils import batch_space
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.registration import REGISTERED_ENVS, register_env

__all__ = [
    "DATA",
    "ENV_ID",
    "GRAD_FACTOR",
    "GRAD_FACTOR_ENV",
    "REPLAY_ID",
    "SPREAD_ENV",
    "STEP_MS_ENV",
    "TARGETS",
    "ReplayPickCube",
    "load_recording",
    "shrink_times",
    "target_step_s",
    "time_scale",
    "time_spread",
]

ENV_ID = "ReplayPickCube-v1"
REPLAY_ID = f"benchmarks.replay_task:{ENV_ID}"
DATA = Path(__file__).resolve().parent / "replay" / "pickcube_state.npz"
STEP_MS_ENV = "MANISKILL_REPLAY_STEP_MS"
SPREAD_ENV = "MANISKILL_REPLAY_SPREAD"
GRAD_FACTOR_ENV = "MANISKILL_REPLAY_GRAD_FACTOR"
#: Mean sim-step times (ms) of machines on record (benchmarks/RESULTS.md, DESIGN.md): the lent H200
#: host (2026-11-28), one raw PickCube-v1 env under inference mode (484 steps/s), and each of 15
#: independent ones together (5,623 steps/s for 15); ``"recorded"``: the recording's own times.
TARGETS = {"h200": 1000 / 484, "h200-loaded": 15 * 1000 / 5623, "recorded": None}
#: What a PickCube-v1 step costs in autograd's grad mode over inference mode (the H200 host: 484 steps/s
#: in inference mode, 386 in grad mode, 2026-11-28). The recording is in inference mode; a step taken
#: with grad enabled (gymnasium's worker loop) lasts this much longer, as a real sim's would.
GRAD_FACTOR = 484 / 386
DEFAULT_TARGET = "h200"
MAX_EPISODE_STEPS = 50

_RECORDING: dict[str, Any] | None = None


def load_recording(path: Path | str = DATA) -> dict[str, Any]:
    """The recording (:data:`DATA`): its arrays by name, ``meta`` (a dict) and ``info_keys``;
    loaded once per process."""
    global _RECORDING
    if _RECORDING is not None and _RECORDING["path"] == str(path):
        return _RECORDING
    with np.load(path) as f:
        rec = {k: f[k] for k in f.files}
    rec["meta"] = json.loads(str(rec.pop("meta")))
    rec["info_keys"] = rec["meta"]["info_keys"]
    rec["path"] = str(path)
    _RECORDING = rec
    return rec


def target_step_s(step_ms: float | str | None = None) -> float | None:
    """The target mean step time in seconds: ``step_ms``, else ``$MANISKILL_REPLAY_STEP_MS``, else
    :data:`DEFAULT_TARGET`; a number of milliseconds or a name of :data:`TARGETS` (None: the
    recorded times, unscaled)."""
    if step_ms is None:
        step_ms = os.environ.get(STEP_MS_ENV) or DEFAULT_TARGET
    if isinstance(step_ms, str):
        if step_ms in TARGETS:
            step_ms = TARGETS[step_ms]
        else:
            try:
                step_ms = float(step_ms)
            except ValueError:
                raise ValueError(
                    f"{ENV_ID}: step_ms={step_ms!r} is neither a number of milliseconds nor one of {sorted(TARGETS)}."
                ) from None
    if step_ms is None:
        return None
    if not step_ms > 0:
        raise ValueError(f"{ENV_ID}: step_ms must be positive, got {step_ms!r}.")
    return float(step_ms) / 1000.0


def time_scale(step_ms: float | str | None = None, recording: dict[str, Any] | None = None) -> float:
    """The factor on every recorded time for the target ``step_ms`` (:func:`target_step_s`): the
    target is the mean time per sim step with the resets counted in, one per episode of recorded
    steps, as a loop of steps and resets on a real machine measures its steps/s."""
    rec = recording if recording is not None else load_recording()
    target = target_step_s(step_ms)
    if target is None:
        return 1.0
    per_step = float(rec["step_s"].mean()) + float(rec["reset_s"].mean()) / rec["obs"].shape[1]
    return target / per_step


def time_spread(spread: float | str | None = None) -> float:
    """The spread of the step times: ``spread``, else ``$MANISKILL_REPLAY_SPREAD``, else 1 (as recorded)."""
    if spread is None:
        spread = os.environ.get(SPREAD_ENV) or 1.0
    spread = float(spread)
    if not 0.0 <= spread <= 1.0:
        raise ValueError(f"{ENV_ID}: spread must be within [0, 1], got {spread!r}.")
    return spread


def shrink_times(times: np.ndarray, spread: float) -> np.ndarray:
    """Each of ``times`` as ``mean + spread * (t - mean)``: the same mean, the spread shrunk."""
    mean = float(times.mean())
    return mean + spread * (times - mean)


_SLACK = threading.local()


def _fine_timer_slack() -> None:
    """Linux's timer slack (50 us by default: each sleep overshoots by about that) at 1 ns for the
    calling thread, once per thread."""
    if getattr(_SLACK, "set", False):
        return
    _SLACK.set = True
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None).prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK
        except (OSError, AttributeError):
            pass


class _Backend:
    """What ManiSkill's ``parse_sim_and_render_backend`` gives, for the CPU sim and no renderer."""

    device = torch.device("cpu")
    sim_backend = "physx_cpu"
    render_backend = "none"
    render_device = None
    sim_device = None


@register_env(ENV_ID, max_episode_steps=MAX_EPISODE_STEPS)
class ReplayPickCube(BaseEnv):
    """PickCube-v1 (``obs_mode="state"``, CPU sim) replayed from :data:`DATA`, each step sleeping its
    recorded time scaled to ``step_ms`` (module docstring). ``BaseEnv.__init__`` is not called: no
    SAPIEN scene, agent or renderer is made; the attributes that gym wrappers and the library read
    (``num_envs``, ``device``, spaces, ``gpu_sim_enabled``, ``get_info()``, ...) are set here."""

    SUPPORTED_OBS_MODES = ("state",)
    SUPPORTED_RENDER_MODES = ()
    metadata = {"render_modes": ()}

    def __init__(
        self,
        num_envs: int = 1,
        obs_mode: str | None = None,
        reward_mode: str | None = None,
        control_mode: str | None = None,
        render_mode: str | None = None,
        sim_backend: str = "auto",
        render_backend: str | None = "gpu",
        step_ms: float | str | None = None,
        spread: float | str | None = None,
        grad_factor: float | str | None = None,
        timing_seed: int | None = None,
        data: str | None = None,
    ) -> None:
        rec = load_recording(data or DATA)
        meta = rec["meta"]
        self._recording = rec
        checks = {
            "num_envs": (num_envs, 1, (1,)),
            "obs_mode": (obs_mode, meta["obs_mode"], (None, meta["obs_mode"])),
            "reward_mode": (reward_mode, meta["reward_mode"], (None, meta["reward_mode"])),
            "control_mode": (control_mode, meta["control_mode"], (None, meta["control_mode"])),
            "render_mode": (render_mode, None, (None,)),
            "sim_backend": (sim_backend, "physx_cpu", ("auto", "cpu", "physx_cpu")),
        }
        for name, (value, _, allowed) in checks.items():
            if value not in allowed:
                raise ValueError(
                    f"{ENV_ID} replays {meta['env_id']} as recorded ({name}={checks[name][1]!r}); got {name}={value!r}."
                )
        self.num_envs = 1
        self._obs_mode = meta["obs_mode"]
        self._reward_mode = meta["reward_mode"]
        self._control_mode_name = meta["control_mode"]
        self._sim_freq, self._control_freq = meta["sim_freq"], meta["control_freq"]
        self._sim_steps_per_control = self._sim_freq // self._control_freq
        self.render_mode = None
        self._viewer = None
        self.backend = _Backend()
        self.device = self.backend.device
        self.reconfiguration_freq = 0
        self._reconfig_counter = 0
        self._main_seed = [2022]
        self._elapsed_steps = torch.zeros(1, dtype=torch.int32)
        self._last_obs = None
        low, high = rec["action_low"], rec["action_high"]
        self.single_action_space = gym.spaces.Box(low, high, dtype=low.dtype)
        self.action_space = batch_space(self.single_action_space, n=1)
        self._orig_single_action_space = copy.deepcopy(self.single_action_space)
        # The step time: the recorded times scaled so that their mean is the target's.
        self._time_scale = time_scale(step_ms, rec)
        self._spread = time_spread(spread)
        # each recorded time t as mean + spread * (t - mean), then scaled: the same mean, its spread shrunk
        self._step_times = shrink_times(rec["step_s"], self._spread) * self._time_scale
        self._reset_times = shrink_times(rec["reset_s"], self._spread) * self._time_scale
        if grad_factor is None:
            grad_factor = os.environ.get(GRAD_FACTOR_ENV) or GRAD_FACTOR
        self._grad_factor = float(grad_factor)
        if not self._grad_factor > 0:
            raise ValueError(f"{ENV_ID}: grad_factor must be positive, got {grad_factor!r}.")
        self._timing = np.random.default_rng(timing_seed)
        #: seconds slept by this env (its steps and resets), and the sleeps' count
        self.slept_s, self.sleeps = 0.0, 0
        self._episode, self._step = 0, 0
        self._played = False  # whether this env has replayed an episode (its unseeded reset goes on from it)
        self._init_raw_obs = torch.from_numpy(rec["reset_obs"][0:1].copy())

    # ------------------------------------------------------------------ what wrappers read
    @property
    def gpu_sim_enabled(self) -> bool:
        return False

    @property
    def control_mode(self) -> str:
        return self._control_mode_name

    @property
    def time_scale(self) -> float:
        """The factor applied to every recorded time (target mean / recorded mean)."""
        return self._time_scale

    @property
    def episode(self) -> int:
        """The recorded episode being replayed (its seed is ``recording["seeds"][episode]``)."""
        return self._episode

    @cached_property
    def single_observation_space(self) -> gym.Space:
        space = self._recording["meta"]["single_observation_space"]
        return gym.spaces.Box(-np.inf, np.inf, tuple(space["shape"]), dtype=np.dtype(space["dtype"]))

    @cached_property
    def observation_space(self) -> gym.Space:
        return batch_space(self.single_observation_space, n=self.num_envs)

    # ------------------------------------------------------------------ the replay
    def evaluate(self) -> dict:
        """The recorded infos of the current step (the reset's before the first step)."""
        rec, e, k = self._recording, self._episode, self._step
        if k == 0:
            return {key: torch.from_numpy(rec["reset_info_" + key][e : e + 1].copy()) for key in rec["info_keys"]}
        k = min(k, rec["obs"].shape[1]) - 1
        return {key: torch.from_numpy(rec["info_" + key][e, k : k + 1].copy()) for key in rec["info_keys"]}

    def _sleep_until(self, t0: float, dt: float) -> None:
        """Sleeps what is left of ``dt`` seconds (times the grad factor in grad mode) since ``t0``."""
        if torch.is_grad_enabled() and not torch.is_inference_mode_enabled():
            dt *= self._grad_factor
        _fine_timer_slack()
        left = t0 + dt - time.perf_counter()
        if left > 0:
            time.sleep(left)
        self.slept_s += max(left, 0.0)
        self.sleeps += 1

    def _recorded_time(self, times: np.ndarray, *index: int) -> float:
        """One of the recorded passes' times (``times``: [passes, episodes, (steps)]) at ``index``, drawn."""
        return float(times[(int(self._timing.integers(times.shape[0])), *index)])

    def reset(self, seed: int | list[int] | None = None, options: dict | None = None):
        t0 = time.perf_counter()
        options = options or {}
        if "reset_to_env_states" in options:
            raise NotImplementedError(f"{ENV_ID} replays recorded episodes: it cannot reset to a saved state.")
        episodes = len(self._recording["seeds"])
        if seed is None and self._played:
            # the next recorded episode: each env goes on from its own offset (module docstring)
            self._episode = (self._episode + 1) % episodes
        elif seed is None:
            # ManiSkill's unseeded reset draws its episode from torch's global RNG.
            self._episode = int(torch.randint(episodes, ()).item())
        else:
            seed = int(seed[0]) if np.iterable(seed) else int(seed)
            self._episode = seed % episodes
            self._main_seed = [seed]
        self._step, self._played = 0, True
        self._elapsed_steps[:] = 0
        info = self.get_info()
        obs = torch.from_numpy(self._recording["reset_obs"][self._episode : self._episode + 1].copy())
        info["reconfigure"] = bool(options.get("reconfigure", False))
        self._last_obs = obs
        self._sleep_until(t0, self._recorded_time(self._reset_times, self._episode))
        return obs, info

    def step(self, action: Any):
        t0 = time.perf_counter()
        rec = self._recording
        steps = rec["obs"].shape[1]
        self._step += 1
        k = min(self._step, steps) - 1
        self._elapsed_steps += 1
        info = self.get_info()
        obs = torch.from_numpy(rec["obs"][self._episode, k : k + 1].copy())
        reward = torch.from_numpy(rec["reward"][self._episode, k : k + 1].copy())
        # BaseEnv.step's rule
        if "success" in info:
            terminated = torch.logical_or(info["success"], info["fail"]) if "fail" in info else info["success"].clone()
        else:
            terminated = info["fail"].clone() if "fail" in info else torch.zeros(1, dtype=torch.bool)
        self._last_obs = obs
        self._sleep_until(t0, self._recorded_time(self._step_times, self._episode, (self._step - 1) % steps))
        return obs, reward, terminated, torch.zeros(1, dtype=torch.bool), info

    def render(self):
        raise NotImplementedError(f"{ENV_ID} replays recorded states: it has no pictures to render.")

    def get_state_dict(self):
        raise NotImplementedError(f"{ENV_ID} replays recorded outputs: it has no sim state.")

    def close(self) -> None:
        pass


# The same task under its `module:EnvId` name: the id a process that has not imported this module
# passes (gym.make imports the module and then makes ENV_ID; gym.spec and ManiSkill's registry look
# the full string up).
if REPLAY_ID not in REGISTERED_ENVS:
    register_env(REPLAY_ID, max_episode_steps=MAX_EPISODE_STEPS)(ReplayPickCube)
