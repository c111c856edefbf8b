"""Baseline reconstructions of the paper's Table 1: Puffball and the SfM convex hull (SFMc).

Both give a closed ``trimesh.Trimesh`` in the reference camera frame of the instance,
the frame of the method's own reconstructions: ``x``, ``y`` = canvas pixels (x right,
y down, pixel centres at integers), ``z`` = depth in pixels (into the scene). Depth has no
absolute origin under orthography; the evaluation (:func:`carvi_torch.evaluation.metrics.
evaluate_reconstruction`) aligns it.

* :func:`puffball` inflates a single silhouette (Twarog, Tappen, Adelson, "Playing with
  Puffball: simple scale-invariant inflation for use in vision and graphics", 2012): the
  union of the balls of the medial axis, blended softly (:mod:`carvi_torch.carve.puffball`, where
  the pipeline's last fallback voxelises the same height field).
* :func:`sfm_convex_hull` is the convex hull of the class's SfM mean shape seen by the
  instance's camera.
"""
from __future__ import annotations

import numpy as np
import torch
import trimesh
from skimage import measure

from ..cameras import ScaledOrthographic
from ..carve.puffball import check_mask, medial_balls, puffball_height  # noqa: F401 - re-exported: the baseline's pieces

__all__ = ["medial_balls", "puffball_height", "puffball", "sfm_convex_hull"]


def puffball(mask: torch.Tensor, camera: ScaledOrthographic | None = None, depth_step: float = 1.0,
             chunk_elems: int = 1 << 24) -> trimesh.Trimesh:
    """Puffball reconstruction of a silhouette: a closed mesh in the reference camera frame.

    The solid is the slab ``|z| <= h(x, y)`` between the front height field and its mirror
    behind the image plane (``h`` from :func:`puffball_height`; depth centred at 0). It is
    meshed by marching cubes (scikit-image) of the field ``f(x, y, z) = h_ext(x, y) - |z|``
    sampled at every pixel and at depths ``(k + 1/2) depth_step``, with ``h_ext = h`` on the
    foreground and ``-1`` on the background (and on a one-pixel frame around the canvas),
    so the surface is closed, its rim crosses between a foreground and a background pixel
    (the projected silhouette matches the mask to within a pixel), and it is symmetric
    about ``z = 0``.

    Args:
        mask: ``(H, W)`` bool canvas silhouette of the reference instance.
        camera: the instance's camera (one :class:`ScaledOrthographic`). The mesh is in
            its camera frame, which the mask already defines, so the camera is only checked;
            it is accepted so that every baseline takes the same inputs.
        depth_step: depth sampling of the field (pixels).
        chunk_elems: see :func:`puffball_height`.

    Returns:
        ``trimesh.Trimesh`` with vertices ``(x, y, z)`` in canvas pixels, outward normals;
        an empty mesh for an empty mask.

    Example:
        >>> yy, xx = torch.meshgrid(torch.arange(21), torch.arange(21), indexing="ij")
        >>> disk = (xx - 10) ** 2 + (yy - 10) ** 2 <= 64
        >>> mesh = puffball(disk)
        >>> mesh.is_watertight, round(float(mesh.vertices[:, 2].max()) / 8, 1)
        (True, 1.1)
    """
    m = check_mask(mask)
    if camera is not None and len(camera) != 1:
        raise ValueError(f"camera must hold one camera, got {len(camera)}")
    if not depth_step > 0:
        raise ValueError(f"depth_step must be > 0, got {depth_step}")
    if not bool(m.any()):
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    h = puffball_height(m, chunk_elems=chunk_elems).cpu()
    h_ext = torch.where(m.cpu(), h, torch.full_like(h, -1.0))
    h_ext = torch.nn.functional.pad(h_ext, (1, 1, 1, 1), value=-1.0)  # (H+2, W+2)
    n = int(np.ceil(float(h.max()) / depth_step)) + 1
    # depth samples at half steps, symmetric about 0 and never on the kink of |z|
    z = (torch.arange(-n, n, dtype=torch.float32) + 0.5) * depth_step  # (D,)
    field = h_ext[None, :, :] - z.abs()[:, None, None]  # (D, H+2, W+2), index (d, y, x)
    verts, faces, _, _ = measure.marching_cubes(field.numpy(), level=0.0)
    # index (d, h, w) -> camera frame (x, y, z)
    xyz = np.stack([verts[:, 2] - 1.0, verts[:, 1] - 1.0, (verts[:, 0] + 0.5 - n) * depth_step], axis=1)
    mesh = trimesh.Trimesh(xyz, faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def sfm_convex_hull(shape: torch.Tensor, camera: ScaledOrthographic) -> trimesh.Trimesh:
    """SFMc baseline: convex hull of the SfM mean shape in the instance's camera frame.

    The points are mapped with ``camera.to_camera_frame`` to ``(u, v, depth)`` in pixels
    (the depth keeps the camera's origin, like the method's own grids); rows with a NaN
    (keypoints SfM could not place) are dropped. The hull is computed by trimesh (qhull).

    Args:
        shape: ``(K, 3)`` mean shape in the object frame (NaN rows allowed).
        camera: a :class:`ScaledOrthographic` holding one camera.

    Returns:
        A closed, convex ``trimesh.Trimesh``; an empty mesh when fewer than four
        non-coplanar points remain (no volume to enclose), which the evaluation reports
        as a failure with its reason.

    Example:
        >>> cube = torch.tensor([[x, y, z] for x in (0., 1) for y in (0., 1) for z in (0., 1)])
        >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.tensor([10.0]), torch.zeros(1, 2))
        >>> round(float(sfm_convex_hull(cube, cam).volume))
        1000
    """
    S = torch.as_tensor(shape)
    if S.dim() != 2 or S.shape[-1] != 3:
        raise ValueError(f"shape must be (K, 3), got {tuple(S.shape)}")
    if len(camera) != 1:
        raise ValueError(f"camera must hold one camera, got {len(camera)}")
    S = S.to(device=camera.R.device, dtype=camera.R.dtype)
    S = S[torch.isfinite(S).all(dim=1)]
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    if S.shape[0] < 4:
        return empty
    pts = camera.to_camera_frame(S)[0].detach().double().cpu().numpy()
    centred = pts - pts.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-9 * max(1.0, float(np.abs(centred).max()))) < 3:
        return empty
    hull = trimesh.convex.convex_hull(pts)
    return hull if hull.volume > 0 else empty
