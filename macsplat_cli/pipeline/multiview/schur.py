"""Levenberg-Marquardt for the bundle adjustment with the points eliminated (the Schur complement on the cameras).

The bundle adjustment's normal equations ``H δ = −g`` have an arrow structure: each point's 3 × 3 block couples it
only with the cameras that see it. Eliminating the points leaves the reduced camera system
``(H_cc − H_cp H_pp⁻¹ H_pc) δ_c = −g_c + H_cp H_pp⁻¹ g_p`` of size ``6 · cameras + focal groups`` (~200 at 32 photos),
solved exactly; the points follow as ``δ_p = H_pp⁻¹ (−g_p − H_pc δ_c)`` (Triggs et al. 2000, "Bundle adjustment — a
modern synthesis", §6.1; what Ceres' ``DENSE_SCHUR`` does). Each step is the exact damped Gauss-Newton step, where
scipy's trust-region solver took ~90 LSMR iterations a step for an inexact one (history/multiview_scaling.md).

The robust loss is Huber's per residual coordinate, reweighted (IRLS: ``H = Jᵀ diag(ρ') J``, ``g = Jᵀ (ρ' r)``, the
curvature of :func:`.bundle._huber_gauss_newton`), its cost scipy's ``0.5 · s² · Σ ρ((r / s)²)``. Damping: Marquardt's
``λ · diag(H)`` (scale-free, as scipy's ``x_scale="jac"``), ``λ`` ÷ 10 after a step that lowers the cost, × 10 after
one that does not. It stops on ``ftol`` (a step lowered the cost by less than that fraction), ``xtol`` (the step
below that fraction of the parameters' norm), ``gtol`` (the largest entry of the gradient scaled by the diagonal's
root) or after ``max_evaluations`` residual evaluations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["SchurResult", "schur_term_reference", "solve_schur"]

LAMBDA_START = 1e-4
"""Marquardt's damping at the start, relative to the diagonal: the start is usually close (a pose from the pairs)."""
LAMBDA_MIN = 1e-10
"""The damping never falls below this: the scale gauge (free when the fixed cameras share a centre) leaves the
reduced system singular along one direction, which the damping keeps solvable."""
LAMBDA_MAX = 1e10
"""Above this damping no step can lower the cost: the solve stops (at a minimum up to rounding)."""
DIAG_FLOOR = 1e-12
"""A diagonal entry of ``H`` is damped as at least this (a parameter no residual moves still gets a finite step)."""


class _Problem(Protocol):
    off_point: int

    def residuals(self, x: np.ndarray) -> np.ndarray: ...

    def blocks(self, x: np.ndarray) -> np.ndarray: ...

    def columns(self) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass
class SchurResult:
    """The solve's end: parameters ``x`` [n], residual evaluations, and whether a tolerance stopped it."""

    x: np.ndarray
    nfev: int
    success: bool


def _huber(r: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
    """``(cost, ρ')``: scipy's Huber cost ``0.5 s² Σ ρ(z)``, ``z = (r / s)²``, and the IRLS weight of each residual."""
    z = (r / scale) ** 2
    far = z > 1
    root = np.sqrt(z[far])
    rho = z.copy()
    rho[far] = 2 * root - 1
    w = np.ones_like(z)
    w[far] = 1 / root
    return 0.5 * scale**2 * float(rho.sum()), w


class _Layout:
    """Where each observation's entries of the normal equations go: its camera columns ``cc`` [O, 7] (the dummy
    column ``nc`` where fixed), its point ``pt`` [O], and the observations sorted by point (``order`` [O], point
    ``p``'s at ``order[starts[p]:starts[p + 1]]``)."""

    def __init__(self, prob: _Problem) -> None:
        cols, self.pt = prob.columns()
        self.nc = prob.off_point
        self.cc = np.where(cols >= 0, cols, self.nc)
        self.n_pts = int(self.pt.max()) + 1 if self.pt.size else 0
        self.flat_cc = (self.cc[:, :, None] * (self.nc + 1) + self.cc[:, None, :]).ravel()
        self.order = np.argsort(self.pt, kind="stable")
        self.starts = np.concatenate([[0], np.cumsum(np.bincount(self.pt, minlength=self.n_pts))])

    def per_point(self, v: np.ndarray) -> np.ndarray:
        """Sum of ``v`` [O, ...] over each point's observations → [P, ...]."""
        flat = v.reshape(len(v), -1)
        out = [np.bincount(self.pt, weights=flat[:, k], minlength=self.n_pts) for k in range(flat.shape[1])]
        return np.stack(out, 1).reshape((self.n_pts, *v.shape[1:]))

    def to_cams(self, v: np.ndarray) -> np.ndarray:
        """Sum of ``v`` [O, 7] into the camera parameters → [nc]."""
        return np.bincount(self.cc.ravel(), weights=v.ravel(), minlength=self.nc + 1)[: self.nc]

    def schur_term(self, Y: np.ndarray, W: np.ndarray) -> np.ndarray:
        """``H_cp H_pp⁻¹ H_pc`` [nc, nc] from ``Y = W V⁻¹`` and ``W`` [O, 7, 3] (:mod:`._schur_kernels`)."""
        from . import _schur_kernels  # Numba on first use

        out = np.zeros((self.nc + 1, self.nc + 1))
        _schur_kernels.schur_term(self.order, self.starts, self.cc, np.ascontiguousarray(Y), np.ascontiguousarray(W),
                                  out)  # fmt: skip
        return out[: self.nc, : self.nc]


def schur_term_reference(lay: _Layout, Y: np.ndarray, W: np.ndarray) -> np.ndarray:
    """The NumPy twin of :meth:`_Layout.schur_term`: every pair of observations of a point gathered, multiplied and
    scattered at once. [nc, nc]"""
    n_of = np.diff(lay.starts)[lay.pt[lay.order]]  # each sorted observation's track length
    pos = np.repeat(np.arange(lay.order.size), n_of)  # o1's place in ``order``, once per partner
    first = np.repeat(np.cumsum(n_of) - n_of, n_of)
    o1 = lay.order[pos]
    o2 = lay.order[lay.starts[lay.pt[o1]] + np.arange(pos.size) - first]
    prod = Y[o1] @ W[o2].transpose(0, 2, 1)  # [pairs, 7, 7]
    flat = lay.cc[o1][:, :, None] * (lay.nc + 1) + lay.cc[o2][:, None, :]
    out = np.bincount(flat.ravel(), weights=prod.ravel(), minlength=(lay.nc + 1) ** 2)
    return out.reshape(lay.nc + 1, lay.nc + 1)[: lay.nc, : lay.nc]


class _Normal:
    """The normal equations at one point ``x`` (``H = Jᵀ W J``, ``g = Jᵀ W r``), kept by blocks: the cameras' dense
    ``H_cc`` [nc, nc], the camera-point blocks of each observation [O, 7, 3] and the points' ``H_pp`` [P, 3, 3]."""

    def __init__(self, lay: _Layout, blocks: np.ndarray, r: np.ndarray, w: np.ndarray) -> None:
        nc = lay.nc
        self.lay = lay
        w2, wr = w.reshape(-1, 2, 1), (w * r).reshape(-1, 2, 1)
        C, P = blocks[:, :, :7], blocks[:, :, 7:]  # [O, 2, 7], [O, 2, 3]
        wCt = (C * w2).transpose(0, 2, 1)  # [O, 7, 2]
        Hcc = np.bincount(lay.flat_cc, weights=(wCt @ C).ravel(), minlength=(nc + 1) ** 2)
        self.Hcc = Hcc.reshape(nc + 1, nc + 1)[:nc, :nc]
        self.W = wCt @ P  # [O, 7, 3]
        self.V = lay.per_point((P * w2).transpose(0, 2, 1) @ P)
        self.gc = lay.to_cams((C * wr).sum(1))
        self.gp = lay.per_point((P * wr).sum(1))  # [P, 3]
        self.dc = np.maximum(np.diag(self.Hcc), DIAG_FLOOR)
        self.dp = np.maximum(np.diagonal(self.V, axis1=1, axis2=2), DIAG_FLOOR)  # [P, 3]

    @property
    def scaled_gradient(self) -> float:
        """Largest entry of the gradient over the root of the diagonal (scale-free)."""
        return max(np.max(np.abs(self.gc) / np.sqrt(self.dc), initial=0.0),
                   np.max(np.abs(self.gp) / np.sqrt(self.dp), initial=0.0))  # fmt: skip

    def step(self, lam: float) -> np.ndarray:
        """The damped Gauss-Newton step ``(H + λ diag(H)) δ = −g`` through the Schur complement. [n]"""
        lay, nc = self.lay, self.lay.nc
        Vinv = np.linalg.inv(self.V + (lam * self.dp)[:, :, None] * np.eye(3))
        dc = np.zeros(0)
        if nc:
            Y = self.W @ Vinv[lay.pt]  # [O, 7, 3]
            S = self.Hcc + np.diag(lam * self.dc) - lay.schur_term(Y, self.W)
            dc = np.linalg.solve(S, -self.gc + lay.to_cams((Y @ self.gp[lay.pt][:, :, None])[:, :, 0]))
        dce = np.concatenate([dc, [0.0]])[lay.cc]  # [O, 7]
        back = lay.per_point((dce[:, None, :] @ self.W)[:, 0])  # Σ Wᵀ δc per point [P, 3]
        dp = (Vinv @ (-self.gp - back)[:, :, None])[:, :, 0]
        return np.concatenate([dc, dp.ravel()])


def solve_schur(
    prob: _Problem, x0: np.ndarray, *, loss_scale: float, ftol: float, xtol: float, gtol: float, max_evaluations: int
) -> SchurResult:
    """Minimise ``prob``'s robust reprojection cost from ``x0`` (module docstring). ``prob``: the residuals [m] and
    their sparse Jacobian [m, n] of the parameters ``[cameras and focal groups | points (3 each)]``, the points from
    column ``prob.off_point``."""
    x = x0.copy()
    r = prob.residuals(x)
    cost, w = _huber(r, loss_scale)
    nfev, lam = 1, LAMBDA_START
    lay = _Layout(prob)
    normal = _Normal(lay, prob.blocks(x), r, w)
    while nfev < max_evaluations:
        if normal.scaled_gradient < gtol:
            return SchurResult(x, nfev, True)
        with np.errstate(all="ignore"):
            try:
                dx = normal.step(lam)
            except np.linalg.LinAlgError:
                dx = np.full_like(x, np.nan)
            x_new = x + dx
            r_new = prob.residuals(x_new) if np.all(np.isfinite(dx)) else np.full_like(r, np.nan)
        nfev += 1
        cost_new = _huber(r_new, loss_scale)[0] if np.all(np.isfinite(r_new)) else np.inf
        if not cost_new < cost:
            lam *= 10.0
            if lam > LAMBDA_MAX:
                return SchurResult(x, nfev, True)
            continue
        small_step = np.linalg.norm(dx) < xtol * (xtol + np.linalg.norm(x))
        converged = cost - cost_new < ftol * cost
        x, r, cost = x_new, r_new, cost_new
        if small_step or converged:
            return SchurResult(x, nfev, True)
        lam = max(lam / 10.0, LAMBDA_MIN)
        w = _huber(r, loss_scale)[1]
        normal = _Normal(lay, prob.blocks(x), r, w)
    return SchurResult(x, nfev, False)
