"""Scaled orthographic cameras and rotation utilities.

Conventions (see ``docs/conventions.md``):

* Image coordinates: x right, y down, pixel centres at integer coordinates.
* A camera maps object-frame points ``X (..., 3)`` to pixels
  ``uv = s * X @ R[:2].T + t`` and to depth ``z = s * X @ R[2]`` (pixels).
* ``R`` is a proper rotation whose rows are the image x axis, the image y axis
  (down) and the viewing direction (into the scene), written in the object frame:
  the OpenCV / COLMAP camera frame.
* Quaternions are ``(w, x, y, z)`` (kornia's order).
* Azimuth / elevation / roll follow PASCAL3D+ for objects with +z up and their
  front towards -y: azimuth 0, elevation 0 is the frontal view, elevation > 0
  looks down on the object. See :func:`rotation_from_azimuth_elevation_roll`.

All functions broadcast over leading batch dimensions and work on any device.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from kornia.geometry import conversions as kconv

__all__ = [
    "ScaledOrthographic",
    "Similarity2D",
    "nearest_scaled_rotation",
    "scaled_stiefel",
    "complete_rotation",
    "rotation_to_quaternion",
    "quaternion_to_rotation",
    "axis_angle_to_rotation",
    "rotation_to_axis_angle",
    "rotation_from_azimuth_elevation_roll",
    "azimuth_elevation_roll_from_rotation",
    "geodesic_angle",
    "align_rotations",
    "geodesic_errors",
    "rotation_about_axis",
    "random_rotations",
    "FLIP_X",
]

#: Left-right image flip of the camera frame, ``diag(-1, 1, 1)``.
FLIP_X = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))


# --------------------------------------------------------------------------- rotations


def complete_rotation(rows: torch.Tensor) -> torch.Tensor:
    """Complete two orthonormal rows into a proper rotation.

    Args:
        rows: ``(..., 2, 3)`` with orthonormal rows.

    Returns:
        ``(..., 3, 3)`` rotation whose third row is ``rows[..., 0, :] x rows[..., 1, :]``.

    Example:
        >>> complete_rotation(torch.eye(3)[:2])
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    third = torch.linalg.cross(rows[..., 0, :], rows[..., 1, :], dim=-1)
    return torch.cat([rows, third.unsqueeze(-2)], dim=-2)


def nearest_scaled_rotation(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project 2x3 blocks onto the nearest scaled Stiefel matrix ``c * U V^T``.

    ``M = U diag(sigma) V^T`` (thin SVD); the nearest matrix with orthogonal rows
    of equal norm is ``c U V^T`` with ``c`` the mean of the two singular values.

    Args:
        M: ``(..., 2, 3)`` affine camera blocks.

    Returns:
        ``R (..., 3, 3)`` proper rotation (third row the cross product of the first
        two) and ``s (...)`` the scale ``c``, so that ``s * R[..., :2, :]`` is the
        projection of ``M``.

    Example:
        >>> R, s = nearest_scaled_rotation(2.0 * torch.eye(3)[:2])
        >>> float(s)
        2.0
    """
    U, S, Vh = torch.linalg.svd(M, full_matrices=False)  # U (..,2,2) S (..,2) Vh (..,2,3)
    rows = U @ Vh
    return complete_rotation(rows), S.mean(dim=-1)


def scaled_stiefel(M: torch.Tensor) -> torch.Tensor:
    """Nearest scaled Stiefel matrix ``c U V^T`` of ``2x3`` blocks, in closed form.

    Same result as :func:`carvi_torch.cameras.nearest_scaled_rotation` (``s * R[:2]``)
    without a batched SVD: with ``A = M M^T`` and ``delta = sqrt(det A) = sigma_1
    sigma_2``, ``(M M^T)^(-1/2) = adj(A + delta I) / (delta (sigma_1 + sigma_2))``
    (the 2x2 square-root formula), so ``c U V^T = adj(A + delta I) M / (2 delta)``.
    Blocks of rank < 2 (``delta <= 1e-10 tr A``) fall back to the SVD. Differentiable.

    Args:
        M: ``(..., 2, 3)``.

    Returns:
        ``(..., 2, 3)`` with orthogonal rows of equal norm ``c`` (the mean singular value).

    Example:
        >>> scaled_stiefel(torch.tensor([[2.0, 0, 0], [0, 4.0, 0]]))
        tensor([[3., 0., 0.],
                [0., 3., 0.]])
    """
    A = M @ M.transpose(-1, -2)
    a, b, _, d = A.flatten(-2).unbind(-1)  # one view op instead of three indexings
    tr = a + d
    delta = (a * d - b * b).clamp(min=0).sqrt()
    ok = delta > 1e-10 * tr
    # adj(A + delta I) = [[d + delta, -b], [-b, a + delta]] (few ops: this runs in every SfM and camera step)
    nb = -b
    adj = torch.stack([d + delta, nb, nb, a + delta], -1).unflatten(-1, (2, 2))
    out = adj @ M / (2.0 * torch.where(ok, delta, 1.0))[..., None, None]
    if bool(ok.all()):
        return out
    # rank < 2 blocks go through the SVD; non-finite blocks stay non-finite (the SVD would fail)
    fallback = ~ok & torch.isfinite(M).flatten(-2).all(-1)
    if bool(fallback.any()):
        R, s = nearest_scaled_rotation(M[fallback])
        out = out.clone()
        out[fallback] = s[:, None, None] * R[:, :2, :]
    return out


def rotation_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` to unit quaternions ``(..., 4)`` in ``(w, x, y, z)``.

    The sign is chosen with ``w >= 0``. Computed by kornia.

    Example:
        >>> rotation_to_quaternion(torch.eye(3))
        tensor([1., 0., 0., 0.])
    """
    q = kconv.rotation_matrix_to_quaternion(R.contiguous())
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_rotation(q: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(..., 4)`` in ``(w, x, y, z)`` (normalised here) to rotations ``(..., 3, 3)``.

    Example:
        >>> quaternion_to_rotation(torch.tensor([1.0, 0, 0, 0]))
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    q = q / q.norm(dim=-1, keepdim=True)
    return kconv.quaternion_to_rotation_matrix(q)


def axis_angle_to_rotation(v: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors ``(..., 3)`` (angle = norm, radians) to rotations ``(..., 3, 3)``.

    Differentiable at zero (kornia >= 0.9).

    Example:
        >>> axis_angle_to_rotation(torch.zeros(3))
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    shape = v.shape[:-1]
    return kconv.axis_angle_to_rotation_matrix(v.reshape(-1, 3)).reshape(*shape, 3, 3)


def rotation_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotations ``(..., 3, 3)`` to axis-angle vectors ``(..., 3)`` (through the quaternion); the inverse of
    :func:`axis_angle_to_rotation` for angles below pi.

    Example:
        >>> v = torch.tensor([0.0, 0.0, 1.5])
        >>> torch.allclose(rotation_to_axis_angle(axis_angle_to_rotation(v)), v, atol=1e-6)
        True
    """
    return kconv.quaternion_to_axis_angle(rotation_to_quaternion(R))


def rotation_about_axis(axis: torch.Tensor, angle: torch.Tensor | float) -> torch.Tensor:
    """Right-handed rotation by ``angle`` (radians) about unit ``axis``.

    Args:
        axis: ``(..., 3)``; normalised here.
        angle: ``(...)`` or a float.

    Returns:
        ``(..., 3, 3)``.
    """
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.as_tensor(angle, dtype=axis.dtype, device=axis.device)
    return axis_angle_to_rotation(axis * angle.unsqueeze(-1))


def geodesic_angle(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Angle (radians, in ``[0, pi]``) of the relative rotation ``R1 R2^T``.

    Uses ``atan2(||skew||, trace - 1)``, accurate near 0 and near pi.

    Args:
        R1, R2: ``(..., 3, 3)`` broadcastable.

    Returns:
        ``(...)`` angles.

    Example:
        >>> float(geodesic_angle(torch.eye(3), torch.eye(3)))
        0.0
    """
    D = R1 @ R2.transpose(-1, -2)
    tr = D[..., 0, 0] + D[..., 1, 1] + D[..., 2, 2]
    skew = torch.stack(
        [D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0], D[..., 1, 0] - D[..., 0, 1]], dim=-1
    )
    return torch.atan2(skew.norm(dim=-1), tr - 1.0)


def check_rotation_pairs(R_est: torch.Tensor, R_gt: torch.Tensor) -> None:
    for name, R in (("R_est", R_est), ("R_gt", R_gt)):
        if not isinstance(R, torch.Tensor) or R.dim() != 3 or R.shape[1:] != (3, 3):
            raise ValueError(f"{name} must be a (N, 3, 3) tensor, got {getattr(R, 'shape', type(R))}")
    if R_est.shape[0] != R_gt.shape[0]:
        raise ValueError("R_est and R_gt must hold the same number of rotations, "
                         f"got {R_est.shape[0]} and {R_gt.shape[0]}")


def finite_rotation_pairs(R_est: torch.Tensor, R_gt: torch.Tensor) -> torch.Tensor:
    return torch.isfinite(R_est).flatten(1).all(1) & torch.isfinite(R_gt).flatten(1).all(1)


def _procrustes(A: torch.Tensor) -> torch.Tensor:
    """Proper rotation ``G`` maximising ``trace(G^T A)`` for ``A (..., 3, 3)``."""
    U, _, Vh = torch.linalg.svd(A)
    d = torch.sign(torch.det(U @ Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    return U @ D @ Vh


def align_rotations(
    R_est: torch.Tensor,
    R_gt: torch.Tensor,
    *,
    robust: bool = False,
    iters: int = 20,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Global rotation ``G`` minimising ``sum_n w_n ||R_est_n G - R_gt_n||_F^2``.

    Closed form (orthogonal Procrustes): ``A = sum_n w_n R_est_n^T R_gt_n = U S V^T``,
    ``G = U diag(1, 1, det(U V^T)) V^T`` (a proper rotation). With ``robust=True``,
    iteratively reweighted with ``w_n = 1 / max(theta_n, 1 deg)`` (``theta_n`` the
    geodesic residual), which approximately minimises the sum of the angles
    rather than of their squares, so a few gross errors (e.g. flipped instances)
    do not tilt ``G``. Pairs with a non-finite entry are ignored.

    Args:
        R_est, R_gt: ``(N, 3, 3)`` proper rotations.
        robust: use the reweighted variant.
        iters: reweighting iterations.
        weights: ``(N,)`` optional non-negative weights, or ``(B, N)``: B weightings at once (e.g. bootstrap
            resamples; not with ``robust``).

    Returns:
        ``(3, 3)`` (``(B, 3, 3)`` with ``(B, N)`` weights) in ``R_est``'s dtype (computed in float64).

    Example:
        >>> from carvi_torch.cameras import random_rotations
        >>> R = random_rotations(5, torch.Generator().manual_seed(0)); G = random_rotations(1)[0]
        >>> torch.allclose(align_rotations(R @ G.T, R), G, atol=1e-5)
        True
    """
    check_rotation_pairs(R_est, R_gt)
    ok = finite_rotation_pairs(R_est, R_gt)
    if not bool(ok.any()):
        raise ValueError("align_rotations: no pair of finite rotations")
    Re = R_est[ok].double()
    Rg = R_gt[ok].double()
    w = torch.ones(Re.shape[0], dtype=torch.float64, device=Re.device)
    if weights is not None:
        w = torch.as_tensor(weights, device=Re.device).double()
        if w.shape[-1:] != ok.shape or w.dim() > 2 or (robust and w.dim() == 2):
            raise ValueError(f"weights must be ({len(ok)},) or (B, {len(ok)}) (not with robust), got {tuple(w.shape)}")
        w = w[..., ok.to(Re.device)]
        if bool((w < 0).any()):
            raise ValueError("weights must be non-negative")
    G = _procrustes(torch.einsum("...n,nji,njk->...ik", w, Re, Rg))
    if robust:
        floor = math.radians(1.0)
        for _ in range(iters):
            theta = geodesic_angle(Re @ G, Rg)
            G_new = _procrustes(torch.einsum("n,nji,njk->ik", w / theta.clamp(min=floor), Re, Rg))
            if float((G_new - G).abs().max()) < 1e-12:
                G = G_new
                break
            G = G_new
    return G.to(R_est.dtype)


def geodesic_errors(R_est: torch.Tensor, R_gt: torch.Tensor, G: torch.Tensor | None = None) -> torch.Tensor:
    """Angle (degrees) between ``R_est_n G`` and ``R_gt_n``; ``G`` = identity when None.

    Returns ``(N,)`` in ``[0, 180]``; NaN where an input is not finite.
    """
    check_rotation_pairs(R_est, R_gt)
    Re = R_est if G is None else R_est @ G.to(R_est)
    return torch.rad2deg(geodesic_angle(Re, R_gt.to(Re)))


def _rz(a: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, -s, z, s, c, z, z, z, o], dim=-1).reshape(*a.shape, 3, 3)


def _rx(a: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([o, z, z, z, c, -s, z, s, c], dim=-1).reshape(*a.shape, 3, 3)


def rotation_from_azimuth_elevation_roll(
    azimuth: torch.Tensor, elevation: torch.Tensor, roll: torch.Tensor
) -> torch.Tensor:
    """Camera rotation from viewpoint angles (radians), PASCAL3D+ convention.

    ``R = diag(1, -1, -1) @ Rz(roll) @ Rx(elevation - pi/2) @ Rz(-azimuth)`` with
    right-handed (active) ``Rz``, ``Rx``. For an object with +z up and its front
    towards -y, azimuth 0 / elevation 0 / roll 0 looks at its front, with the object's
    up pointing up in the image; azimuth turns the camera about the object's up
    axis, elevation > 0 raises it, roll turns the image in its plane. This equals
    PASCAL3D+'s ``R = diag(1,-1,-1) @ rot.T`` for its ``euler = [roll, elevation, azimuth]``.

    Args:
        azimuth, elevation, roll: ``(...)`` broadcastable tensors.

    Returns:
        ``(..., 3, 3)`` rotations.

    Example:
        >>> z = torch.tensor(0.0)
        >>> rotation_from_azimuth_elevation_roll(z, z, z)[2].round(decimals=6)   # looks along +y
        tensor([0., 1., 0.])
    """
    azimuth, elevation, roll = torch.broadcast_tensors(
        torch.as_tensor(azimuth), torch.as_tensor(elevation), torch.as_tensor(roll)
    )
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=azimuth.dtype, device=azimuth.device))
    return flip @ _rz(roll) @ _rx(elevation - math.pi / 2) @ _rz(-azimuth)


def azimuth_elevation_roll_from_rotation(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inverse of :func:`rotation_from_azimuth_elevation_roll`.

    Args:
        R: ``(..., 3, 3)`` rotations.

    Returns:
        ``azimuth`` in ``(-pi, pi]``, ``elevation`` in ``[-pi/2, pi/2]``, ``roll`` in
        ``(-pi, pi]``, each ``(...)``. At elevation +-90 degrees azimuth and roll are
        not separable; roll is then reported as 0.
    """
    flip = torch.tensor([1.0, -1.0, -1.0], dtype=R.dtype, device=R.device)
    M = flip[:, None] * R  # Rz(roll) Rx(phi) Rz(psi), phi = elev - pi/2 in [-pi, 0]
    sin_phi = -torch.sqrt(M[..., 2, 0] ** 2 + M[..., 2, 1] ** 2)
    phi = torch.atan2(sin_phi, M[..., 2, 2])
    degenerate = sin_phi.abs() < 1e-9
    psi = torch.atan2(-M[..., 2, 0], -M[..., 2, 1])
    roll = torch.atan2(-M[..., 0, 2], M[..., 1, 2])
    # Gimbal lock: M = Rz(roll + psi) (up to Rx(0 or -pi)); put everything in psi.
    psi_deg = torch.atan2(M[..., 1, 0], M[..., 0, 0]) * torch.where(M[..., 2, 2] > 0, 1.0, -1.0)
    psi = torch.where(degenerate, psi_deg, psi)
    roll = torch.where(degenerate, torch.zeros_like(roll), roll)
    azimuth = torch.remainder(-psi + math.pi, 2 * math.pi) - math.pi
    return azimuth, phi + math.pi / 2, roll


def random_rotations(n: int, generator: torch.Generator | None = None, dtype=torch.float32,
                     device="cpu") -> torch.Tensor:
    """``n`` rotations drawn uniformly (Haar) from random unit quaternions. Returns ``(n, 3, 3)``."""
    q = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    return quaternion_to_rotation(q).to(dtype=dtype, device=device)


# --------------------------------------------------------------------------- similarities


@dataclass
class Similarity2D:
    """Batch of 2-D similarities ``p' = scale * p + offset`` (no rotation).

    Used for the image -> canvas map of every instance: canvas pixels =
    ``scale * image pixels + offset``.

    Attributes:
        scale: ``(N,)`` positive.
        offset: ``(N, 2)``.
    """

    scale: torch.Tensor
    offset: torch.Tensor

    def apply(self, p: torch.Tensor) -> torch.Tensor:
        """Map points ``p (N, P, 2)`` (or ``(N, 2)``)."""
        if p.dim() == 2:
            return self.scale[:, None] * p + self.offset
        return self.scale[:, None, None] * p + self.offset[:, None, :]

    def inverse(self) -> "Similarity2D":
        return Similarity2D(1.0 / self.scale, -self.offset / self.scale[:, None])

    def __getitem__(self, idx) -> "Similarity2D":
        return Similarity2D(self.scale[idx], self.offset[idx])

    def to(self, *args, **kwargs) -> "Similarity2D":
        return Similarity2D(self.scale.to(*args, **kwargs), self.offset.to(*args, **kwargs))


# --------------------------------------------------------------------------- cameras


@dataclass
class ScaledOrthographic:
    """A batch of N scaled orthographic cameras.

    ``uv = s * X @ R[:2].T + t`` and ``depth = s * X @ R[2]``, in pixels.

    Attributes:
        R: ``(N, 3, 3)`` proper rotations; rows = image x, image y (down), viewing
            direction, in the object frame.
        s: ``(N,)`` positive scales (pixels per object unit).
        t: ``(N, 2)`` image position of the object-frame origin.

    Example:
        >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.tensor([2.0]), torch.tensor([[10.0, 5.0]]))
        >>> cam.project(torch.tensor([[1.0, 1.0, 3.0]]))
        tensor([[[12.,  7.]]])
    """

    R: torch.Tensor
    s: torch.Tensor
    t: torch.Tensor

    def __post_init__(self):
        if self.R.dim() != 3 or self.R.shape[-2:] != (3, 3):
            raise ValueError(f"R must be (N, 3, 3), got {tuple(self.R.shape)}")
        n = self.R.shape[0]
        if self.s.shape != (n,) or self.t.shape != (n, 2):
            raise ValueError(f"expected s ({n},) and t ({n}, 2); got {tuple(self.s.shape)} and {tuple(self.t.shape)}")

    # -- basics
    def __len__(self) -> int:
        return self.R.shape[0]

    def __getitem__(self, idx) -> "ScaledOrthographic":
        if isinstance(idx, int):
            idx = slice(idx, idx + 1) if idx != -1 else slice(-1, None)
        return ScaledOrthographic(self.R[idx], self.s[idx], self.t[idx])

    def to(self, *args, **kwargs) -> "ScaledOrthographic":
        return ScaledOrthographic(self.R.to(*args, **kwargs), self.s.to(*args, **kwargs), self.t.to(*args, **kwargs))

    @property
    def device(self) -> torch.device:
        return self.R.device

    @staticmethod
    def cat(cams: Sequence["ScaledOrthographic"]) -> "ScaledOrthographic":
        return ScaledOrthographic(
            torch.cat([c.R for c in cams]), torch.cat([c.s for c in cams]), torch.cat([c.t for c in cams])
        )

    @property
    def M(self) -> torch.Tensor:
        """``(N, 2, 3)`` affine block ``s * R[:2]``."""
        return self.s[:, None, None] * self.R[:, :2, :]

    @property
    def view_direction(self) -> torch.Tensor:
        """``(N, 3)`` viewing direction (into the scene) in the object frame: ``R[2]``."""
        return self.R[:, 2, :]

    @classmethod
    def from_affine(cls, M: torch.Tensor, t: torch.Tensor) -> "ScaledOrthographic":
        """Nearest scaled orthographic camera to affine cameras ``M (N, 2, 3)``, ``t (N, 2)``."""
        R, s = nearest_scaled_rotation(M)
        return cls(R, s, t)

    # -- projection
    def project(self, X: torch.Tensor) -> torch.Tensor:
        """Project object-frame points.

        Args:
            X: ``(P, 3)`` shared by all cameras, or ``(N, P, 3)`` one set per camera.

        Returns:
            ``(N, P, 2)`` pixels.
        """
        if X.dim() == 2:
            X = X.unsqueeze(0)
        return self.s[:, None, None] * (X @ self.R[:, :2, :].transpose(-1, -2)) + self.t[:, None, :]

    def depth(self, X: torch.Tensor) -> torch.Tensor:
        """Depth (pixels, along the viewing direction) of ``X (P, 3)`` or ``(N, P, 3)``; returns ``(N, P)``."""
        if X.dim() == 2:
            X = X.unsqueeze(0)
        return self.s[:, None] * (X @ self.R[:, 2, :, None]).squeeze(-1)

    def to_camera_frame(self, X: torch.Tensor) -> torch.Tensor:
        """Object-frame points ``(P,3)`` / ``(N,P,3)`` to ``(u, v, depth)`` ``(N, P, 3)``."""
        return torch.cat([self.project(X), self.depth(X).unsqueeze(-1)], dim=-1)

    def from_camera_frame(self, p: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`to_camera_frame`: ``(N, P, 3)`` camera-frame points to object frame."""
        q = p.clone()
        q[..., :2] = q[..., :2] - self.t[:, None, :]
        return (q / self.s[:, None, None]) @ self.R

    # -- composition
    def camera_to_object_4x4(self) -> torch.Tensor:
        """``(N, 4, 4)`` float64 maps of camera-frame points ``(u, v, depth, 1)`` to object-frame ones
        (:meth:`from_camera_frame` as a matrix: ``X = R^T [(u - t_x) / s, (v - t_y) / s, depth / s]``).

        Example:
            >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.tensor([2.0]), torch.tensor([[4.0, 6.0]]))
            >>> (cam.camera_to_object_4x4()[0] @ torch.tensor([6.0, 6.0, 2.0, 1.0], dtype=torch.float64)).tolist()
            [1.0, 0.0, 1.0, 1.0]
        """
        R, s, t = self.R.double(), self.s.double(), self.t.double()
        A = torch.zeros(len(self), 4, 4, dtype=torch.float64, device=R.device)
        A[:, :3, :3] = R.transpose(1, 2) / s[:, None, None]
        A[:, :3, 3] = -(R.transpose(1, 2)[:, :, :2] @ t[:, :, None])[..., 0] / s[:, None]
        A[:, 3, 3] = 1.0
        return A

    def compose_similarity(self, sim: Similarity2D) -> "ScaledOrthographic":
        """The camera followed by a 2-D similarity ``p' = a p + b`` (e.g. image -> canvas).

        Returns the camera with ``s' = a s`` and ``t' = a t + b``: projecting with it
        equals projecting with ``self`` and then applying ``sim``.
        """
        return ScaledOrthographic(self.R, sim.scale * self.s, sim.apply(self.t))

    def mirror(self, width: torch.Tensor | float, reflection: torch.Tensor | None = None) -> "ScaledOrthographic":
        """Camera of the left-right flipped image (``x' = width - 1 - x``).

        A flipped photograph of an object is a photograph of its mirror image.
        With ``reflection`` = the object's symmetry plane ``P (3, 3)`` (an improper
        orthogonal matrix, e.g. ``diag(-1, 1, 1)``), the returned camera sees the
        object itself: ``R' = diag(-1,1,1) R P`` (proper), and a point ``X`` of the
        object projects where its mirror ``P X`` appeared, flipped. Without
        ``reflection`` the object frame's x axis is used as the symmetry plane normal.

        Args:
            width: image width(s), float or ``(N,)``.
            reflection: ``(3, 3)`` or ``(N, 3, 3)``.

        Mirroring twice with the same width and reflection gives back the camera.
        """
        if reflection is None:
            reflection = FLIP_X.to(self.R)
        flip = FLIP_X.to(self.R)
        width = torch.as_tensor(width, dtype=self.t.dtype, device=self.t.device)
        R = flip @ self.R @ reflection
        t = self.t.clone()
        t[:, 0] = width - 1 - self.t[:, 0]
        return ScaledOrthographic(R, self.s.clone(), t)

    # -- serialisation
    def to_list(self) -> list[dict]:
        """One ``{"R": 3x3, "s": float, "t": [x, y]}`` dict per camera (float64 lists)."""
        R = self.R.detach().double().cpu().tolist()
        s = self.s.detach().double().cpu().tolist()
        t = self.t.detach().double().cpu().tolist()
        return [{"R": R[i], "s": s[i], "t": t[i]} for i in range(len(self))]

    @classmethod
    def from_list(cls, items: Sequence[dict], dtype=torch.float32, device="cpu") -> "ScaledOrthographic":
        if len(items) == 0:
            return cls(torch.zeros(0, 3, 3, dtype=dtype, device=device), torch.zeros(0, dtype=dtype, device=device),
                       torch.zeros(0, 2, dtype=dtype, device=device))
        R = torch.tensor([it["R"] for it in items], dtype=dtype, device=device)
        s = torch.tensor([float(it["s"]) for it in items], dtype=dtype, device=device)
        t = torch.tensor([it["t"] for it in items], dtype=dtype, device=device)
        return cls(R, s, t)
