"""Nonlinear (MAP) refinement of a relative pose (:mod:`flight_sw.pose_refine`, step 3).

Over the two attitudes ``R1, R2`` and the unit world baseline direction ``b``
(8 unknowns: two rotation increments and a tangent step of ``b``),
Levenberg-Marquardt (Hartley & Zisserman 2004, A6.2) minimises
``sum rho(r_i / sigma) + |prior|^2``: Cauchy-weighted Sampson errors ``r_i``
(H&Z eq. 11.9) of ``F = K^-T [t]x R21 K^-1`` with ``R21 = R2 R1^T``,
``t = -R2 b``, plus whitened Gaussian navigation priors on frame 1's attitude
error, the error frame 2 adds to it, and the baseline direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .twoview import fundamental, homog, rot_exp, rot_log, sampson_px, skew, tangent_basis


@dataclass
class MotionState:
    R1: np.ndarray
    R2: np.ndarray
    b: np.ndarray  # unit world baseline direction C2 - C1

    def step(self, d: np.ndarray) -> MotionState:
        b = self.b + tangent_basis(self.b) @ d[6:8]
        return MotionState(rot_exp(d[0:3]) @ self.R1, rot_exp(d[3:6]) @ self.R2, b / np.linalg.norm(b))


def relative_whitening(nav: MotionState, s_r: float, s_axis: float | None) -> np.ndarray | None:
    """Whitening of the relative-rotation prior when its sd differs about frame 1's optical axis: ``W r`` with
    ``W = diag(1/s_r, 1/s_r, 1/s_axis) R1`` (``R1``'s rows are frame 1's camera axes in world coordinates, the
    third its optical axis). None when the prior is isotropic (``s_axis`` None or ``s_r``): ``r / s_r``."""
    if s_axis is None or s_axis == s_r:
        return None
    return np.diag([1.0 / s_r, 1.0 / s_r, 1.0 / s_axis]) @ nav.R1


def _prior_residuals(
    s: MotionState, nav: MotionState, B_nav: np.ndarray, sig: tuple[float, float, float], W: np.ndarray | None
) -> np.ndarray:
    """Whitened navigation priors (world axes): frame-1 attitude error ``e1 = c``, frame-2 error ``e2 = c + r``
    (``c`` common to both frames, ``r`` accrued between them; ``W r`` with :func:`relative_whitening`'s ``W``
    where given), and the baseline direction."""
    e1 = nav.R1.T @ rot_log(s.R1 @ nav.R1.T)
    e2 = nav.R2.T @ rot_log(s.R2 @ nav.R2.T)
    s_c, s_r, s_dir = sig
    rel = (e2 - e1) / s_r if W is None else W @ (e2 - e1)
    return np.r_[e1 / s_c, rel, (B_nav.T @ s.b) / s_dir]


def _data_residuals(s: MotionState, K: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    R21 = s.R2 @ s.R1.T
    return sampson_px(fundamental(K, R21, -s.R2 @ s.b), u1, u2)


def _f_derivatives(s: MotionState, K: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """``F`` of the state and its derivatives along the 8 increments of :meth:`MotionState.step`.

    ``R1 <- exp(d1) R1`` gives ``dR21 = -R21 [e_k]x``; ``R2 <- exp(d2) R2`` gives
    ``dR21 = [e_k]x R21`` and ``dt = [e_k]x t``; ``b <- b + B e`` gives ``dt = -R2 B_k``;
    with ``E = [t]x R21``, ``dE = [dt]x R21 + [t]x dR21``.
    """
    Ki = np.linalg.inv(K)
    R21 = s.R2 @ s.R1.T
    t = -s.R2 @ s.b
    B = tangent_basis(s.b)
    tx = skew(t)
    dE = []
    for k in range(3):
        G = skew(np.eye(3)[k])
        dE.append(tx @ (-R21 @ G))
    for k in range(3):
        G = skew(np.eye(3)[k])
        dE.append(skew(G @ t) @ R21 + tx @ G @ R21)
    for k in range(2):
        dE.append(skew(-s.R2 @ B[:, k]) @ R21)
    return Ki.T @ tx @ R21 @ Ki, [Ki.T @ d @ Ki for d in dE]


def map_refine(
    K: np.ndarray,
    u1: np.ndarray,
    u2: np.ndarray,
    nav: MotionState,
    prior_sigmas: tuple[float, float, float],
    sigma_px: float,
    cauchy_k: float,
    max_iterations: int,
    start: MotionState | None = None,
    axis_sigma: float | None = None,
) -> tuple[MotionState, np.ndarray, np.ndarray, int, bool]:
    """Levenberg-Marquardt on ``sum rho(r_i / sigma_px) + |prior|^2`` with Cauchy ``rho`` (IRLS weights).

    ``axis_sigma``: the relative rotation's prior sd about frame 1's optical axis, where it differs from
    ``prior_sigmas[1]`` (:func:`relative_whitening`). Returns the state, the data residuals (px), the 8x8
    posterior covariance (rad^2), the iterations and whether the step converged.
    """
    B_nav = tangent_basis(nav.b)
    W = relative_whitening(nav, prior_sigmas[1], axis_sigma)
    c = cauchy_k
    u1, u2 = homog(u1), homog(u2)

    def cost(s: MotionState) -> tuple[float, np.ndarray, np.ndarray]:
        r = _data_residuals(s, K, u1, u2) / sigma_px
        q = _prior_residuals(s, nav, B_nav, prior_sigmas, W)
        return float(c * c * np.log1p((r / c) ** 2).sum() + q @ q), r, q

    s = start or nav
    f0, r, q = cost(s)
    lam, h = 1e-3, 1e-7
    converged = False
    it = 0
    J = np.zeros((r.size, 8))
    Jq = np.zeros((q.size, 8))
    w = np.ones(r.size)
    s_c, s_r, s_dir = prior_sigmas
    for it in range(1, max_iterations + 1):  # noqa: B007 (it is returned)
        F, dF = _f_derivatives(s, K)
        for k in range(8):  # data: central differences of the Sampson error along dF/dp_k
            J[:, k] = (sampson_px(F + h * dF[k], u1, u2) - sampson_px(F - h * dF[k], u1, u2)) / (2 * h * sigma_px)
        # priors: first-order derivatives (d log(exp(d) R) ~ d for the sub-degree errors at stake)
        Jq[0:3, 0:3] = nav.R1.T / s_c
        if W is None:
            Jq[3:6, 0:3] = -nav.R1.T / s_r
            Jq[3:6, 3:6] = nav.R2.T / s_r
        else:
            Jq[3:6, 0:3] = -W @ nav.R1.T
            Jq[3:6, 3:6] = W @ nav.R2.T
        Jq[6:8, 6:8] = B_nav.T @ tangent_basis(s.b) / s_dir
        w = 1.0 / (1.0 + (r / c) ** 2)
        A = J.T @ (J * w[:, None]) + Jq.T @ Jq
        g = J.T @ (w * r) + Jq.T @ q
        f_prev = f0
        while True:
            dp = -np.linalg.solve(A + lam * np.diag(np.diag(A)) + 1e-12 * np.eye(8), g)
            s_new = s.step(dp)
            f1, r1, q1 = cost(s_new)
            if f1 <= f0:
                s, f0, r, q = s_new, f1, r1, q1
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
            if lam > 1e8:
                break
        if lam > 1e8:
            converged = True  # no downhill step left: at the minimum to numerical precision
            break
        if np.linalg.norm(dp) < 1e-10 or f_prev - f0 < 1e-10 * max(1.0, f0):
            converged = True
            break
    w = 1.0 / (1.0 + (r / c) ** 2)
    cov = np.linalg.pinv(J.T @ (J * w[:, None]) + Jq.T @ Jq)
    return s, r * sigma_px, cov, it, converged
