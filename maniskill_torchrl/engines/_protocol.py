"""The bytes a step crosses a worker's pipe as, one each way: the parent's wake (:data:`STEP`, or
:data:`STEP_RESET` in split-phase engines: step, and reset at once if that step ended the episode) and
the worker's :data:`DONE`. The data lies in the shared block (``_shared.py``). The worker (``_worker.py``)
and the parent's pool (``_pool.py``) both import them from here, and nothing else with them.
"""

from __future__ import annotations

__all__ = ["DONE", "STEP", "STEP_RESET"]

STEP, DONE, STEP_RESET = b"s", b"k", b"a"
