"""The worker side of :class:`~maniskill_torchrl.CPUVectorEnv`.

Each worker process holds one ManiSkill CPU-sim env behind :class:`StepInObservation`, which packs
its whole step (observation, reward, flags, tensor infos) into one tree with ManiSkill's own
dtypes, and runs :func:`serve`: it waits on its pipe, steps with the action it reads from the
shared block (``_shared.py``) and writes its step into its own row there. A step crosses the pipe
as one byte each way; other calls (reset, call, close) as small pickles. :class:`MakeWorker` is
the picklable factory that builds the env in the worker (and the parent's own sub-env 0, which
writes its row the same way).

Like ``cpu_vector.py``, this module imports neither TorchRL nor the rest of the library beyond
``_internal``'s ManiSkill helpers and the step bytes (``_protocol.py``) when it loads: the workers import it,
and start faster without them. A worker told to repeat actions imports ``_repeat`` (the gym shim's
repeat step) then.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import sys
import traceback
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from maniskill_torchrl._internal.assets import no_asset_prompt
from maniskill_torchrl._internal.rendering import default_render_backend, make_maniskill, render_frame_shape
from maniskill_torchrl._internal.sim import maniskill_base_env, wrapper_attr
from maniskill_torchrl.engines._protocol import DONE, STEP, STEP_RESET

__all__ = [
    "OBS",
    "INFO",
    "REWARD",
    "TERMINATED",
    "TRUNCATED",
    "StepInObservation",
    "MakeWorker",
    "serve",
    "SUB_ENV_STATES",
    "join_states",
    "to_numpy",
    "zeros_tree",
]

# The entries of a worker's observation: its whole step.
OBS, INFO, REWARD, TERMINATED, TRUNCATED = "obs", "info", "reward", "terminated", "truncated"
# A reset option of the CPUVectorEnv's own: (sub-env indices being reset, their saved states, one row each).
SUB_ENV_STATES = "_sub_env_states"


def _numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return torch.empty((), dtype=dtype).numpy().dtype


def _info_space(infos: Mapping[str, Any]) -> gym.spaces.Dict:
    """Spaces for the per-env tensor infos of a one-env ManiSkill info dict (``[1, ...]`` tensors).

    The same entries as the adapter (``maniskill_torchrl.envs.maniskill``) declares:
    python values such as ``reconfigure`` are per-call metadata and are left out.
    """
    spaces: dict[str, gym.Space] = {}
    for key, value in infos.items():
        if isinstance(value, Mapping):
            sub = _info_space(value)
            if sub.spaces:
                spaces[key] = sub
        elif isinstance(value, torch.Tensor) and value.ndim >= 1 and value.shape[0] == 1:
            dtype = _numpy_dtype(value.dtype)
            if dtype == np.bool_:
                spaces[key] = gym.spaces.Box(0, 1, tuple(value.shape[1:]), dtype=np.bool_)
            else:
                spaces[key] = gym.spaces.Box(-np.inf, np.inf, tuple(value.shape[1:]), dtype=dtype)
    return gym.spaces.Dict(spaces)


def _select(infos: Mapping[str, Any], space: gym.spaces.Dict) -> dict:
    """The entries of ``infos`` that ``space`` declares, unbatched to numpy."""
    return {
        k: _select(infos[k], sub) if isinstance(sub, gym.spaces.Dict) else infos[k][0].cpu().numpy()
        for k, sub in space.spaces.items()
    }


def _unbatch(x: Any) -> Any:
    # .cpu(): on a CUDA machine ManiSkill's CPU sim renders with sapien_cuda, and its pictures come
    # back on the GPU (a copy to host memory; a no-op for the CPU tensors).
    if isinstance(x, torch.Tensor):
        return x[0].cpu().numpy()
    return {k: _unbatch(v) for k, v in x.items()}


def _batch(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x).unsqueeze(0)
    if isinstance(x, torch.Tensor):
        return x.unsqueeze(0)
    return {k: _batch(v) for k, v in x.items()}


class StepInObservation(gym.Wrapper):
    """Worker side: one ManiSkill CPU env whose whole step travels as one observation.

    The observation becomes ``{"obs", "info", "reward", "terminated", "truncated"}``,
    unbatched numpy with ManiSkill's dtypes, which the worker writes into its row of the shared
    block; ``step`` returns a dummy reward, dummy flags and an empty info dict (no per-step
    pickling of infos, no merging of info dicts in the parent). Actions arrive
    unbatched (numpy, or dicts of them) and reach ManiSkill as ``[1, ...]`` torch tensors,
    as a batched ManiSkill env expects them.

    :meth:`set_repeat` ``(k)`` makes each ``step`` the gym shim's
    :class:`~maniskill_torchrl.wrappers.ActionRepeatWrapper` step (ManiSkill's, bit for bit;
    ``maniskill_torchrl._repeat``, which both use, so no gym shim is imported here) on
    the env with its reward in float32: up to ``k`` steps in this worker, none after its
    episode's end, rewards summed in float32 as :class:`~maniskill_torchrl.transforms.ActionRepeat`
    sums them.

    Every call into the env runs under :func:`torch.inference_mode`: a ManiSkill step is
    hundreds of small torch ops, and inference mode skips autograd's bookkeeping for each
    (same values, less CPU). The sim's tensors become inference tensors, which is safe here
    because nothing but numpy copies leaves the worker.
    """

    def __init__(self, env: gym.Env, index: int = 0) -> None:
        super().__init__(env)
        self.index = index  # this sub-env's place in the CPUVectorEnv's batch
        base = maniskill_base_env(env)
        if base is None or base.num_envs != 1 or base.gpu_sim_enabled:
            raise ValueError("CPUVectorEnv workers hold one ManiSkill env on the CPU sim (num_envs=1).")
        self._info_space = _info_space(base.get_info())
        single_obs = wrapper_attr(env, "single_observation_space")
        self.observation_space = gym.spaces.Dict(
            {
                OBS: single_obs,
                INFO: self._info_space,
                REWARD: gym.spaces.Box(-np.inf, np.inf, (), dtype=np.float32),
                TERMINATED: gym.spaces.Box(0, 1, (), dtype=np.bool_),
                TRUNCATED: gym.spaces.Box(0, 1, (), dtype=np.bool_),
            }
        )
        self.action_space = wrapper_attr(env, "single_action_space")
        self._stepper: gym.Env = env  # what step() steps: the env, or its float32-reward view to repeat on
        self.repeat = 1
        self.trace = None  # a StepTrace (engines/_trace.py) this sub-env stamps, when the engine traces

    @torch.inference_mode()
    def set_repeat(self, repeat: int) -> None:
        """From the next ``step`` on, each action is applied up to ``repeat`` times (1: plain steps)."""
        if repeat == 1:
            self._stepper = self.env
        else:
            # The masked merge (tensordict, no TorchRL) is imported only by workers that repeat.
            from maniskill_torchrl._internal.repeat import repeat_step

            # Each inner step's reward in float32 before the sum, as ActionRepeat sums the
            # parent env's float32 rewards: one rule for bool and float64 tasks on both paths.
            self._stepper = _Float32Reward(self.env)
            self._repeat_step = repeat_step
        self.repeat = repeat

    @torch.inference_mode()
    def render_frame_shape(self) -> tuple[int, ...]:
        return render_frame_shape(self.env.unwrapped)

    @torch.inference_mode()
    def render(self) -> Any:
        """ManiSkill's ``render()`` as numpy (what crosses the pipe: a ``sapien_cuda`` frame is on the GPU)."""
        frame = self.env.render()
        return frame.cpu().numpy() if isinstance(frame, torch.Tensor) else frame

    def _pack(self, obs: Any, info: Mapping, reward: Any, terminated: Any, truncated: Any) -> dict:
        return {
            OBS: _unbatch(obs),
            INFO: _select(info, self._info_space),
            REWARD: reward,
            TERMINATED: terminated,
            TRUNCATED: truncated,
        }

    @torch.inference_mode()
    def get_state_dict(self) -> dict:
        """ManiSkill's ``get_state_dict()`` of this env (``[1, ...]`` tensors), as normal tensors."""
        return _map_tensors(self.env.unwrapped.get_state_dict(), torch.Tensor.clone)

    @torch.inference_mode()
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if options and SUB_ENV_STATES in options:
            # The batch's saved states, one row per sub-env being reset: this env takes its own.
            options = dict(options)
            rows, states, obs = options.pop(SUB_ENV_STATES)
            k = rows.index(self.index)
            options["reset_to_env_states"] = {"env_states": _map_tensors(states, lambda x: x[k : k + 1])}
            if obs is not None:  # ManiSkill returns these observations instead of computing them
                options["reset_to_env_states"]["obs"] = _map_tensors(obs, lambda x: x[k : k + 1])
        obs, info = self.env.reset(seed=seed, options=options)
        return self._pack(obs, info, np.float32(0), False, False), {}

    @torch.inference_mode()
    def step(self, action: Any):
        trace = self.trace
        if trace is not None:
            trace.stamp(3 + 2 * self.index)
        if self.repeat == 1:
            obs, reward, terminated, truncated, info = self._stepper.step(_batch(action))
        else:
            obs, reward, terminated, truncated, info = self._repeat_step(self._stepper, _batch(action), self.repeat)
        if trace is not None:
            trace.stamp(4 + 2 * self.index)
            trace.count += 1
        packed = self._pack(obs, info, reward[0].numpy(), terminated[0].numpy(), truncated[0].numpy())
        return packed, 0.0, False, False, {}


class _Float32Reward(gym.RewardWrapper):
    """ManiSkill's batched reward as float32 (bool and float64 tasks), as the TorchRL env has it."""

    def reward(self, reward: Any) -> Any:
        return reward if reward.dtype == torch.float32 else reward.to(torch.float32)


def join_states(states: Any) -> dict:
    """Sub-envs' ``get_state_dict()`` trees (``[1, ...]`` tensors) joined into one ``[N, ...]`` tree."""
    first = states[0]
    if isinstance(first, Mapping):
        return {k: join_states([s[k] for s in states]) for k in first}
    return torch.cat(list(states))


def _map_tensors(tree: Any, fn: Any) -> Any:
    """``tree`` (nested dicts of tensors) with ``fn`` applied to every tensor."""
    if isinstance(tree, Mapping):
        return {k: _map_tensors(v, fn) for k, v in tree.items()}
    return fn(tree)


class MakeWorker:
    """Picklable env factory for the forkserver workers (``index``: the sub-env it makes)."""

    def __init__(self, env_id: str, kwargs: dict, index: int = 0, trace: tuple | None = None) -> None:
        self.env_id, self.kwargs, self.index = env_id, kwargs, index
        self.trace = trace  # a StepTrace's spec: a worker's sub-env stamps its steps there

    def __call__(self) -> gym.Env:
        env = self.make()
        if multiprocessing.parent_process() is not None:  # a worker
            _batch_scheduling()
            # One intra-op thread per worker, as TorchRL's ParallelEnv sets: N workers on N cores,
            # not N thread pools of every core each (a ManiSkill step is many small torch ops).
            torch.set_num_threads(1)
            if self.trace is not None:
                from maniskill_torchrl.engines._trace import StepTrace

                env.trace = StepTrace(*self.trace)
        return env

    def make(self) -> StepInObservation:
        """The env, with no change to this process's scheduling (the parent's own sub-env)."""
        import mani_skill.envs  # noqa: F401  (registers the tasks in the worker)

        with no_asset_prompt(self.env_id):  # a worker has no terminal to answer ManiSkill's prompt
            kwargs = default_render_backend(self.kwargs)
            # Sub-env 0 in the parent shares its render device with the parent's other envs.
            env = make_maniskill(self.env_id, batched=True, num_envs=1, **kwargs)
            return StepInObservation(env, self.index)


def serve(conn: Any, make: MakeWorker) -> None:
    """A worker's life: make the env, say what it is, then answer the parent until told to close.

    Messages on ``conn`` (a duplex :class:`multiprocessing.connection.Connection`):

    - the first reply: ``("ready", result space, action space, render mode)``, or an error;
    - :data:`STEP`: step with this sub-env's row of the block's actions, write its row of the
      results, answer :data:`DONE`;
    - :data:`STEP_RESET` (a split-phase block): the same, then, if that step ended the episode,
      reset with the block's seed for this sub-env (-1: unseeded) and write the reset into row
      ``N + index``;
    - a pickled ``(command, args, kwargs)``: ``attach`` (the block's layout and name), ``reset``
      (its row written, like a step), ``call`` (a method or attribute of the env, its value
      pickled back), ``close``. Each is answered ``("ok", value)``.

    An exception is answered ``("error", exception or None, type name, message)`` after its
    traceback is printed here, and the worker waits for the next message. A closed pipe (the parent
    is gone) ends it.
    """
    index = make.index
    # Ctrl-C reaches every process of the terminal's group: the parent decides, and closes its
    # workers itself (a worker that quit here would leave the parent's receive a dead pipe).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        env = make()
        _send(conn, ("ready", env.observation_space, env.action_space, env.render_mode))
    except BaseException as err:
        _fail(conn, index, err)
        return
    block = None
    try:
        while True:
            try:
                message = conn.recv_bytes()
            except (EOFError, OSError):
                return
            try:
                if message == STEP:
                    block.write_row(index, env.step(block.action_row(index))[0])
                    conn.send_bytes(DONE)
                    continue
                if message == STEP_RESET:  # split phase: the episode's next start right after its end
                    step = env.step(block.action_row(index))[0]
                    block.write_row(index, step)
                    if step[TERMINATED] or step[TRUNCATED]:
                        seed = int(block.seeds[index])
                        reset = env.reset(seed=seed if seed >= 0 else None)[0]
                        block.write_row(block.layout.num_envs + index, reset)
                    conn.send_bytes(DONE)
                    continue
                command, args, kwargs = pickle.loads(message)
                value = None
                if command == "attach":
                    from maniskill_torchrl.engines._shared import SharedBlock

                    block = SharedBlock(*args)
                elif command == "reset":
                    block.write_row(index, env.reset(**kwargs)[0])
                elif command == "call":
                    attr = env.get_wrapper_attr(args[0])
                    value = attr(*args[1:], **kwargs) if callable(attr) else attr
                elif command == "close":
                    _send(conn, ("ok", None))
                    return
                else:
                    raise ValueError(f"unknown command {command!r}")
                _send(conn, ("ok", value))
            except Exception as err:
                _fail(conn, index, err)
    finally:
        env.close()
        if block is not None:
            block.close()


def _send(conn: Any, message: tuple) -> None:
    conn.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))


def _fail(conn: Any, index: int, err: BaseException) -> None:
    """Prints ``err``'s traceback and sends it to the parent (the exception itself where it pickles)."""
    sys.stderr.write(f"CPUVectorEnv: the worker of sub-env {index} raised:\n{traceback.format_exc()}")
    sys.stderr.flush()
    try:
        payload = pickle.dumps(err)
        pickle.loads(payload)
    except Exception:
        err_copy = None
    else:
        err_copy = err
    try:
        _send(conn, ("error", err_copy, type(err).__name__, str(err)))
    except (OSError, EOFError):
        pass


def _batch_scheduling() -> None:
    """Runs this worker (and the threads it starts) under Linux's ``SCHED_BATCH`` policy.

    Same fair share, but a woken worker does not preempt the running process: the parent
    sends every worker its action before one of them takes its core (the pipe wake-up
    otherwise hands the parent's core to the first worker for a time slice).
    """
    policy = getattr(os, "SCHED_BATCH", None)
    if policy is not None and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, policy, os.sched_param(0))
        except OSError:
            pass


# ----------------------------------------------------------- parent side of the buffers
def to_numpy(action: Any) -> Any:
    """Batched torch actions (or dicts of them) -> numpy, for the workers' pipes."""
    if isinstance(action, torch.Tensor):
        return action.detach().cpu().numpy()
    return {k: to_numpy(v) for k, v in action.items()}


def zeros_tree(space: gym.spaces.Dict, n: int) -> dict:
    """``[n, ...]`` torch zeros shaped and typed as ``space``'s entries."""
    return {
        k: zeros_tree(sub, n)
        if isinstance(sub, gym.spaces.Dict)
        else torch.zeros((n, *sub.shape), dtype=torch.from_numpy(np.zeros((), sub.dtype)).dtype)
        for k, sub in space.spaces.items()
    }
