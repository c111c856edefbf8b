"""Our cameras in PyTorch3D's and kornia's conventions.

Ours (docs/conventions.md): scaled orthographic, ``uv = s * R[:2] X + t`` in image pixels, x right,
y down, pixel centres at integer coordinates; ``R``'s rows are the image x axis, the image y axis
(down) and the viewing direction (into the scene): the OpenCV camera frame.

**PyTorch3D** (``pytorch3d.renderer.OrthographicCameras``; its ``docs/notes/cameras.md``): the view
frame has +X left, +Y up, +Z into the scene; a world point maps to view space as the *row vector*
``X_view = X_world @ R + T``; an orthographic camera with ``in_ndc=False`` takes its focal length
and principal point in pixels and ``image_size = (height, width)``, and puts a point at screen
``(px - fx X_view_x, py - fy X_view_y)``, where screen coordinates run from 0 at the image's left
(top) *edge*, so pixel ``j`` has its centre at ``j + 0.5``. In NDC (``in_ndc=True``),
``+1`` is the left (top) edge of the shorter side: ``f_ndc = 2 f / S``, ``p_ndc = -(p - W / 2) 2 / S``
(``S = min(H, W)``). Hence, with ``F = diag(-1, -1, 1)`` (our frame -> PyTorch3D's view frame):
``R_p3d = (F R)^T``, ``T = (0, 0, depth)``, ``focal = s``, ``principal_point = t + 0.5``.

**kornia**: ``kornia.sensors.camera.CameraModel(..., CameraModelType.ORTHOGRAPHIC, [fx, fy, cx, cy])``
projects a camera-frame point (OpenCV axes) to ``(fx x + cx, fy y + cy)``, pixel centres at
integers like ours: ``fx = fy = s``, ``(cx, cy) = t``, and the world-to-camera extrinsics are
``[R | (0, 0, depth)]``. ``kornia.geometry.camera.PinholeCamera`` is perspective only:
:func:`to_kornia_pinhole` gives the weak-perspective equivalent, a camera ``distance`` away with
focal ``s * distance``, which matches ours to a relative ``O(object depth / distance)``.

Example:
    >>> import torch
    >>> from carvi_torch.cameras import ScaledOrthographic
    >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.tensor([2.0]), torch.tensor([[10.0, 20.0]]))
    >>> p = to_pytorch3d(cam, image_size=(64, 48))
    >>> p["R"][0].diagonal().tolist(), p["focal_length"].tolist(), p["principal_point"].tolist()
    ([-1.0, -1.0, 1.0], [[2.0, 2.0]], [[10.5, 20.5]])
"""
from __future__ import annotations

import torch

from .cameras import ScaledOrthographic

__all__ = ["to_pytorch3d", "from_pytorch3d", "to_kornia", "to_kornia_pinhole", "P3D_FROM_OURS"]

#: Our camera frame (x right, y down, z into the scene) -> PyTorch3D's view frame (x left, y up, z into it).
P3D_FROM_OURS = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))


def _hw(image_size, n: int, dtype) -> torch.Tensor:
    hw = torch.as_tensor(image_size, dtype=dtype).reshape(-1, 2)
    return hw.expand(n, 2) if hw.shape[0] == 1 else hw


def to_pytorch3d(cameras: ScaledOrthographic, image_size, in_ndc: bool = False, depth: float = 0.0) -> dict:
    """Keyword arguments of ``pytorch3d.renderer.OrthographicCameras`` for ``cameras`` (image pixels).

    Args:
        cameras: ``N`` cameras of ours.
        image_size: ``(height, width)`` or ``(N, 2)``, the images the cameras' pixels refer to.
        in_ndc: give focal length and principal point in PyTorch3D's NDC instead of pixels.
        depth: view-space depth of the world origin (``T_z``; orthography ignores it, clipping does not).

    Returns:
        ``R (N, 3, 3)``, ``T (N, 3)``, ``focal_length (N, 2)``, ``principal_point (N, 2)``, ``in_ndc`` and
        (screen space) ``image_size (N, 2)``: ``OrthographicCameras(**to_pytorch3d(...))``.
    """
    R, s, t = cameras.R.double(), cameras.s.double(), cameras.t.double()
    n = len(s)
    Rp = (P3D_FROM_OURS.to(R) @ R).transpose(-1, -2)
    T = torch.zeros(n, 3, dtype=R.dtype)
    T[:, 2] = depth
    focal = s[:, None].expand(n, 2).clone()
    pp = t + 0.5
    hw = _hw(image_size, n, R.dtype)
    out = {"R": Rp, "T": T, "in_ndc": in_ndc}
    if in_ndc:
        S = hw.min(dim=1).values[:, None]
        wh = hw.flip(-1)
        out.update(focal_length=2.0 * focal / S, principal_point=-(pp - wh / 2.0) * 2.0 / S)
    else:
        out.update(focal_length=focal, principal_point=pp, image_size=hw)
    return out


def from_pytorch3d(R: torch.Tensor, focal_length: torch.Tensor, principal_point: torch.Tensor,
                   T: torch.Tensor | None = None, image_size=None, in_ndc: bool = False) -> ScaledOrthographic:
    """Our cameras from ``OrthographicCameras`` parameters (square pixels: ``fx == fy``); the inverse of
    :func:`to_pytorch3d`. ``T``'s x, y (view-space shifts) move the principal point; its z is dropped."""
    R, f, pp = R.double(), focal_length.double(), principal_point.double()
    n = R.shape[0]
    f = f.reshape(n, -1)
    if in_ndc:
        hw = _hw(image_size, n, R.dtype)
        S = hw.min(dim=1).values[:, None]
        f, pp = f * S / 2.0, -pp * S / 2.0 + hw.flip(-1) / 2.0
    s = f[:, 0]
    t = pp - 0.5
    if T is not None:  # screen x = px - f (X R)_x - f T_x: the shift lands in t
        t = t - f[:, :2].expand(n, 2) * T.double()[:, :2]
    ours = P3D_FROM_OURS.to(R) @ R.transpose(-1, -2)
    return ScaledOrthographic(ours, s, t)


def to_kornia(cameras: ScaledOrthographic, image_size, depth: float = 0.0):
    """kornia's orthographic camera model and the world-to-camera extrinsics ``(N, 4, 4)``.

    Returns:
        ``(model, extrinsics)``: ``kornia.sensors.camera.CameraModel`` of type ``ORTHOGRAPHIC`` with
        params ``(N, 4) = (s, s, t_x, t_y)``; ``extrinsics = [[R, (0, 0, depth)], [0, 0, 0, 1]]``. A world
        point ``X`` projects to ``model.project(Vector3(R X + (0, 0, depth)))``.
    """
    from kornia.geometry.vector import Vector3  # noqa: F401 - the type model.project takes
    from kornia.image import ImageSize
    from kornia.sensors.camera import CameraModel, CameraModelType

    R, s, t = cameras.R.double(), cameras.s.double(), cameras.t.double()
    hw = _hw(image_size, len(s), R.dtype)
    params = torch.stack([s, s, t[:, 0], t[:, 1]], dim=-1)
    model = CameraModel(ImageSize(int(hw[0, 0]), int(hw[0, 1])), CameraModelType.ORTHOGRAPHIC, params)
    return model, _extrinsics(R, depth)


def _extrinsics(R: torch.Tensor, depth: float) -> torch.Tensor:
    E = torch.zeros(R.shape[0], 4, 4, dtype=R.dtype)
    E[:, :3, :3] = R
    E[:, 2, 3] = depth
    E[:, 3, 3] = 1.0
    return E


def to_kornia_pinhole(cameras: ScaledOrthographic, image_size, distance: float):
    """``kornia.geometry.camera.PinholeCamera`` seeing like ``cameras`` from ``distance`` (world units) away:
    focal ``s * distance``, principal point ``t``, extrinsics ``[R | (0, 0, distance)]`` (weak perspective:
    exact as ``distance`` grows; off by about ``|depth| / distance`` of a point's offset from ``t``)."""
    from kornia.geometry.camera import PinholeCamera

    R, s, t = cameras.R.double(), cameras.s.double(), cameras.t.double()
    n = len(s)
    hw = _hw(image_size, n, R.dtype)
    K = torch.zeros(n, 4, 4, dtype=R.dtype)
    K[:, 0, 0] = K[:, 1, 1] = s * distance
    K[:, 0, 2], K[:, 1, 2] = t[:, 0], t[:, 1]
    K[:, 2, 2] = K[:, 3, 3] = 1.0
    return PinholeCamera(K, _extrinsics(R, distance), hw[:, 0], hw[:, 1])
