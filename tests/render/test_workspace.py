"""The kernels' reusable buffers (``render/_workspace.py``): no render sees another's values, no autograd node reads
a buffer a later render took, and the pool holds only what recent renders used."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from macsplat_cli.gaussians import Gaussians
from macsplat_cli.render import _workspace, render
from macsplat_cli.render.fused import project_gaussians_fused

from support.gaussians import pinhole, random_gaussians

V = torch.tensor([[0.98, -0.1, 0.17, 0.1], [0.1, 0.99, 0.0, -0.2], [-0.17, 0.02, 0.98, 0.3], [0.0, 0.0, 0.0, 1.0]])


@pytest.fixture
def pool(monkeypatch: pytest.MonkeyPatch):  # noqa: ANN201
    """Every array of a render on the pool (the small scenes here would otherwise get plain allocations)."""
    monkeypatch.setattr(_workspace, "MIN_BYTES", 0)
    _workspace.release()
    yield
    _workspace.release()


def _poison() -> None:
    """Every free pooled buffer filled with 0xFF bytes (NaN in float, -1 in int): a kernel that reads what it did
    not write gives another result."""
    for b in _workspace._POOL._buffers:
        if b.free():
            b.array.fill(0xFF)


def _scene(n: int, seed: int, sh_degree: int) -> Gaussians:
    """Random Gaussians, some culled (behind the camera, non-finite, transparent) and, with SH, colours clamped."""
    g = random_gaussians(n, seed=seed, sh_degree=sh_degree, scale_range=(0.01, 0.2))
    g.means[:5, 2] = -1.0
    g.means[5, 0] = float("nan")
    g.opacity_logits[6:9] = -9.0
    return g


def _forward(g: Gaussians, w: int, h: int, camera_grad: bool = False):  # noqa: ANN202
    params = [t.detach().clone().requires_grad_(True) for t in g.tensors()]
    view = V.clone().requires_grad_(camera_grad)
    out = render(Gaussians(*params), view, pinhole(w, h, 0.9 * w), w, h, background=(0.1, 0.2, 0.3))
    gen = torch.Generator().manual_seed(w)
    loss = sum((o * torch.randn(o.shape, generator=gen)).sum() for o in (out.rgb, out.depth, out.alpha))
    loss = loss + out.means2d.sum()
    values = [t.detach().clone() for t in (out.rgb, out.depth, out.alpha, out.visible, out.means2d)]
    return loss, params + ([view] if camera_grad else []), values


def _backward(loss: torch.Tensor, params: list[torch.Tensor]) -> list[torch.Tensor]:
    loss.backward()
    return [p.grad.clone() for p in params]


def _step(g: Gaussians, w: int, h: int, camera_grad: bool = False) -> list[torch.Tensor]:
    loss, params, values = _forward(g, w, h, camera_grad)
    return values + _backward(loss, params)


def _assert_identical(a: list[torch.Tensor], b: list[torch.Tensor]) -> None:
    assert len(a) == len(b)
    for i, (x, y) in enumerate(zip(a, b)):
        assert x.dtype == y.dtype and x.shape == y.shape, i
        assert torch.equal(_bits(x), _bits(y)), i


def _bits(t: torch.Tensor) -> torch.Tensor:
    """A float tensor's bytes (``-0.0`` differs from ``0.0``, a NaN equals itself), other tensors as they are."""
    return t.contiguous().view(torch.uint8) if t.is_floating_point() else t


@pytest.mark.parametrize("camera_grad", [False, True])
def test_renders_back_to_back_equal_a_fresh_one(pool: None, camera_grad: bool) -> None:
    """A render after another scene's, on buffers full of stale bytes, gives the fresh render's bits: outputs and
    every gradient (the fused path, and the camera-gradient path through the twin's projection)."""
    a, b = _scene(300, 1, 2), _scene(700, 2, 0)
    fresh = _step(a, 48, 40, camera_grad)
    assert _workspace.pooled_bytes() > 0
    _step(b, 64, 56, camera_grad)
    _poison()
    _assert_identical(_step(a, 48, 40, camera_grad), fresh)


def test_backward_after_another_forward(pool: None) -> None:
    """Two forwards, then their backwards in the other order: each gradient is that of its render alone (a saved
    array is not handed to the later forward)."""
    a, b = _scene(300, 3, 1), _scene(500, 4, 0)
    alone_a, alone_b = _step(a, 40, 40), _step(b, 56, 48)
    loss_a, params_a, values_a = _forward(a, 40, 40)
    loss_b, params_b, values_b = _forward(b, 56, 48)
    _poison()
    grads_b = _backward(loss_b, params_b)
    _poison()
    _assert_identical(values_a + _backward(loss_a, params_a), alone_a)
    _assert_identical(values_b + grads_b, alone_b)


def test_fused_projection_on_stale_buffers(pool: None) -> None:
    """The fused projection's own autograd node (``project_gaussians_fused``) after a poisoned pool: its outputs and
    gradients are the fresh ones'."""
    g = _scene(400, 5, 2)
    K = pinhole(64, 48, 60.0)

    def run() -> list[torch.Tensor]:
        params = [t.detach().clone().requires_grad_(True) for t in g.tensors()]
        proj = project_gaussians_fused(*params, V, K, 64, 48)
        outs = [proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths]
        sum((o * (i + 1)).sum() for i, o in enumerate(outs)).backward()
        return [o.detach().clone() for o in outs] + [proj.ids.clone()] + [p.grad.clone() for p in params]

    fresh = run()
    _poison()
    _assert_identical(run(), fresh)


def test_a_held_view_keeps_its_buffer_and_a_dropped_one_frees_it(pool: None) -> None:
    x = _workspace.empty((4000, 3), np.float64)
    y = _workspace.empty((4000, 3), np.float64)
    assert x.base is not y.base  # x is held: y gets another buffer
    address = x.ctypes.data
    del x
    z = _workspace.empty(20000, np.float32)  # 80,000 bytes of x's ~100 kB buffer (within the slack): reused
    assert z.ctypes.data == address and z.shape == (20000,)
    assert np.all(_workspace.zeros(40, np.int64) == 0) and np.all(_workspace.full(7, -1, np.int32) == -1)


def test_the_pool_drops_idle_buffers_and_keeps_its_cap(pool: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """A buffer no render took for ``IDLE_RENDERS`` renders is dropped (one still held is not); past ``KEEP_BYTES``
    a request gets a plain array; :func:`release` forgets every buffer."""
    held = _workspace.empty(1000, np.float64)
    _workspace.empty(3000, np.float64)
    for _ in range(_workspace.IDLE_RENDERS + 1):
        _workspace.next_render()
    assert _workspace.pooled_bytes() == held.base.nbytes
    monkeypatch.setattr(_workspace, "KEEP_BYTES", 1 << 20)
    big = _workspace.empty(1 << 19, np.float32)  # 2 MiB
    assert big.base is None and _workspace.pooled_bytes() <= 1 << 20
    _workspace.release()
    assert _workspace.pooled_bytes() == 0
    held[:] = 1.0  # still the caller's


def test_steady_steps_take_no_new_buffers(pool: None) -> None:
    """After a first step, the same step again allocates nothing new: its arrays come from the pool."""
    g = _scene(600, 6, 0)
    _step(g, 64, 64)
    size = _workspace.pooled_bytes()
    for _ in range(3):
        _step(g, 64, 64)
    assert _workspace.pooled_bytes() == size


def test_the_kernel_threads_hold_no_array_after_their_job(monkeypatch: pytest.MonkeyPatch) -> None:
    """After ``parallel_for`` returns, no worker thread still references its arguments (an idle worker holding the
    last job's arrays would keep their buffers out of the pool until its next job)."""
    import weakref

    from macsplat_cli._threads import parallel_for

    monkeypatch.setenv("NUMBA_NUM_THREADS", "3")
    a = np.zeros(8)
    gone = weakref.ref(a)  # an ndarray takes weak references
    parallel_for(lambda start, stop, x: x[start:stop].fill(1.0), 8, a)
    assert a.sum() == 8.0
    del a
    assert gone() is None


@pytest.mark.parametrize("camera_grad", [False, True])
def test_each_render_counts_for_the_idle_drop(pool: None, camera_grad: bool) -> None:
    """Renders at 32² after one at 128² drop the larger render's framebuffers ``IDLE_RENDERS`` renders later (every
    CPU path of ``render`` counts itself)."""
    g = _scene(300, 7, 0)
    _step(g, 128, 128, camera_grad)
    big = _workspace.pooled_bytes()
    _step(g, 32, 32, camera_grad)
    both = _workspace.pooled_bytes()
    for _ in range(_workspace.IDLE_RENDERS):
        _step(g, 32, 32, camera_grad)
    assert _workspace.pooled_bytes() <= both - big // 2
