"""The library's private helpers, one module per feature; no TorchRL env imports.

- :mod:`.repeat`: action repeat's rules (the transform, the gym shim and the engine's workers).
- :mod:`.episode_stats`: the ``"episode"`` entries and their sums (``EpisodeMetrics``, the gym shim).
- :mod:`.assertions`: TensorDict equality to the bit (:mod:`maniskill_torchrl.testing`).
- :mod:`.mp`: process start-up facts for ManiSkill under multiprocessing.

Their names may change in any release.
"""
