"""Two-view geometry for the relative pose refinement (:mod:`flight_sw.pose_refine`, issue #10).

Rotations by the exponential map (Rodrigues), the relative pose of two world
poses ``R21 = R2 R1^T``, ``t21 = R2 (C1 - C2)``, its fundamental matrix
``F = K^-T [t21]x R21 K^-1`` (Hartley & Zisserman 2004, eq. 9.2), first-order
geometric errors of a match under ``F`` and under a homography (Sampson, H&Z
eq. 4.10 and 11.9), Torr's model-selection score GRIC (1998), and depths by
midpoint triangulation. Arrays in, arrays out.
"""

from __future__ import annotations

import math

import numpy as np

from protocol.pairdir import Pose


def skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x``, the cross-product matrix: ``skew(v) @ u = v x u``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rot_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation by ``|w|`` about ``w``."""
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3) + skew(w)
    k = skew(np.asarray(w, float) / th)
    return np.eye(3) + math.sin(th) * k + (1.0 - math.cos(th)) * (k @ k)


def rot_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation (inverse of :func:`rot_exp` for angles < pi)."""
    c = (float(np.trace(R)) - 1.0) / 2.0
    th = math.acos(min(1.0, max(-1.0, c)))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    if th < 1e-9:
        return v
    return v * (th / math.sin(th))


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of a rotation, ``|log R|`` (:func:`rot_log`), in degrees."""
    return math.degrees(float(np.linalg.norm(rot_log(R))))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """``acos(a . b / (|a| |b|))`` in degrees (clipped: rounding cannot leave acos's domain)."""
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def tangent_basis(b: np.ndarray) -> np.ndarray:
    """3x2 orthonormal basis of the plane orthogonal to the unit vector ``b``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(b[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = skew(b) @ a
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, skew(b) @ e1], axis=1)


# --------------------------------------------------------------------------- two-view geometry
def relative_pose(pose1: Pose, pose2: Pose) -> tuple[np.ndarray, np.ndarray]:
    """``(R21, t21)`` with ``X2 = R21 X1 + t21`` (DESIGN.md): ``R21 = R2 R1^T``, ``t21 = R2 (C1 - C2)``."""
    return pose2.R @ pose1.R.T, pose2.R @ (pose1.position - pose2.position)


def fundamental(K: np.ndarray, R21: np.ndarray, t21: np.ndarray) -> np.ndarray:
    """``F = K^-T [t]x R K^-1`` (H&Z eq. 9.12 with ``E = [t]x R``, eq. 9.13)."""
    Ki = np.linalg.inv(K)
    return Ki.T @ skew(t21) @ R21 @ Ki


def homog(u: np.ndarray) -> np.ndarray:
    """Nx2 pixels -> Nx3 homogeneous."""
    return np.concatenate([u, np.ones((len(u), 1))], axis=1)


def sampson_px(F: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Signed Sampson distance (px, H&Z eq. 11.9).

    ``r = x2^T F x1 / sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2)``.

    ``u1``, ``u2``: Nx2 pixels or Nx3 homogeneous pixels.
    """
    x1 = u1 if u1.shape[1] == 3 else homog(u1)
    x2 = u2 if u2.shape[1] == 3 else homog(u2)
    Fx1 = x1 @ F.T
    Ftx2 = x2 @ F
    num = np.sum(x2 * Fx1, axis=1)
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.asarray(num / np.sqrt(np.maximum(den, 1e-300)))


def homography_sampson_px(H: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Sampson error of correspondences to a homography (H&Z sec 4.2.6), px: ``sqrt(e^T (J J^T)^-1 e)``.

    ``e`` are the two first rows of ``x2 x (H x1)`` and ``J`` their derivatives
    with respect to ``(u1, v1, u2, v2)``.
    """
    x, y = u1[:, 0], u1[:, 1]
    X, Y = u2[:, 0], u2[:, 1]
    h = H.ravel()
    a = h[0] * x + h[1] * y + h[2]
    b = h[3] * x + h[4] * y + h[5]
    c = h[6] * x + h[7] * y + h[8]
    e1 = b - Y * c  # row of x2 x Hx1 (up to sign)
    e2 = X * c - a
    j1 = np.stack([h[3] - Y * h[6], h[4] - Y * h[7], np.zeros_like(x), -c], axis=1)
    j2 = np.stack([X * h[6] - h[0], X * h[7] - h[1], c, np.zeros_like(x)], axis=1)
    A = np.sum(j1 * j1, 1)
    B = np.sum(j1 * j2, 1)
    C = np.sum(j2 * j2, 1)
    det = np.maximum(A * C - B * B, 1e-300)
    q = (C * e1 * e1 - 2 * B * e1 * e2 + A * e2 * e2) / det
    return np.asarray(np.sqrt(np.maximum(q, 0.0)))


def gric(err_px: np.ndarray, sigma_px: float, d: int, k: int) -> float:
    """Torr's Geometric Robust Information Criterion (1998), ``r = 4`` (two image points per match)."""
    n = err_px.size
    r = 4
    rho = np.minimum((err_px / sigma_px) ** 2, 2.0 * (r - d))
    return float(rho.sum() + math.log(r) * d * n + math.log(r * n) * k)


def triangulate_depths(R21: np.ndarray, t21: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Camera-1 depth ``z`` of each normalised match: least squares of ``x2 x (z R21 x1 + t21) = 0``."""
    c = np.cross(x2, x1 @ R21.T)
    d = np.cross(x2, np.broadcast_to(t21, x2.shape))
    return np.asarray(-np.sum(c * d, 1) / np.maximum(np.sum(c * c, 1), 1e-300))


def axis_depth(x: np.ndarray, z: np.ndarray, radius: float = 0.08) -> float:
    """Depth on the optical axis from scattered depths: weighted LS of ``1/z = a x + b y + c``, returns ``1/c``.

    Inverse depth is exactly linear in normalised coordinates over a plane, so
    the fit follows the terrain's mean plane; Gaussian weights of ``radius``
    (rad) keep it local to the axis. NaN when the fit is not possible.
    """
    ok = np.isfinite(z) & (z > 0)
    if ok.sum() < 6:
        return math.nan
    xs, zs = x[ok], z[ok]
    w = np.exp(-0.5 * (xs[:, 0] ** 2 + xs[:, 1] ** 2) / radius**2)
    A = np.c_[xs[:, 0], xs[:, 1], np.ones(len(xs))] * w[:, None]
    sol, *_ = np.linalg.lstsq(A, w / zs, rcond=None)
    return float(1.0 / sol[2]) if sol[2] > 0 else math.nan
