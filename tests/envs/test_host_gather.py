"""The host gather (``HostGather``, ``maniskill_torchrl/_internal/host_gather.py``) on its own:
one copy of a step's host tensors, handed out as views that later calls never write into. Its CUDA
side (pinned buffers, events) runs under the CUDA double in ``tests/gpu/cuda_device_cases.py``;
here the target is the CPU."""

from __future__ import annotations

import pytest
import torch

from maniskill_torchrl._internal.host_gather import HostGather


def _step(i: int) -> dict:
    return {
        "agent": {"qpos": torch.arange(9, dtype=torch.float32) + i, "qvel": torch.full((2, 9), float(i))[:, ::2]},
        "rgb": torch.full((2, 4, 4, 3), i, dtype=torch.uint8),
        "reward": torch.tensor([[i / 3]], dtype=torch.float32),
        "done": torch.tensor([[i % 2 == 1]]),
        "elapsed_steps": torch.tensor(i, dtype=torch.int32),  # 0-dim, 4 bytes beside 8-byte leaves
        "count": torch.tensor([i], dtype=torch.int64),
        "name": "not a tensor",
    }


def test_values_dtypes_shapes_and_no_aliasing():
    gather = HostGather(torch.device("cpu"))
    kept = []
    for i in range(5):
        source = _step(i)
        out = gather(source)
        assert out["name"] == "not a tensor"
        for path, want in _leaves(source):
            got = _get(out, path)
            assert got.dtype == want.dtype and got.shape == want.shape and torch.equal(got, want), path
        kept.append((out, source))
    for out, source in kept:  # later calls rewrote the host buffers, never what was handed out
        for path, want in _leaves(source):
            assert torch.equal(_get(out, path), want), path


def test_new_leaves_grow_the_layout_and_host_values():
    gather = HostGather(torch.device("cpu"))
    first = gather({"obs": torch.ones(3)})
    out = gather({"obs": torch.zeros(3), "reward": torch.tensor([2.0])})
    assert torch.equal(first["obs"], torch.ones(3)) and torch.equal(out["reward"], torch.tensor([2.0]))
    assert torch.equal(gather.host_value(out["reward"]), torch.tensor([2.0]))
    assert gather.host_value(out["reward"].clone()) is None  # not a leaf it handed out


def _leaves(tree: dict, prefix: tuple = ()):
    for k, v in tree.items():
        if isinstance(v, dict):
            yield from _leaves(v, (*prefix, k))
        elif isinstance(v, torch.Tensor):
            yield (*prefix, k), v


def _get(tree: dict, path: tuple):
    for k in path:
        tree = tree[k]
    return tree


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs in the GPU check)")
def test_cuda_pinned_buffers_one_copy_and_events():
    """On CUDA: pinned host buffers, an event per buffer waited for before its reuse, device leaves
    on the GPU (pictures already there copied on it) that later calls never write into."""
    device = torch.device("cuda", torch.cuda.current_device())
    gather = HostGather(device)
    kept = []
    for i in range(6):
        source = _step(i)
        source["picture"] = picture = torch.full((1, 8, 8, 3), i, dtype=torch.uint8, device=device)
        out = gather(source)
        assert out["picture"].data_ptr() != picture.data_ptr()  # a copy on the device
        kept.append((out, {k: v.clone() for k, v in source.items() if isinstance(v, torch.Tensor)}))
    assert all(buf.is_pinned() for buf, _, _ in gather._buffers)
    assert all(event is not None for _, _, event in gather._buffers)
    torch.cuda.synchronize()
    for out, source in kept:
        for key, want in source.items():
            got = out[key]
            assert got.device == device and got.dtype == want.dtype and torch.equal(got.cpu(), want.cpu()), key
