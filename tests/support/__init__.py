"""What the test areas share: ``helpers`` (making and stepping ManiSkill envs, comparing to the
bit, subprocesses), ``toy_env`` (a small TorchRL env ending at chosen steps, the double for what
the CPU sim cannot show), ``cuda_double`` (a stand-in CUDA machine) and ``maniskill_versions``
(what differs on the nightly). The fixtures live in ``tests/conftest.py``; pytest puts ``tests/``
on the path, so a test imports ``from support.helpers import ...``."""
