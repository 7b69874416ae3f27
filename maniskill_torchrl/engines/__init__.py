"""Engines: what runs several ManiSkill envs for :class:`~maniskill_torchrl.ManiSkillEnv`.

- :class:`~maniskill_torchrl.CPUVectorEnv` (``engines/cpu_vector.py``): N CPU-sim envs, one per
  process, with the GPU sim's batched API. ``_worker.py`` is its worker side, ``_shared.py`` the
  shared-memory block of actions and results, ``_pool.py`` the workers seen from the parent
  (and what it does when one dies or raises), ``_trace.py`` the per-step trace.

An engine answers ManiSkill's batched env API (``num_envs``, ``device``, ``gpu_sim_enabled``,
``single_observation_space``, ``single_action_space``, ``render_mode``, ``spec``, ``unwrapped``,
``step``, ``reset``, ``get_info``, ``get_state_dict``, ``render``, ``close``) and declares what it
can do as attributes, which the env core reads without importing the engine:

- ``returns_copies``: every output is a fresh, normal tensor;
- ``runs_inference_mode``: it calls ManiSkill under :func:`torch.inference_mode` itself;
- ``seeds_partial_resets``: a reset with ``options={"env_idx": ...}`` takes a seed;
- ``reconfigures_partially``: a partial reset may reconfigure the envs it resets;
- ``repeats_actions``: ``repeat`` and ``set_repeat(k)``, each step's action repeated up to ``k``
  times inside the sub-envs;
- ``render_frame_shape()``: the ``(H, W, 3)`` of one sub-env's ``render()`` frame (also as
  ManiSkill's ``_human_render_camera_configs``, where the adapter reads it).

Only the factory (:class:`~maniskill_torchrl.ManiSkillEnv`) imports an engine. Names are loaded
on first use: a worker that unpickles its factory from ``_worker.py`` loads nothing else here.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__all__ = ["CPUVectorEnv"]

if TYPE_CHECKING:
    from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv


def __getattr__(name: str) -> Any:
    if name != "CPUVectorEnv":
        raise AttributeError(f"module 'maniskill_torchrl.engines' has no attribute {name!r}")
    value = importlib.import_module("maniskill_torchrl.engines.cpu_vector").CPUVectorEnv
    globals()[name] = value
    return value
