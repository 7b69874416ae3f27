"""A consistent stack: torchrl's C extension loads against the installed torch, so prioritized
replay (its segment trees are C++) works in the project's own set-up.

torchrl 0.14.1's wheels are built for torch 2.14. Elsewhere (the accelerator machine's preinstalled
torch 2.11, with the GPU kit's torchrl) the extension does not load and ``PrioritizedReplayBuffer``
raises "SumSegmentTreeFp32 is not available": the test then skips and names the mismatch, but only
when torch's minor version is not the one torchrl was built for; in the project's set-up it never skips.
"""

from __future__ import annotations

import pytest
import torch

TORCHRL_BUILT_FOR = (2, 14)  # torch minor version of torchrl 0.14.1's wheels (pyproject: torch>=2.14,<2.15)


def test_prioritized_replay_buffer_extends_and_samples():
    import torchrl
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, PrioritizedReplayBuffer

    torch_minor = tuple(int(p) for p in torch.__version__.split("+")[0].split(".")[:2])
    try:
        rb = PrioritizedReplayBuffer(alpha=0.6, beta=0.4, storage=LazyTensorStorage(10), batch_size=4)
    except (RuntimeError, ImportError) as err:  # "SumSegmentTreeFp32 is not available": the extension did not load
        if torch_minor == TORCHRL_BUILT_FOR or not torchrl.__version__.startswith("0.14."):
            raise
        pytest.skip(
            f"torch {torch.__version__} / torchrl {torchrl.__version__} mismatch: torchrl's C extension is built "
            f"for torch {'.'.join(map(str, TORCHRL_BUILT_FOR))} and does not load here, so prioritized replay "
            f"is unavailable with this torch ({type(err).__name__}: {err})"
        )
    rb.extend(TensorDict(obs=torch.arange(8.0).unsqueeze(-1), batch_size=[8]))
    assert len(rb) == 8
    sample, info = rb.sample(return_info=True)
    assert sample.batch_size == (4,)
    assert torch.isin(sample["obs"].squeeze(-1), torch.arange(8.0)).all()
    assert info["index"].shape == (4,) and info["priority_weight"].shape == (4,)
    rb.update_priority(info["index"], torch.full((4,), 5.0))  # the segment trees take new priorities
    assert rb.sample(return_info=True)[1]["priority_weight"].gt(0).all()
