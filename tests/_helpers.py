"""Scene and tensor helpers shared by the tests (synthetic data only)."""

from __future__ import annotations

import math

import numpy as np
import torch

from macsplat_cli.gaussians import Gaussians

# Tolerances by dtype: (rtol, atol), relative to the largest magnitude of the reference.
TOL = {torch.float32: 2e-4, torch.float64: 1e-10}
GC_EPS = 1e-6
GC_ATOL = 1e-5
GC_RTOL = 1e-3


def random_gaussians(
    n: int,
    *,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    sh_degree: int = 0,
    extent: float = 1.0,
    z_range: tuple[float, float] = (2.0, 4.0),
    scale_range: tuple[float, float] = (0.02, 0.12),
    opacity_logit_range: tuple[float, float] = (-2.0, 2.0),
) -> Gaussians:
    """Random Gaussians in ``[-extent, extent]² × z_range`` in front of an identity camera."""
    g = torch.Generator().manual_seed(seed)

    def u(*shape: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=torch.float64) * (hi - lo) + lo

    means = torch.stack(
        [u(n, lo=-extent, hi=extent), u(n, lo=-extent, hi=extent), u(n, lo=z_range[0], hi=z_range[1])], -1
    )
    log_scales = torch.log(u(n, 3, lo=scale_range[0], hi=scale_range[1]))
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opacity = u(n, lo=opacity_logit_range[0], hi=opacity_logit_range[1])
    k = (sh_degree + 1) ** 2
    sh = torch.randn(n, k, 3, generator=g, dtype=torch.float64) * 0.5
    return Gaussians(means, log_scales, quats, opacity, sh).to(dtype)


def pinhole(width: int, height: int, focal: float | None = None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A centred pinhole K (principal point at the image centre). [3, 3]"""
    f = focal if focal is not None else float(width)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)


def look_at_viewmat(
    eye: tuple[float, float, float], target: tuple[float, float, float], dtype=torch.float32
) -> torch.Tensor:  # noqa: ANN001
    """World-to-camera matrix (OpenCV axes) of a camera at ``eye`` looking at ``target``, y down."""
    e = torch.tensor(eye, dtype=torch.float64)
    z = torch.tensor(target, dtype=torch.float64) - e
    z = z / z.norm()
    down = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(down, z)
    if x.norm() < 1e-9:
        x = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world coordinates
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R
    V[:3, 3] = -R @ e
    return V.to(dtype)


def max_rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a − b| / max |b| (0 when both are empty or zero)."""
    a, b = a.detach(), b.detach()
    if b.numel() == 0:
        return 0.0
    scale = float(b.abs().max())
    return float((a - b).abs().max()) / scale if scale > 0 else float((a - b).abs().max())


def unit_roundoff(dtype: torch.dtype | np.dtype | type) -> float:
    """u = eps / 2: the largest relative error of one rounded operation in ``dtype``."""
    if isinstance(dtype, torch.dtype):
        return torch.finfo(dtype).eps / 2
    return float(np.finfo(dtype).eps) / 2


def gamma(n: int, dtype: torch.dtype | np.dtype | type) -> float:
    """Higham's γₙ = n·u / (1 − n·u): |fl(Σ xᵢyᵢ) − Σ xᵢyᵢ| ≤ γₙ Σ |xᵢyᵢ| for a sum of n products in any order.

    The bound holds whatever the summation order, blocking or vector width of the kernel, so a tolerance built
    from it holds on every CPU (SSE, AVX2, AVX-512, NEON) and thread count; two results computed in different
    orders differ by at most twice it.
    """
    u = unit_roundoff(dtype)
    assert n * u < 1, "γₙ needs n·u < 1"
    return n * u / (1 - n * u)


def _as_f64(x) -> np.ndarray:  # noqa: ANN001
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def assert_within(actual, expected, bound, what: str = "") -> None:  # noqa: ANN001
    """``|actual − expected| ≤ bound`` elementwise, compared in float64 (tensors or arrays; ``bound`` is a scalar or
    broadcasts, e.g. one derived bound per element). The message gives the worst element and its bound."""
    a, e = np.broadcast_arrays(_as_f64(actual), _as_f64(expected))
    b = np.broadcast_to(_as_f64(bound), a.shape)
    assert a.shape == e.shape, f"{what}: shapes {a.shape} and {e.shape}"
    err = np.abs(a - e)
    bad = ~(err <= b)  # NaN fails too
    if bad.any():
        ratio = np.where(bad, err / np.where(b > 0, b, np.finfo(float).tiny), -1.0)
        i = np.unravel_index(int(np.argmax(ratio)), a.shape)
        raise AssertionError(
            f"{what}: {int(bad.sum())} of {a.size} elements exceed the bound; worst at {tuple(int(k) for k in i)}: "
            f"|{float(a[i])!r} − {float(e[i])!r}| = {err[i]:.3e} > {b[i]:.3e}"
        )


def dot_lengths(module: torch.nn.Module) -> list[int]:
    """The number of terms of the dot products in ``module``'s layers: fan-in of each Linear and convolution, and
    two sums (mean, variance) over the normalised size of each LayerNorm/GroupNorm."""
    out: list[int] = []
    for m in module.modules():
        if isinstance(m, torch.nn.Linear):
            out.append(m.in_features)
        elif isinstance(m, (torch.nn.Conv1d, torch.nn.Conv2d, torch.nn.Conv3d)):
            out.append(m.in_channels // m.groups * math.prod(m.kernel_size))
        elif isinstance(m, (torch.nn.ConvTranspose1d, torch.nn.ConvTranspose2d, torch.nn.ConvTranspose3d)):
            out.append(m.in_channels // m.groups * math.prod(m.kernel_size))  # an upper bound of the fan-in
        elif isinstance(m, torch.nn.LayerNorm):
            out += [math.prod(m.normalized_shape)] * 2
        elif isinstance(m, torch.nn.GroupNorm):
            out += [m.num_channels // m.num_groups] * 2
    return out


def forward_rel_tol(module: torch.nn.Module, *sums: int, dtype: torch.dtype = torch.float32) -> float:
    """A first-order estimate of a forward pass's relative rounding error: ``Σ_l γ(n_l)`` over every dot product
    of the network (:func:`dot_lengths`) and the extra ``sums`` (e.g. attention's ``QKᵀ`` over the head size and
    ``softmax·V`` over the tokens, once per attention layer), each layer taken to pass its input's relative error
    on with unit gain (normalisations and residual connections keep activations O(1)).

    Not a rigorous a-priori bound for a deep network, but the worst case of every layer's rounding at once: two
    evaluations in different orders differ by up to twice it, one against a float64 reference by up to it. Compare
    with :func:`max_rel_err` (relative to the largest magnitude, so a cancelling element is not over-weighted)."""
    return sum(gamma(n, dtype) for n in [*dot_lengths(module), *sums])


def forward_rel_tol_probabilistic(
    module: torch.nn.Module, *sums: int, dtype: torch.dtype = torch.float32, lam: float = 8.0
) -> float:
    """:func:`forward_rel_tol` with each layer's γ(n) replaced by the probabilistic bound λ·√n·u (Higham & Mary,
    SIAM J. Sci. Comput. 41(5), 2019: with independent rounding errors, a sum of n terms is within λ√n·u·Σ|terms|
    except with probability ≤ 2n·exp(−λ²(1 − u)²/2); λ = 8: < 1e-12 per 4608-term dot). For wide layers, where the
    worst case n·u is √n times too pessimistic to leave a meaningful tolerance."""
    u = unit_roundoff(dtype)
    return sum(lam * math.sqrt(n) * u for n in [*dot_lengths(module), *sums])


# Rounding budgets of the rotation conversions (macsplat_cli.rotations and NumPy twins), in units of the unit
# roundoff u of the working precision, first order (derivations in tests/test_rotations.py):
ROT_UNIT_Q = 4  # a normalised quaternion q/‖q‖, per component; and ‖q̂‖ − 1
ROT_MAT = 16  # R(q̂) per entry, off a rotation (its own 8u, plus 2·(‖q̂‖² − 1))
ROT_QUAT = 13 + ROT_MAT  # Shepperd's R → q per component, for an R within ROT_MAT of a rotation
ROT_ROUND_TRIP = 2 * math.sqrt(2) * 2 * ROT_QUAT + ROT_MAT  # R → q → R per entry (a rotation by ≤ 2‖δq‖)


def deg(x: float) -> float:
    return math.degrees(x)


def smooth_texture(rng: np.random.Generator):  # noqa: ANN201
    """A smooth random texture over continuous pixel coordinates (sum of sinusoids, periods 5–25 px):
    ``tex(xy [N, 2]) → [N]`` float32."""
    freq = rng.uniform(-1, 1, (12, 2))
    freq *= (2 * np.pi / rng.uniform(5, 25, 12))[:, None] / np.linalg.norm(freq, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, 12)

    def tex(xy: np.ndarray) -> np.ndarray:
        return (0.5 + 0.1 * np.sin(xy @ freq.T + phase).sum(-1)).astype(np.float32)

    return tex


def pixel_centres(w: int, h: int) -> np.ndarray:
    """Pixel centres (x + 0.5, y + 0.5), row-major. [h·w, 2]"""
    ys, xs = np.mgrid[0:h, 0:w]
    return np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)


def apply_homography(Hm: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``xy`` [N, 2] mapped by the 3×3 homography ``Hm``. [N, 2]"""
    p = np.c_[xy, np.ones(len(xy))] @ Hm.T
    return p[:, :2] / p[:, 2:]


def orbit_views(kind: str, angle: float, w: int = 320, h: int = 240, seed: int = 1):  # noqa: ANN201
    """A ray-traced synthetic orbit pair with its true geometry (unit baseline) and true correspondences as the
    inliers: ``(views, geometry, depths)``, the ground-truth depths in baseline units ([h, w] each)."""
    from pathlib import Path

    from macsplat_cli.datasets import synthetic as S
    from macsplat_cli.pipeline.types import Matches, TwoViewGeometry, View

    scene = S.make_scene(kind, 0)
    cam0, cam1 = S.orbit_pair(scene, angle, width=w, height=h, seed=seed)
    renders = [S.render(scene, cam0), S.render(scene, cam1)]
    R, t = S.relative_pose(cam0, cam1)
    baseline = float(np.linalg.norm(t))
    grid = pixel_centres(w, h)[::37]
    px1, visible = S.transfer_points(scene, cam0, cam1, grid)
    n = int(visible.sum())
    inliers = Matches(grid[visible], px1[visible], np.ones(n, np.float32), np.arange(n), np.arange(n))
    geometry = TwoViewGeometry(R, t / baseline, cam0.K.copy(), cam1.K.copy(), inliers)
    views = [
        View(f"v{i}", Path(f"v{i}.png"), r.image, r.mask.copy(), c.K.copy(), (w, h), "file")
        for i, (r, c) in enumerate(zip(renders, (cam0, cam1)))
    ]
    return views, geometry, [r.depth / baseline for r in renders]


def run_cli(args: list) -> tuple[int, str, str]:  # noqa: ANN001 - paths or strings
    """``macsplat ARGS`` in this process: (exit code, stdout, stderr)."""
    import contextlib
    import io

    from macsplat_cli.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


def one_error_line(err: str) -> str:
    """The one ``error:`` line of a command's stderr (asserts there is exactly one)."""
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


def file_size_limit(n_bytes: int):  # noqa: ANN201 - a context manager
    """Within it, writes past ``n_bytes`` in a file fail in this process (EFBIG), as on a full disk (SIGXFSZ
    ignored meanwhile)."""
    import contextlib
    import resource
    import signal

    @contextlib.contextmanager
    def limit():  # noqa: ANN202
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (n_bytes, hard))
        try:
            yield
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
            signal.signal(signal.SIGXFSZ, previous)

    return limit()


def render_pair(
    folder, size: tuple[int, int], *, kind: str = "room", angle: float = 20.0, fov_deg: float = 50.0, seed: int = 0
):  # noqa: ANN001, ANN201 - a folder path; returns (a.png, b.png)
    """Two ray-traced views of a synthetic ``kind`` scene ``angle`` degrees apart, saved as ``a.png`` and
    ``b.png`` in ``folder`` at ``size`` = (W, H)."""
    from macsplat_cli.datasets import synthetic as syn
    from macsplat_cli.images import save_image

    scene = syn.make_scene(kind, seed)
    cams = syn.orbit_pair(kind, angle, width=size[0], height=size[1], fov_deg=fov_deg)
    paths = (folder / "a.png", folder / "b.png")
    for p, c in zip(paths, cams):
        save_image(p, syn.render(scene, c).image)
    return paths
