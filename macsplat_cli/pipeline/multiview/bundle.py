"""Bundle adjustment: poses, points and shared focal lengths refined on the reprojection errors of all observations.

:func:`bundle_adjust` minimises ``Σ_o Σ_k ρ(e_ok)`` over both coordinates ``k`` of every reprojection error
``e_o = π(K_c (R_c X_p + t_c)) − x_o`` with Huber's ``ρ`` (scale ``BundleConfig.loss_scale_px``; scipy's robust
losses act on scalar residuals, so per coordinate), with the Gauss-Newton curvature of :func:`_huber_gauss_newton`,
by Levenberg-Marquardt with the points eliminated (:mod:`.schur`, exact steps on the reduced camera system;
``BundleConfig.solver = "schur"``) or by :func:`scipy.optimize.least_squares` (``"lsmr"``: trust-region reflective,
the 2-D subspace steps of LSMR on a sparse Jacobian). The parameters:

* per non-fixed camera, a rotation update ``δ`` (axis-angle, ``R = Exp(δ) · R₀``) and the translation ``t``;
* per focal group, a log-focal multiplier ``s``: ``fx``, ``fy`` (and the skew) times ``exp(s)``, principal point kept;
* per point with at least ``BundleConfig.min_observations`` observations, its world position.

The Jacobian is analytic (``BundleConfig.jacobian = "analytic"``; ``"2-point"`` takes scipy's finite differences
grouped by the same sparsity instead): for ``p = R X + t`` and ``n = p_xy / p_z``,
``∂pixel/∂p = e^s K₂ₓ₂ ∂n/∂p``, ``∂p/∂X = R``, ``∂p/∂t = I``, ``∂p/∂δ = −[R X]ₓ J_l(δ)`` with ``J_l`` the left Jacobian
of SO(3) (``Exp(δ + ε) ≈ Exp(J_l(δ) ε) Exp(δ)``), ``∂pixel/∂s = e^s K₂ₓ₂ n``.

Gauge: the fixed poses (camera 0 by default) fix rotation and translation; when they all share one centre the scale is
still free, and after the solve a similarity about that centre restores the distance from it to the first free
camera with a non-zero baseline (its value before the solve). A similarity scales every camera-frame point by one
factor, so it leaves every reprojection error unchanged.

Conventions: OpenCV axes, ``X_cam = R · X_world + t``, pixel ``= K · X_cam / z`` (``K`` encodes the +0.5 pixel
centres). float64 throughout.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from ...errors import NonFiniteError, ShapeError
from .schur import solve_schur
from .triangulate import _check_inputs, reprojection_errors

if TYPE_CHECKING:  # scipy is imported where it is used: two-photo runs never load it (start-up time)
    import scipy.sparse as sp

__all__ = ["BundleConfig", "BundleResult", "bundle_adjust", "compile_kernels"]

_SERIES_BELOW = 1e-2  # rotation angle (rad) under which Rodrigues' coefficients come from their Taylor series


@dataclass
class BundleConfig:
    """Settings of :func:`bundle_adjust`.

    Args:
        loss_scale_px: robust loss (Huber) scale, px: one pixel of SIFT localisation noise; errors beyond it count
            linearly, so a mismatched track pulls with a bounded force.
        max_evaluations: residual evaluations at most (one per trust-region step tried, the Jacobian once per
            accepted step). Measured at 32 cameras, 8,000 points, 40,000 observations from a start 1° and a few % off:
            11 at 0.5 px noise, 57 with 10 % of the observations 30 px off (points seen mostly by outliers drift
            slowly on Huber's linear branch); 100 bounds the time of a bad start.
        ftol: stop when a step lowers the robust cost by less than this fraction. 1e-6 converges the clean case in
            11 evaluations; with 10 % outliers 1e-5 stops at 27 and 1e-4 at 16, the poses within 0.005° and 0.008°
            of the converged ones (their error to the truth, from the noise, is 0.11°): raise it to trade those.
        xtol: stop when the step is below this fraction of the parameters' norm (tiny: points' world coordinates
            dominate that norm, so a relative 1e-8 would stop before pixel-level convergence).
        gtol: stop when the scaled gradient's largest entry is below this (an exact fit reaches it).
        min_observations: a point with fewer observations is not adjusted and its observations are left out of the
            solve (one observation leaves the point free along its ray); they are still in the reported errors.
        jacobian: ``"analytic"`` (default: exact, one evaluation per accepted step) or ``"2-point"`` (scipy's
            finite differences grouped by the sparsity, ~10 extra residual evaluations per step; for checking).
        lsmr_max_iterations: LSMR iterations at most for the Gauss-Newton direction of each step (the 2-D subspace
            with the gradient makes an inexact direction safe). LSMR is most of the time; at the size above, at
            0.5 px noise, 60 and 100 took 12 and 11 steps, 40 took 18, and scipy's own tolerances alone ~250
            iterations a step (2× the time); from a noise-free start 100 needed 36 steps, 60 71, 40 over 100.
        solver: ``"schur"`` (default: :mod:`.schur`'s exact Levenberg-Marquardt steps on the cameras with the points
            eliminated; the adjustments of 8 / 16 orbit photos' registration 3.0 / 4.6 s → 1.8 / 2.2 s CPU, the poses
            within 0.003° of LSMR's: benchmarks/history/multiview_scaling.md) or ``"lsmr"`` (scipy's trust-region
            solver; the analytic or ``"2-point"`` Jacobian; ``"2-point"`` always takes it).
    """

    loss_scale_px: float = 1.0
    max_evaluations: int = 100
    ftol: float = 1e-6
    xtol: float = 1e-12
    gtol: float = 1e-10
    min_observations: int = 2
    jacobian: str = "analytic"
    lsmr_max_iterations: int = 100
    solver: Literal["schur", "lsmr"] = "schur"


@dataclass
class BundleResult:
    """What :func:`bundle_adjust` returns: the adjusted cameras and points (new arrays) and how the solve went.

    Args:
        R, t, K: the cameras after the solve (fixed poses unchanged; ``K`` changed only in focal groups).
            [C, 3, 3], [C, 3], [C, 3, 3]
        points: the points after the solve (points with fewer than ``min_observations`` only rescaled with the
            gauge). [P, 3]
        rms_before_px, rms_after_px: ``sqrt(mean ‖e_o‖²)`` over all observations before and after, px.
        residual_px: reprojection error norm of each observation after, px. [O]
        evaluations: residual evaluations used.
        seconds: wall time of the call.
        success: the solve stopped on a tolerance (``ftol``, ``xtol``, ``gtol``), not on ``max_evaluations``.
    """

    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    points: np.ndarray
    rms_before_px: float
    rms_after_px: float
    residual_px: np.ndarray
    evaluations: int
    seconds: float
    success: bool


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]ₓ`` [N, 3, 3] of ``v`` [N, 3]."""
    z = np.zeros(v.shape[0])
    return np.stack(
        [np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1), np.stack([-v[:, 1], v[:, 0], z], 1)],
        axis=1,
    )


def _rodrigues(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Exp(w), J_l(w))`` [N, 3, 3] each for axis-angle vectors ``w`` [N, 3]: ``I + a W + b W²`` and
    ``I + b W + c W²`` with ``W = [w]ₓ``, ``a = sin θ/θ``, ``b = (1 − cos θ)/θ²``, ``c = (θ − sin θ)/θ³``."""
    th2 = np.sum(w * w, axis=1)
    th = np.sqrt(th2)
    small = th < _SERIES_BELOW
    ts = np.where(small, 1.0, th)
    a = np.where(small, 1 - th2 / 6 * (1 - th2 / 20 * (1 - th2 / 42)), np.sin(ts) / ts)
    b = np.where(small, 0.5 - th2 / 24 * (1 - th2 / 30 * (1 - th2 / 56)), (1 - np.cos(ts)) / ts**2)
    c = np.where(small, 1 / 6 - th2 / 120 * (1 - th2 / 42 * (1 - th2 / 72)), (ts - np.sin(ts)) / ts**3)
    W = _skew(w)
    W2 = W @ W
    eye = np.eye(3)[None]
    return eye + a[:, None, None] * W + b[:, None, None] * W2, eye + b[:, None, None] * W + c[:, None, None] * W2


def _huber_gauss_newton(z: np.ndarray) -> np.ndarray:
    """Huber's loss for :func:`~scipy.optimize.least_squares` on ``z = (r / scale)²`` [m]: ``(ρ, ρ', ρ'')`` [3, m]
    with ``ρ = z`` up to 1 and ``2√z − 1`` beyond, and ``ρ''`` reported as 0.

    The cost is scipy's ``loss="huber"`` exactly; only the curvature differs. With the true ``ρ''`` scipy's
    correction of the Jacobian (``ρ' + 2 ρ'' z``) is 0 for every residual beyond the scale, so a start where most
    errors exceed 1 px has an almost flat model and crawls (measured, 8 cameras, 200 points, errors ~20 px: 100
    evaluations to 0.83 px RMS against 7 to 0.58 px); with ``ρ'' = 0`` each step is the Gauss-Newton step of the
    reweighted problem (IRLS, what Ceres does when ``ρ'' ≤ 0``), and the minimiser is the same."""
    out = np.empty((3, z.size))
    far = z > 1
    root = np.sqrt(z[far])
    out[0] = z
    out[0, far] = 2 * root - 1
    out[1] = 1.0
    out[1, far] = 1 / root
    out[2] = 0.0
    return out


class _Problem:
    """The parameter layout ``[cameras 6F | focal groups G | points 3Pf]`` and the residuals and Jacobian of the
    observations used (those of adjusted points), with the Jacobian's CSR structure built once."""

    def __init__(
        self,
        R: np.ndarray,
        t: np.ndarray,
        K: np.ndarray,
        points: np.ndarray,
        cam_idx: np.ndarray,
        point_idx: np.ndarray,
        xy: np.ndarray,
        free_cam: np.ndarray,
        group: np.ndarray,
        free_point: np.ndarray,
    ) -> None:
        """Cameras [C], points [P], observations [O] as :func:`bundle_adjust` takes them; ``free_cam`` [C] and
        ``free_point`` [P] bool say which are adjusted, ``group`` [C] the focal group ids (-1: focal fixed)."""
        self.R0, self.t0, self.K0, self.X0 = R, t, K, points
        C, P = R.shape[0], points.shape[0]
        used = free_point[point_idx]
        self.cam, self.pt, self.xy = cam_idx[used], point_idx[used], xy[used]
        self.free_cams = np.flatnonzero(free_cam)
        self.cam_slot = np.full(C, -1)
        self.cam_slot[self.free_cams] = np.arange(self.free_cams.size)
        groups, self.group = np.unique(group, return_inverse=True)  # compact the ids ≥ 0 to 0..G−1
        self.group = np.where(group >= 0, self.group - int((groups < 0).any()), -1)
        self.n_groups = int((groups >= 0).sum())
        self.free_points = np.flatnonzero(free_point)
        self.point_slot = np.full(P, -1)
        self.point_slot[self.free_points] = np.arange(self.free_points.size)
        self.off_focal = 6 * self.free_cams.size
        self.off_point = self.off_focal + self.n_groups
        self.n_params = self.off_point + 3 * self.free_points.size
        self._structure()

    def _structure(self) -> None:
        """Columns [O, 10] of each observation's two rows (δ, t, s, X), which of them exist, and the CSR arrays."""
        cs, g, ps = self.cam_slot[self.cam], self.group[self.cam], self.point_slot[self.pt]
        cam_cols = 6 * cs[:, None] + np.arange(6)
        point_cols = self.off_point + 3 * ps[:, None] + np.arange(3)
        cols = np.concatenate([cam_cols, (self.off_focal + g)[:, None], point_cols], axis=1)
        mask = np.concatenate([np.repeat((cs >= 0)[:, None], 6, 1), (g >= 0)[:, None], np.ones((len(cs), 3), bool)], 1)
        self.mask2 = np.repeat(mask[:, None, :], 2, axis=1)  # [O, 2, 10]
        self.indices = np.repeat(cols[:, None, :], 2, axis=1)[self.mask2]
        self.indptr = np.concatenate([[0], np.cumsum(np.repeat(mask.sum(1), 2))])
        self.shape = (2 * len(cs), self.n_params)

    def x0(self) -> np.ndarray:
        x = np.zeros(self.n_params)
        x[: self.off_focal].reshape(-1, 6)[:, 3:] = self.t0[self.free_cams]
        x[self.off_point :] = self.X0[self.free_points].ravel()
        return x

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(R, t, K, X, δ, s)`` from the parameters ``x``: every camera and point, fixed ones included."""
        cams = x[: self.off_focal].reshape(-1, 6)
        d = np.zeros((self.R0.shape[0], 3))
        d[self.free_cams] = cams[:, :3]
        t = self.t0.copy()
        t[self.free_cams] = cams[:, 3:]
        s = np.zeros(self.R0.shape[0])
        s[self.group >= 0] = x[self.off_focal : self.off_point][self.group[self.group >= 0]]
        K = self.K0.copy()
        K[:, :2, :2] *= np.exp(s)[:, None, None]
        X = self.X0.copy()
        X[self.free_points] = x[self.off_point :].reshape(-1, 3)
        Rd, _ = _rodrigues(d)
        return Rd @ self.R0, t, K, X, d, s

    def residuals(self, x: np.ndarray) -> np.ndarray:
        R, t, K, X, _, _ = self.unpack(x)
        p = np.einsum("oij,oj->oi", R[self.cam], X[self.pt]) + t[self.cam]
        pix = np.einsum("oij,oj->oi", K[self.cam][:, :2, :], p) / p[:, 2:3]
        return (pix - self.xy).ravel()

    def jacobian(self, x: np.ndarray) -> sp.csr_matrix:
        """The analytic Jacobian [2O, n_params] (module docstring), as CSR on the structure of :meth:`_structure`."""
        import scipy.sparse as sp

        return sp.csr_matrix((self.blocks(x)[self.mask2], self.indices, self.indptr), shape=self.shape)

    def blocks(self, x: np.ndarray) -> np.ndarray:
        """Each observation's two Jacobian rows over its columns ``(δ, t, s, X)`` [O, 2, 10], those of a fixed camera
        or focal included (:meth:`columns` says which exist)."""
        R, t, K, X, d, _ = self.unpack(x)
        _, Jl = _rodrigues(d)
        Ro = R[self.cam]
        RX = np.einsum("oij,oj->oi", Ro, X[self.pt])
        p = RX + t[self.cam]
        iz = 1.0 / p[:, 2]
        n = p[:, :2] * iz[:, None]
        dn = np.zeros((len(p), 2, 3))
        dn[:, 0, 0] = dn[:, 1, 1] = iz
        dn[:, :, 2] = -n * iz[:, None]
        A = K[self.cam][:, :2, :2]
        Jp = A @ dn  # [O, 2, 3]
        return np.concatenate(
            [-Jp @ _skew(RX) @ Jl[self.cam], Jp, np.einsum("oij,oj->oi", A, n)[:, :, None], Jp @ Ro], axis=2
        )

    def columns(self) -> tuple[np.ndarray, np.ndarray]:
        """``(camera columns [O, 7], point slot [O])``: the parameter of each observation's camera and focal entries of
        :meth:`blocks` (−1 where fixed), and the index of its point among the adjusted ones."""
        cs, g = self.cam_slot[self.cam], self.group[self.cam]
        cols = np.concatenate([6 * cs[:, None] + np.arange(6), (self.off_focal + g)[:, None]], axis=1)
        cols[cs < 0, :6] = -1
        cols[g < 0, 6] = -1
        return cols, self.point_slot[self.pt]

    def sparsity(self) -> sp.csr_matrix:
        import scipy.sparse as sp

        return sp.csr_matrix((np.ones(self.indices.size), self.indices, self.indptr), shape=self.shape)


def _solve(prob: _Problem, cfg: BundleConfig):  # noqa: ANN202  (scipy's OptimizeResult, or SchurResult)
    """``cfg.solver`` on ``prob`` from its start, as the module docstring says (``x``, ``nfev`` and, for scipy's,
    ``status``)."""
    analytic = cfg.jacobian == "analytic"
    if cfg.solver == "schur" and analytic:
        return solve_schur(prob, prob.x0(), loss_scale=cfg.loss_scale_px, ftol=cfg.ftol, xtol=cfg.xtol, gtol=cfg.gtol,
                           max_evaluations=cfg.max_evaluations)  # fmt: skip
    from scipy.optimize import least_squares

    return least_squares(
        prob.residuals,
        prob.x0(),
        jac=prob.jacobian if analytic else cfg.jacobian,
        jac_sparsity=None if analytic else prob.sparsity(),
        method="trf",
        loss=_huber_gauss_newton,
        f_scale=cfg.loss_scale_px,
        x_scale="jac",
        ftol=cfg.ftol,
        xtol=cfg.xtol,
        gtol=cfg.gtol,
        max_nfev=cfg.max_evaluations,
        tr_solver="lsmr",
        tr_options={"maxiter": cfg.lsmr_max_iterations},
    )


def _centres(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centres ``−Rᵀ t`` [C, 3]."""
    return -np.einsum("cji,cj->ci", R, t)


def _scale_reference(R: np.ndarray, t: np.ndarray, fixed: np.ndarray) -> tuple[int, int] | None:
    """``(anchor, reference)``: the first fixed camera and the first free camera at a non-zero distance from it,
    when the fixed cameras share one centre (the scale is free); None when the fixed poses fix the scale or no free
    camera has a baseline. "Non-zero" is above 1e-9 of the cameras' largest distance from the anchor."""
    centres = _centres(R, t)
    anchor = int(np.flatnonzero(fixed)[0])
    dist = np.linalg.norm(centres - centres[anchor], axis=1)
    tol = 1e-9 * max(float(dist.max()), 1e-300)
    if (dist[fixed] > tol).any():
        return None
    candidates = np.flatnonzero(~fixed & (dist > tol))
    return (anchor, int(candidates[0])) if candidates.size else None


def _restore_scale(
    R: np.ndarray, t: np.ndarray, X: np.ndarray, free: np.ndarray, anchor: int, ref: int, distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(t, X)`` after the similarity ``Y ↦ C_a + λ (Y − C_a)`` about the anchor's centre ``C_a`` that makes
    ``‖C_ref − C_a‖ = distance``: centres and points scale about ``C_a``, rotations stay, so every camera-frame point
    is ``λ`` times itself and the reprojections are unchanged; cameras at ``C_a`` (the fixed ones) keep their pose."""
    centres = _centres(R, t)
    ca = centres[anchor]
    now = float(np.linalg.norm(centres[ref] - ca))
    if not now > 0:
        return t, X
    lam = distance / now
    new_c = ca + lam * (centres - ca)
    t_new = np.where(free[:, None], -np.einsum("cij,cj->ci", R, new_c), t)
    return t_new, ca + lam * (X - ca)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else 0.0


def _options(
    C: int, fixed_pose: np.ndarray | None, focal_group: np.ndarray | None, cfg: BundleConfig
) -> tuple[np.ndarray, np.ndarray]:
    """``(fixed [C] bool, group [C] int)`` with their defaults (camera 0 fixed, no focal adjusted), checked with
    ``cfg``."""
    fixed = np.zeros(C, bool) if fixed_pose is None else np.asarray(fixed_pose, dtype=bool)
    if fixed_pose is None and C:
        fixed[0] = True
    group = np.full(C, -1, np.int64) if focal_group is None else np.asarray(focal_group, dtype=np.int64)
    if fixed.shape != (C,):
        raise ShapeError("fixed_pose", fixed.shape, "[C]")
    if group.shape != (C,):
        raise ShapeError("focal_group", group.shape, "[C]")
    if not fixed.any():
        raise ValueError("bundle_adjust needs at least one fixed pose (the gauge of rotation and translation)")
    if cfg.jacobian not in ("analytic", "2-point"):
        raise ValueError(f'BundleConfig.jacobian must be "analytic" or "2-point", not {cfg.jacobian!r}')
    if cfg.solver not in ("schur", "lsmr"):
        raise ValueError(f'BundleConfig.solver must be "schur" or "lsmr", not {cfg.solver!r}')
    return fixed, group


def bundle_adjust(
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    points: np.ndarray,
    cam_idx: np.ndarray,
    point_idx: np.ndarray,
    xy: np.ndarray,
    *,
    fixed_pose: np.ndarray | None = None,
    focal_group: np.ndarray | None = None,
    config: BundleConfig | None = None,
) -> BundleResult:
    """Refine poses, points and focal groups on the robust reprojection error (module docstring).

    Args:
        R, t: world → camera poses. [C, 3, 3], [C, 3]
        K: intrinsics (pixel centres at +0.5). [C, 3, 3]
        points: world points. [P, 3]
        cam_idx, point_idx: camera and point of each observation. [O] each
        xy: observed pixels. [O, 2]
        fixed_pose: poses kept as given (default: camera 0 only); at least one. [C] bool
        focal_group: focal parameter of each camera: -1 keeps its focal, cameras with the same id ≥ 0 share one
            log-focal multiplier (default: all -1). [C] int
        config: :class:`BundleConfig`.

    Returns:
        :class:`BundleResult`. A free camera without an observation of an adjusted point keeps its pose (up to the
        scale gauge); its focal follows its group.

    Raises:
        ShapeError, NonFiniteError: malformed inputs; ValueError: an index out of range, no fixed pose, or an
        observation at depth 0 at the start.
    """
    start = time.perf_counter()
    cfg = config or BundleConfig()
    R, t, K, X, xy = (np.asarray(a, dtype=np.float64) for a in (R, t, K, points, xy))
    cam_idx, point_idx = np.asarray(cam_idx, dtype=np.int64), np.asarray(point_idx, dtype=np.int64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ShapeError("points", X.shape, "[P, 3]")
    if not np.isfinite(X).all():
        raise NonFiniteError(f"points holds {int((~np.isfinite(X)).sum())} non-finite value(s) (NaN or Inf)")
    _check_inputs(R, t, K, cam_idx, point_idx, xy, X.shape[0])
    fixed, group = _options(R.shape[0], fixed_pose, focal_group, cfg)

    before = reprojection_errors(R, t, K, X, cam_idx, point_idx, xy)
    free_point = np.bincount(point_idx, minlength=X.shape[0]) >= cfg.min_observations
    used = free_point[point_idx]
    free_cam = ~fixed & (np.bincount(cam_idx[used], minlength=R.shape[0]) > 0)
    prob = _Problem(R, t, K, X, cam_idx, point_idx, xy, free_cam, group, free_point)
    evaluations, success = 0, True
    R1, t1, K1, X1 = R, t, K, X
    if prob.n_params and prob.cam.size:
        if not np.all(np.isfinite(prob.residuals(prob.x0()))):
            raise ValueError("an observation is at depth 0 in its camera at the start: its reprojection is undefined")
        sol = _solve(prob, cfg)
        R1, t1, K1, X1, _, _ = prob.unpack(sol.x)
        evaluations, success = int(sol.nfev), bool(sol.success)
        gauge = _scale_reference(R, t, fixed)
        if gauge is not None:
            anchor, ref = gauge
            distance = float(np.linalg.norm(_centres(R, t)[ref] - _centres(R, t)[anchor]))
            t1, X1 = _restore_scale(R1, t1, X1, ~fixed, anchor, ref, distance)
    after = reprojection_errors(R1, t1, K1, X1, cam_idx, point_idx, xy)
    return BundleResult(
        R=R1,
        t=t1,
        K=K1,
        points=X1,
        rms_before_px=_rms(before),
        rms_after_px=_rms(after),
        residual_px=after,
        evaluations=evaluations,
        seconds=time.perf_counter() - start,
        success=success,
    )


def compile_kernels() -> None:
    """Compile (or load from the cache) the Schur complement's Numba kernel now: for a background thread."""
    from . import _schur_kernels

    _schur_kernels.compile_kernels()
