"""The library on a machine with CUDA running ManiSkill's CPU sim (the common set-up: ManiSkill's
CPU sim renders with ``sapien_cuda`` there, pictures on the GPU, states on the CPU), proven on any
machine with the test double of ``tests/support/cuda_double.py``.

The cases are in ``cuda_machine_cases.py`` and ``cuda_device_cases.py`` beside it (``env.to()``,
the copies of a step); they run here with pytest in a subprocess whose
every Python process (the batched env's and ``ParallelEnv``'s workers too) loads the double
through ``cuda_site/sitecustomize.py``. The double registers a torch device, which torch then
takes for the machine's accelerator: so it never loads in this pytest process.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

# Not support.helpers's: that imports torch, and this process only starts the subprocess (tests/conftest.py
# then skips its set-up here).
ROOT = Path(__file__).resolve().parents[2]

#: Run together, in one pytest subprocess. In one process, not pytest-xdist's two: the cases' env
#: workers already keep 2 cores busy, and a second test process only adds its start-up (torch, TorchRL,
#: ManiSkill) and its own BRDF table: beside `make test-upstream`, as CI runs it, 131 s instead of 174 s.
HERE = ROOT / "tests" / "gpu"
CASES = [HERE / "cuda_machine_cases.py", HERE / "cuda_device_cases.py"]


def subprocess_env() -> dict[str, str]:
    """The environment of a subprocess (and of its workers) that runs under the double."""
    env = dict(os.environ, MANISKILL_TORCHRL_CUDA_DOUBLE="1")
    paths = [HERE / "cuda_site", ROOT / "tests", ROOT]
    env["PYTHONPATH"] = os.pathsep.join([*map(str, paths), *filter(None, [env.get("PYTHONPATH")])])
    return env


def test_library_on_a_cuda_machine():
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "--tb=short", "--show-capture=no"]
        + ["-p", "no:cacheprovider", "-p", "no:warnings", *map(str, CASES)],
        cwd=ROOT,
        env=subprocess_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, f"{result.stdout[-6000:]}\n{result.stderr[-3000:]}"
    assert " passed" in result.stdout and "skipped" not in result.stdout, result.stdout[-2000:]
