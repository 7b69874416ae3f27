"""A CUDA machine running ManiSkill's CPU sim, on a CPU-only torch: the test double.

What it stands for: on a machine with an NVIDIA GPU, ManiSkill's CPU sim renders with
``sapien_cuda`` (its default there). Camera pictures (``sensor_data/*``) and ``render()`` then
come back as CUDA tensors, views of SAPIEN buffers that the next render overwrites, while the
agent and extra observations, rewards, done flags and infos come back on the CPU. Seen on a lent
H200 on 2026-11-26 (issue 32).

How: a second torch device, ``fakecuda``, made of PyTorch's PrivateUse1 key renamed and
registered as a Python backend (``torch.utils.backend_registration``). Its tensors
(:class:`DeviceTensor`) hold a CPU tensor and behave as CUDA tensors do where the library could
go wrong: ``.numpy()`` raises, an op mixing them with CPU tensors (other than 0-dim ones, a
``copy_`` or CPU indices) raises ``Expected all tensors to be on the same device``, and
``.cpu()`` / ``.to("cpu")`` give a plain CPU tensor. Then, at ManiSkill's own seams:

- ``RenderCamera.get_picture`` copies each picture into one ``fakecuda`` buffer per camera and
  texture and returns that buffer, as SAPIEN's ``get_picture_cuda(name).torch()`` does;
- new envs report ``backend.render_backend == "sapien_cuda"`` (ManiSkill's and the library's
  test of that road);
- the library's probe for a CUDA render device says there is one (so it leaves ManiSkill's
  default render backend alone, as on a CUDA machine);
- ``torch.cuda.is_available()`` is True, one device, device 0 current, as TorchRL's collectors
  and envs ask before they pick a synchronisation (``synchronize`` is counted; nothing runs on
  ``"cuda"`` itself).

It counts what crosses between host and device (:data:`TRANSFERS`): copies each way, and the
host's waits for the device (``.cpu()``, ``.tolist()``, ``.item()``, ``synchronize``, events).

Importing this module registers the device, which torch then takes for the machine's
accelerator: so it is only imported in processes that stand for a CUDA machine.
``tests/gpu/cuda_site`` holds a ``sitecustomize.py`` that calls :func:`install` in every Python
process started with that folder on ``PYTHONPATH`` and ``MANISKILL_TORCHRL_CUDA_DOUBLE=1``
(``tests/gpu/test_cuda_machine.py`` starts one so): the test's subprocess and the CPU workers of a batched env or of a
``ParallelEnv``, started by forkserver or spawn. ``tests/gpu/test_cuda_machine.py`` runs
``tests/gpu/cuda_machine_cases.py`` with pytest in such a subprocess.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import torch
from torch.utils._pytree import tree_map

NAME = "fakecuda"

#: Copies between the host and the device, and on the device, since the process started:
#: ``{"d2h": n, "d2h_bytes": b, "h2d": ..., "d2d": ...}`` (``benchmarks/bench_obs_copy.py`` reads it);
#: ``"sync"``: the host waiting for the device, as CUDA makes it (a blocking copy to the host:
#: ``.cpu()``, ``.to("cpu")``, ``.tolist()``, ``.item()``, ``bool()``; ``torch.cuda.synchronize``);
#: ``"event_record"`` / ``"event_wait"``: an event recorded on the device, a wait for a recorded one
#: (the wait for one copy, not for the device); ``"render_upload"``: a picture written into its
#: device buffer by the stand-in renderer (SAPIEN's, not the library's, so not an ``h2d``).
TRANSFERS: Counter = Counter()


def _count(kind: str, t: torch.Tensor) -> None:
    TRANSFERS[kind] += 1
    TRANSFERS[f"{kind}_bytes"] += t.numel() * t.element_size()


# Ops that take CPU tensors beside device tensors on CUDA too: copies across devices, CPU indices.
_MIXED_OK = {"copy_", "index", "index_put", "index_put_", "_index_put_impl_"}


class DeviceTensor(torch.Tensor):
    """A tensor on ``fakecuda:0``: a CPU tensor inside, CUDA's rules outside."""

    inner: torch.Tensor

    @staticmethod
    def __new__(cls, inner: torch.Tensor) -> DeviceTensor:
        return torch.Tensor._make_wrapper_subclass(
            cls,
            inner.shape,
            strides=inner.stride(),
            storage_offset=inner.storage_offset(),
            dtype=inner.dtype,
            device=DEVICE,
            requires_grad=False,
        )

    def __init__(self, inner: torch.Tensor) -> None:
        self.inner = inner

    def __repr__(self) -> str:
        return f"DeviceTensor({self.inner!r}, device='{DEVICE}')"

    def numpy(self, *args: Any, **kwargs: Any) -> Any:
        raise TypeError(
            f"can't convert {DEVICE} device type tensor to numpy. "
            "Use Tensor.cpu() to copy the tensor to host memory first."
        )

    __array__ = numpy

    def tolist(self) -> Any:  # as from CUDA: a copy to the host, read
        _count("d2h", self.inner)
        TRANSFERS["sync"] += 1
        return self.inner.tolist()

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func.overloadpacket.__name__
        if name in ("_to_copy", "to"):  # inference mode dispatches `to` itself
            src = args[0].inner if isinstance(args[0], DeviceTensor) else args[0]
            device = kwargs.get("device")
            to_host = device is not None and torch.device(device).type == "cpu"
            if device is not None:
                kwargs["device"] = torch.device("cpu")
            if to_host and name == "to":
                kwargs["copy"] = True  # out of device memory: always a copy, as from CUDA
            out = func(src, *args[1:], **kwargs)
            if out is not src:
                _count("d2h" if to_host else "d2d" if isinstance(args[0], DeviceTensor) else "h2d", out)
                TRANSFERS["sync"] += to_host
            if to_host:
                return out
            with torch.inference_mode(False):
                return DeviceTensor(out)
        mixed = []

        def unwrap(x: Any) -> Any:
            if isinstance(x, DeviceTensor):
                return x.inner
            if isinstance(x, torch.Tensor) and x.dim() > 0:
                mixed.append(x.device)
            return x

        args, kwargs = tree_map(unwrap, args), tree_map(unwrap, kwargs)
        if name == "copy_" and mixed:
            _count("h2d", args[0])
        elif name == "_local_scalar_dense":  # .item(), bool(): a read on the host
            _count("d2h", args[0])
            TRANSFERS["sync"] += 1
        elif name == "clone":
            _count("d2d", args[0])
        if mixed and name not in _MIXED_OK:
            raise RuntimeError(
                f"Expected all tensors to be on the same device, but found at least two devices, {DEVICE} and "
                f"{mixed[0]}! (aten.{name}, fakecuda double)"
            )
        out = func(*args, **kwargs)
        # Wrappers made outside inference mode: autograd's view tracking may write their version
        # counter when a view of a normal tensor is taken under inference mode (ManiSkill's workers).
        with torch.inference_mode(False):
            return tree_map(lambda x: DeviceTensor(x) if type(x) is torch.Tensor else x, out)


def _empty(*args: Any, **kwargs: Any) -> DeviceTensor:
    kwargs["device"] = "cpu"
    kwargs.pop("pin_memory", None)
    return DeviceTensor(torch.empty(*args, **kwargs))


def _empty_strided(size: Any, stride: Any, **kwargs: Any) -> DeviceTensor:
    kwargs["device"] = "cpu"
    kwargs.pop("pin_memory", None)
    return DeviceTensor(torch.empty_strided(size, stride, **kwargs))


class _Event:
    """``torch.fakecuda.Event``, as ``torch.cuda.Event``: copies here end at once, so it only counts."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.recorded = False

    def record(self, stream: Any = None) -> None:
        self.recorded = True
        TRANSFERS["event_record"] += 1

    def synchronize(self) -> None:
        TRANSFERS["event_wait"] += self.recorded

    def query(self) -> bool:
        return True


class _DeviceModule:
    """``torch.fakecuda``: what torch asks of a device module (``fork_rng`` saves its RNG state)."""

    Event = _Event

    def is_initialized(self) -> bool:
        return True

    def is_available(self) -> bool:
        return True

    def current_device(self) -> int:
        return 0

    def device_count(self) -> int:
        return 1

    def _is_in_bad_fork(self) -> bool:
        return False

    def manual_seed_all(self, seed: int) -> None:
        pass

    def get_rng_state(self, device: Any = None) -> torch.Tensor:
        return torch.zeros(1, dtype=torch.uint8)

    def set_rng_state(self, state: torch.Tensor, device: Any = None) -> None:
        pass

    def synchronize(self, device: Any = None) -> None:
        TRANSFERS["sync"] += 1


def _copy_from(src: torch.Tensor, dst: DeviceTensor, non_blocking: bool = False) -> torch.Tensor:
    dst.inner.copy_(src.inner if isinstance(src, DeviceTensor) else src)
    _count("d2d" if isinstance(src, DeviceTensor) else "h2d", dst.inner)
    return dst


def _register_device() -> Any:
    """Registers ``fakecuda`` (once per process: importing this module does it)."""
    from torch.utils.backend_registration import _setup_privateuseone_for_python_backend

    _setup_privateuseone_for_python_backend(NAME, backend_module=_DeviceModule())
    # Factories on the device (`torch.zeros(..., device=...)`, `cpu_tensor.to(device)`) start here.
    lib = torch.library.Library("aten", "IMPL")
    lib.impl("empty.memory_format", _empty, "PrivateUse1")
    lib.impl("empty_strided", _empty_strided, "PrivateUse1")
    lib.impl("_copy_from", _copy_from, "PrivateUse1")  # torch.tensor(data, device=...)
    return lib


_LIB = _register_device()
DEVICE = torch.device(NAME, 0)


# ----------------------------------------------------------------------------- ManiSkill's seams
def _patches() -> list[tuple[Any, str, Any]]:
    """(object, attribute, replacement) for the three seams."""
    import mani_skill.envs.sapien_env as sapien_env
    from mani_skill.utils import common
    from mani_skill.utils.structs.render_camera import RenderCamera

    import maniskill_torchrl._internal.rendering as lib_maniskill

    parse = sapien_env.parse_sim_and_render_backend

    def get_picture(self, names):
        names = [names] if isinstance(names, str) else names
        out = []
        for name in names:
            # ManiSkill's CPU read, then SAPIEN's CUDA road: one buffer per camera and texture.
            picture = common.to_tensor(self._render_cameras[0].get_picture(name))[None, ...]
            # Kept on the camera itself: a dict keyed by id() hands a dead camera's buffer to a new
            # one that reuses its address. Made outside inference mode, as SAPIEN's own buffers are,
            # so a later upload outside it may write into it.
            buffers = self.__dict__.setdefault("_double_buffers", {})
            buf = buffers.get(name)
            if buf is None or buf.shape != picture.shape:
                with torch.inference_mode(False):
                    buf = buffers[name] = torch.empty(picture.shape, dtype=picture.dtype, device=DEVICE)
            buf.inner.copy_(picture)  # SAPIEN's own upload: counted apart from the library's copies
            TRANSFERS["render_upload"] += 1
            out.append(buf)
        return out

    def parse_backends(sim_backend, render_backend):
        # ManiSkill's GPU renderer names (its default "gpu" among them): rendered on the CPU here,
        # without ManiSkill's no-CUDA fallback warning, and reported as sapien_cuda.
        name = str(render_backend)
        on_gpu = name in ("gpu", "cuda", "sapien_cuda") or name.startswith(("cuda:", "sapien_cuda:"))
        info = parse(sim_backend, "sapien_cpu" if on_gpu else render_backend)
        if on_gpu:
            info.render_backend = "sapien_cuda"
        return info

    return [
        (RenderCamera, "get_picture", get_picture),
        (sapien_env, "parse_sim_and_render_backend", parse_backends),
        (lib_maniskill, "_no_cuda_render_device", lambda: False),
    ]


def _cuda_answers() -> list[tuple[Any, str, Any]]:
    """``torch.cuda`` answering as on a CUDA machine where TorchRL asks (its collectors refuse a
    device they know no synchronisation for: ``"Non supported device"``): available, one device,
    device 0 current, ``synchronize`` counted (the double's device never lags). Nothing runs on
    ``"cuda"`` itself: the double's device is ``fakecuda``."""
    return [
        (torch.cuda, "is_available", lambda: True),
        (torch.cuda, "device_count", lambda: 1),
        (torch.cuda, "current_device", lambda: 0),
        (torch.cuda, "synchronize", _DeviceModule().synchronize),
    ]


def install() -> None:
    """The double, for good, in this process (``sitecustomize``)."""
    for obj, attr, new in [*_patches(), *_cuda_answers()]:
        setattr(obj, attr, new)
