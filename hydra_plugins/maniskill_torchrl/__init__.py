"""maniskill_torchrl's nodes in TorchRL's Hydra config groups, for TorchRL's own scripts, unmodified.

Hydra imports every module under the ``hydra_plugins`` namespace package when an app starts (its
plugin discovery, at the first ``@hydra.main`` call, before any config is composed). This one
registers :mod:`maniskill_torchrl.configs` (``env=maniskill``, the library's transforms, replay
buffers and hooks) in Hydra's ``ConfigStore``, so that TorchRL's ``sota-implementations/*_trainer``
scripts take ``env@training_env.create_env_fn.base_env=maniskill`` without an edit.

It registers them only where TorchRL's configs are already imported (``torchrl.trainers.algorithms.configs``
in ``sys.modules``: every sota ``train.py`` imports them at its top, before ``hydra.main`` runs), so an
unrelated Hydra app imports nothing of TorchRL's or this library's and sees no new node.
"""

from __future__ import annotations

import sys

if "torchrl.trainers.algorithms.configs" in sys.modules:
    import maniskill_torchrl.configs  # noqa: F401  (registers the nodes on import)
