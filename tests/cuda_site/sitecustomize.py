"""Installs the CUDA-machine test double (``tests/cuda_double.py``) in every Python process started
with this folder on ``PYTHONPATH`` and ``MANISKILL_TORCHRL_CUDA_DOUBLE=1``: a test's subprocess and
the CPU workers it starts (forkserver and spawn start fresh interpreters, which run this file)."""

import os

if os.environ.get("MANISKILL_TORCHRL_CUDA_DOUBLE") == "1":
    import cuda_double

    cuda_double.install()
