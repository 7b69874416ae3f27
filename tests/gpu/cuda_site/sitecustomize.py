"""Installs the CUDA-machine test double (``tests/support/cuda_double.py``) in every Python
process started with this folder and ``tests/`` on ``PYTHONPATH`` and
``MANISKILL_TORCHRL_CUDA_DOUBLE=1``: a test's subprocess and the CPU workers it starts
(forkserver and spawn start fresh interpreters, which run this file)."""

import os

if os.environ.get("MANISKILL_TORCHRL_CUDA_DOUBLE") == "1":
    from support import cuda_double

    cuda_double.install()
