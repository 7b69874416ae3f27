"""The library's own exceptions, public: ``from maniskill_torchrl import RenderDeviceError``.

Each is defined beside the code that raises it (so that the CPU engine's workers, which import as
little as they can, need not import this module) and has this module as its public home.
"""

from __future__ import annotations

from maniskill_torchrl._internal.rendering import RenderDeviceError

__all__ = ["RenderDeviceError"]

RenderDeviceError.__module__ = __name__
