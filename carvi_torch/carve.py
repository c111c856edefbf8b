"""Imprinted visual hulls on voxel grids, batched over proposals.

A *proposal* is a reference silhouette ``r`` plus further views ``m`` (surrogate
silhouettes, their mirrored copies, the mirrored reference...). Its shape is carved on
a voxel grid in the reference camera frame: voxel ``v`` gets the cone cost
``C(v) = max_m C_m(v)`` over the reference and the views, is *interior* iff
``C(v) < 0``, and, with imprinting, every foreground column of the reference that has
no interior voxel gets its voxel of minimal ``C`` (Carreira et al., "Lifting Object
Detection Datasets into 3D", section "Imprinted visual hull reconstruction").

Frames and units
----------------
* **Silhouettes** are exact signed distance maps ``sdf (M, H, W)`` (pixels, negative
  inside, zero level half-way between a foreground and a background pixel centre:
  :func:`carvi_torch.sdf.signed_distance`) with scaled orthographic cameras
  ``ScaledOrthographic (M)`` in the same canvas pixels (image x right, y down, pixel
  centres at integers).
* **Reference camera frame** of proposal ``b``: ``p = (x, y, z) = (u, v, depth)`` in
  pixels of the reference canvas; depth 0 is the object-frame origin
  (``z = s_r R_r[2] . X``). A point ``p`` maps to the object frame by
  ``cameras[r].from_camera_frame(p)`` and into view ``m`` by ``cameras[m].project``;
  composed, ``u_m = A p + c`` with ``A = (s_m / s_r) R_m[:2] R_r^T`` (2x3) and
  ``c = t_m - A[:, :2] t_r``: one affine map per (proposal, view), folded together
  with the voxel-to-camera map and the normalisation of ``grid_sample`` into one
  ``(2, 4)`` matrix from voxel indices to sampling coordinates.
* **Voxel grid**: ``(D, H, W)`` = (depth, y, x) indices with ``D = H = W =
  resolution``, voxel centres at integer indices, and ``voxel_to_camera (4, 4)``
  mapping ``(d, h, w, 1)`` to ``(x, y, z, 1)``::

      x = x0 + sx * w,   y = y0 + sy * h,   z = z0 + sz * d

  i.e. ``voxel_to_camera = [[0, 0, sx, x0], [0, sy, 0, y0], [sz, 0, 0, z0], [0, 0, 0, 1]]``
  (a permutation of axes, so its determinant is ``-sx sy sz < 0``). Spacing is
  **anisotropic**: each axis has its own step, so that every proposal has the same
  ``(D, H, W)`` and a batch is one tensor.
* **Bounds**. ``x`` and ``y``: the reference mask's bounding box extended by half a
  pixel (the zero level of the sdf) is the *extent*; it is tiled by ``resolution -
  2`` voxel cells (centres ``1 .. resolution - 2``, cell edges on the extent's
  edges, so a box-shaped hull has exactly its volume) plus one voxel on each side
  whose centre lies half a voxel outside the extent: the outer layer is always
  exterior. Depth: every interior point projects inside each view's
  mask, hence inside its bounding box; with the reference box this bounds ``z``
  through each row of ``u_m = A p + c`` (interval arithmetic, one interval per view
  and image axis, intersected). The result is capped to ``|z| <= s_r max_m rho_m /
  s_m`` where ``rho_m`` is the radius of view ``m``'s mask around ``t_m`` (the
  projection of the object origin) plus one pixel diagonal: the ball of the largest
  silhouette, in object units times the reference scale. The cap only binds when the
  views leave depth (nearly) unconstrained, e.g. a reference with only its own
  mirror, whose view direction is parallel to it. Inconsistent views (an empty
  intersection) give the span between their intervals; the depth extent is at least
  one pixel. The depth extent is tiled like ``x`` and ``y``.
* **Cone cost** ``C_m``: view ``m``'s sdf, bilinearly interpolated at ``u_m``
  (``grid_sample``, ``align_corners=True``, pixel centres are sample points; with
  ``interpolation="nearest"``, the value at the pixel centre nearest ``u_m``), times
  ``s_r / s_m``: each map is in its own pixels, so dividing by its scale (object
  units) and multiplying by the reference scale expresses every ``C_m`` in reference
  pixels ("pixels over camera scale") and the max over views is meaningful.
  Outside the canvas counts as outside the silhouette: every map is extended by a
  band of ``PAD`` pixels holding ``sdf(clamp(q)) + |q - clamp(q)|`` (the value at the
  nearest canvas pixel plus the distance to the canvas; a 1-Lipschitz extension, so
  a mask touching the border ends half a pixel beyond it), and ``padding_mode=
  "border"`` holds the band's outer values beyond it (positive, at least ``PAD -
  0.5``). Signs, hence interior labels, are exact everywhere; values saturate only
  farther than ``PAD`` pixels outside a canvas. Empty masks (``+inf`` maps) are
  clamped to ``BIG``.
* **Reference column term**: the grid is aligned with the reference camera, so
  ``C_r`` is constant along depth: it is sampled once per column (``H * W``
  samples) and broadcast. A column is a *foreground column* iff ``C_r < 0`` at its
  centre. Background columns can hold no interior voxel (``C >= C_r >= 0``) and are
  never imprinted, so the batched carving samples the views only along foreground
  columns (unless the full cost is asked for).
* **Batching**: one affine map per (proposal, view) from voxel indices to sampling
  coordinates; the coordinates of a chunk of proposals are two broadcast adds (a
  depth term plus a column term) into a reused buffer, one ``grid_sample`` call per
  chunk and view slot samples them, and the max over views is taken in place. The
  per-proposal loop :func:`carve_proposals_loop` uses the same arithmetic, so both
  give the same labels bit for bit.
* **Coarse-to-fine** (optional, ``coarse_to_fine=True``): exact costs on the voxels of
  even indices decide the sign of whole 2x2x2 blocks through the Lipschitz bound of
  the maps; only undecided blocks, and the blocks that can hold an imprinting
  argmin, are sampled. Labels are identical; see :func:`carve_proposals` for when it
  pays.

Example:
    >>> masks = torch.zeros(1, 32, 32, dtype=torch.bool); masks[0, 8:24, 10:22] = True
    >>> cams = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.full((1, 2), 16.0))
    >>> grid = imprinted_visual_hull(masks, cams, resolution=20)
    >>> grid.occupancy.shape
    torch.Size([20, 20, 20])
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from carvi_torch import carve_fused
from carvi_torch.cameras import ScaledOrthographic
from carvi_torch.sdf import signed_distance

__all__ = [
    "default_batch_voxels",
    "VoxelGrid",
    "ProposalGrids",
    "imprinted_visual_hull",
    "carve_proposals",
    "carve_proposals_loop",
    "resolve_backend",
    "INTERPOLATIONS",
    "CarveMaps",
    "prepare_maps",
    "extend_maps",
    "mask_geometry",
    "proposal_geometry",
    "PAD",
    "BIG",
]

#: Width (pixels) of the band that extends every distance map beyond its canvas.
PAD = 8
#: Finite stand-in for ``+inf`` distances (empty masks).
BIG = 1.0e6
#: Cone value of an unused view slot: below any real cost, so never the maximum.
_UNUSED = -1.0e30
#: Default ``max_batch_voxels`` per device type (CPU: per intra-op thread, see :func:`default_batch_voxels`).
_DEFAULT_BATCH_VOXELS = {"cpu": 1 << 19, "cuda": 1 << 25}
#: Bound on the CPU default: chunks grow with the threads up to it (measured with 1 and 2 threads only).
_CPU_BATCH_VOXELS_MAX = 1 << 21
#: Coarse-to-fine evaluates a fraction of the voxels: its chunks hold this many times more proposals.
_C2F_CHUNK = 2


# --------------------------------------------------------------------------- containers


@dataclass
class VoxelGrid:
    """One voxel grid in a camera frame.

    Attributes:
        occupancy: ``(D, H, W)`` bool, (depth, y, x) order.
        voxel_to_camera: ``(4, 4)`` float, ``(d, h, w, 1) -> (x, y, z, 1)``.
        cost: optional ``(D, H, W)`` float, the cone cost ``C`` (negative inside the hull).

    Example:
        >>> g = VoxelGrid(torch.ones(2, 2, 2, dtype=torch.bool), torch.diag(torch.tensor([2.0, 1.0, 1.0, 1.0])))
        >>> g.volume()
        16.0
    """

    occupancy: torch.Tensor
    voxel_to_camera: torch.Tensor
    cost: torch.Tensor | None = None

    def __post_init__(self):
        if not isinstance(self.occupancy, torch.Tensor) or self.occupancy.dim() != 3:
            got = getattr(self.occupancy, "shape", type(self.occupancy))
            raise ValueError(f"occupancy must be a (D, H, W) tensor, got {got}")
        if self.occupancy.dtype != torch.bool:
            raise ValueError(f"occupancy must be bool, got {self.occupancy.dtype}")
        if not isinstance(self.voxel_to_camera, torch.Tensor) or self.voxel_to_camera.shape != (4, 4):
            got = getattr(self.voxel_to_camera, "shape", type(self.voxel_to_camera))
            raise ValueError(f"voxel_to_camera must be a (4, 4) tensor, got {got}")
        if self.cost is not None and self.cost.shape != self.occupancy.shape:
            raise ValueError(f"cost must match occupancy {tuple(self.occupancy.shape)}, got {tuple(self.cost.shape)}")

    @property
    def shape(self) -> torch.Size:
        return self.occupancy.shape

    @property
    def device(self) -> torch.device:
        return self.occupancy.device

    def voxel_volume(self) -> float:
        """Volume of one voxel in cubic frame units: ``|det voxel_to_camera[:3, :3]|``."""
        return float(torch.linalg.det(self.voxel_to_camera[:3, :3].double()).abs())

    def volume(self) -> float:
        """Occupied volume in cubic pixels of the frame: count x ``|det voxel_to_camera[:3, :3]|``."""
        return float(self.occupancy.sum()) * self.voxel_volume()

    def camera_points(self) -> torch.Tensor:
        """Occupied voxel centres in the camera frame, ``(P, 3)`` float32, in ``(d, h, w)`` raster order."""
        idx = self.occupancy.nonzero().to(torch.float32)
        T = self.voxel_to_camera.to(device=idx.device, dtype=torch.float32)
        return idx @ T[:3, :3].T + T[:3, 3]

    def to_mesh(self, largest_component: bool = False):
        """Closed surface (``trimesh.Trimesh``) in the camera frame; see :func:`carvi_torch.mesh.occupancy_to_mesh`."""
        from carvi_torch.mesh import occupancy_to_mesh

        return occupancy_to_mesh(self.occupancy, self.voxel_to_camera, largest_component=largest_component)

    def to(self, device) -> "VoxelGrid":
        """The grid with every tensor on ``device``."""
        return VoxelGrid(self.occupancy.to(device), self.voxel_to_camera.to(device),
                         None if self.cost is None else self.cost.to(device))


@dataclass
class ProposalGrids:
    """The carved grids of a batch of ``B`` proposals (all of one resolution).

    Attributes:
        occupancy: ``(B, D, H, W)`` bool.
        voxel_to_camera: ``(B, 4, 4)`` float32.
        empty: ``(B,)`` bool: no interior voxel even after imprinting (e.g. an empty
            reference mask).
        reference_columns: ``(B, H, W)`` bool: the reference mask at grid resolution
            (``C_r < 0`` at the column centres, the columns imprinting fills).
        column_cost: ``(B, H, W)`` float32: the reference cone cost ``C_r`` at the
            column centres.
        cost: ``(B, D, H, W)`` float32 ``C``, only when asked for (``return_cost``).
        columns: ``(B, H, W)`` bool, the columns holding an occupied voxel
            (``occupancy.any(dim=1)``, known from the carving without a pass over the grids).
    """

    occupancy: torch.Tensor
    voxel_to_camera: torch.Tensor
    empty: torch.Tensor
    reference_columns: torch.Tensor
    column_cost: torch.Tensor
    cost: torch.Tensor | None = field(default=None)
    columns: torch.Tensor | None = field(default=None)

    def __len__(self) -> int:
        return self.occupancy.shape[0]

    def __getitem__(self, i: int) -> VoxelGrid:
        """Proposal ``i`` as a :class:`VoxelGrid` (views of the batch tensors)."""
        return VoxelGrid(self.occupancy[i], self.voxel_to_camera[i], None if self.cost is None else self.cost[i])

    def volumes(self) -> torch.Tensor:
        """``(B,)`` float64 occupied volumes in cubic pixels of each reference frame."""
        det = torch.linalg.det(self.voxel_to_camera[:, :3, :3].double()).abs()
        return self.occupancy.flatten(1).sum(1).double() * det

    def to(self, device) -> "ProposalGrids":
        """The grids with every tensor on ``device``."""
        return ProposalGrids(*(None if v is None else v.to(device) for v in
                               (self.occupancy, self.voxel_to_camera, self.empty, self.reference_columns,
                                self.column_cost, self.cost, self.columns)))


# --------------------------------------------------------------------------- prepared maps


@dataclass
class CarveMaps:
    """Silhouettes prepared once for many carvings: extended maps, cameras, mask geometry.

    A carving reads every map it uses many times (once per proposal that uses it), so the
    per-map work -- checks, the extension beyond the canvas (:func:`extend_maps`), bounding
    boxes and radii (:func:`mask_geometry`) -- is done once here, and a proposal names its
    views by *entry* index. An entry is a map seen by one camera; several entries may share
    a map (:meth:`with_entries`, e.g. the rotated cameras of a rotationally symmetric
    reference), so no map is ever copied per proposal.

    Attributes:
        ext: ``(K + 1, H + 2 PAD, W + 2 PAD)`` float32 extended maps; the last one is the
            unused-slot map (``_UNUSED`` everywhere).
        entry_map: ``(M,)`` long, the map (row of ``ext``) of each entry.
        cameras: ``ScaledOrthographic (M)`` float64, one per entry.
        box: ``(M, 4)`` float64, nonempty: ``(M,)`` bool, radius: ``(M,)`` float64: the
            :func:`mask_geometry` of each entry (the radius is about the entry's ``t``).
        size: ``(H, W)`` of the canvas.
    """

    ext: torch.Tensor
    entry_map: torch.Tensor
    cameras: ScaledOrthographic
    box: torch.Tensor
    nonempty: torch.Tensor
    radius: torch.Tensor
    size: tuple[int, int]
    _lip: torch.Tensor | None = field(default=None, repr=False)
    _diff: tuple | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return self.entry_map.shape[0]

    @property
    def device(self) -> torch.device:
        return self.ext.device

    @property
    def unused(self) -> int:
        """Row of ``ext`` that unused view slots sample."""
        return self.ext.shape[0] - 1

    def sdf(self, i: int | torch.Tensor) -> torch.Tensor:
        """The canvas part of the map(s) of entry ``i``: ``(H, W)`` (or ``(n, H, W)``) float32 signed distances."""
        return self.ext[self.entry_map[i]][..., PAD:-PAD, PAD:-PAD]

    def pixel_differences(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``lx, ly``: ``(K + 1,)`` float64 :func:`_pixel_differences` of every map (computed once)."""
        if self._diff is None:
            parts = [_pixel_differences(self.ext[i:i + _PREP_CHUNK]) for i in range(0, len(self.ext), _PREP_CHUNK)]
            self._diff = tuple(torch.cat(x) for x in zip(*parts))
        return self._diff

    def lipschitz(self) -> torch.Tensor:
        """``(K + 1,)`` float64 :func:`_lipschitz` bound of every map (computed once)."""
        if self._lip is None:
            lx, ly = self.pixel_differences()
            self._lip = torch.sqrt(lx ** 2 + ly ** 2)
        return self._lip

    def with_entries(self, maps: torch.Tensor, cameras: ScaledOrthographic) -> "CarveMaps":
        """These entries plus ``E`` more: entry ``M + e`` is map ``maps[e]`` seen by ``cameras[e]``.

        Args:
            maps: ``(E,)`` long map indices (rows of ``ext``, ``< K``), e.g. ``entry_map[i]``.
            cameras: ``ScaledOrthographic (E)`` in the canvas pixels of those maps.
        """
        maps = torch.as_tensor(maps, device=self.device).long().reshape(-1)
        if len(cameras) != maps.shape[0]:
            raise ValueError(f"with_entries: {maps.shape[0]} maps but {len(cameras)} cameras")
        if maps.numel() and (int(maps.min()) < 0 or int(maps.max()) >= self.unused):
            raise ValueError(f"with_entries: map indices must lie in [0, {self.unused})")
        cams = _checked_cameras(cameras, self.device)
        box, nonempty, radius = _chunked_geometry(self.ext, maps, cams.t)
        return CarveMaps(self.ext, torch.cat([self.entry_map, maps]), ScaledOrthographic.cat([self.cameras, cams]),
                         torch.cat([self.box, box]), torch.cat([self.nonempty, nonempty]),
                         torch.cat([self.radius, radius]), self.size, self._lip, self._diff)


#: Maps extended (and measured) at once by :func:`prepare_maps` (bounds its temporary memory).
_PREP_CHUNK = 256


def _checked_cameras(cameras, device) -> ScaledOrthographic:
    if not isinstance(cameras, ScaledOrthographic):
        raise ValueError(f"cameras must be a ScaledOrthographic, got {type(cameras).__name__}")
    cams = cameras.to(device=device, dtype=torch.float64)
    if len(cams) and not bool(((cams.s > 0) & torch.isfinite(cams.s)).all()):
        raise ValueError("cameras.s must be finite and positive")
    return cams


def _chunked_geometry(ext: torch.Tensor, maps: torch.Tensor, t: torch.Tensor):
    """:func:`mask_geometry` of the canvas part of ``ext[maps]`` about ``t``, a chunk of maps at a time."""
    parts = [mask_geometry(ext[maps[i:i + _PREP_CHUNK], PAD:-PAD, PAD:-PAD], t[i:i + _PREP_CHUNK])
             for i in range(0, maps.shape[0], _PREP_CHUNK)]
    if not parts:
        dev = ext.device
        return (torch.zeros(0, 4, dtype=torch.float64, device=dev), torch.zeros(0, dtype=torch.bool, device=dev),
                torch.zeros(0, dtype=torch.float64, device=dev))
    return tuple(torch.cat(x) for x in zip(*parts))


def prepare_maps(sdf, cameras: ScaledOrthographic, *, count: int | None = None) -> CarveMaps:
    """Prepare signed distance maps for :func:`carve_proposals` (entry ``i`` = map ``i`` seen by ``cameras[i]``).

    Args:
        sdf: ``(M, H, W)`` float signed distance maps (:func:`carvi_torch.sdf.signed_distance`),
            or a function ``sdf(start, stop) -> (stop - start, H, W)`` giving them a chunk at a
            time (then ``count = M`` is required), so the full ``sdf`` never needs to exist
            beside the extended maps.
        cameras: ``ScaledOrthographic (M)`` in the maps' pixels.
        count: ``M`` when ``sdf`` is a function.

    Returns:
        :class:`CarveMaps`. Values are the same, bit for bit, as the maps
        :func:`carve_proposals` prepares from a plain ``sdf`` tensor.
    """
    if callable(sdf) and not isinstance(sdf, torch.Tensor):
        if count is None:
            raise ValueError("prepare_maps: count is required when sdf is a function")
        M, source = int(count), sdf
    else:
        if not isinstance(sdf, torch.Tensor) or sdf.dim() != 3 or not sdf.is_floating_point():
            raise ValueError(f"sdf must be a floating (M, H, W) tensor, got {getattr(sdf, 'shape', type(sdf))}")
        M, source = sdf.shape[0], (lambda a, b: sdf[a:b])
    if M == 0:
        raise ValueError("sdf must hold at least one map")
    if not isinstance(cameras, ScaledOrthographic) or len(cameras) != M:
        raise ValueError(f"cameras must be a ScaledOrthographic of length {M} (one per map), got "
                         f"{len(cameras) if isinstance(cameras, ScaledOrthographic) else type(cameras)}")
    ext = None
    for start in range(0, M, _PREP_CHUNK):
        part = source(start, min(M, start + _PREP_CHUNK))
        if not isinstance(part, torch.Tensor) or part.dim() != 3 or not part.is_floating_point():
            raise ValueError(f"sdf must give floating (n, H, W) maps, got {getattr(part, 'shape', type(part))}")
        H, W = part.shape[1:]
        if H < 2 or W < 2:
            raise ValueError(f"sdf maps must be at least 2x2 pixels, got {tuple(part.shape[1:])}")
        if torch.isnan(part).any():
            raise ValueError(f"sdf contains NaN (maps {start} to {start + part.shape[0] - 1})")
        if ext is None:
            ext = torch.empty(M + 1, H + 2 * PAD, W + 2 * PAD, device=part.device)
            ext[M] = _UNUSED
        ext[start:start + part.shape[0]] = extend_maps(part.detach().to(torch.float32).clamp(-BIG, BIG))
    cams = _checked_cameras(cameras, ext.device)
    entry = torch.arange(M, device=ext.device)
    box, nonempty, radius = _chunked_geometry(ext, entry, cams.t)
    return CarveMaps(ext, entry, cams, box, nonempty, radius, (ext.shape[1] - 2 * PAD, ext.shape[2] - 2 * PAD))


# --------------------------------------------------------------------------- input checks


def _check_indices(M: int, reference, views, resolution, device):
    """Proposal indices as long tensors on ``device``, checked against ``M`` entries (one host read)."""
    reference = torch.as_tensor(reference, device=device)
    views = torch.as_tensor(views, device=device)
    if reference.dim() != 1 or reference.is_floating_point() or reference.dtype == torch.bool:
        raise ValueError(f"reference must be a (B,) integer tensor, got {tuple(reference.shape)} {reference.dtype}")
    B = reference.shape[0]
    if views.dim() != 2 or views.shape[0] != B or views.is_floating_point() or views.dtype == torch.bool:
        raise ValueError(f"views must be a (B, V) = ({B}, V) integer tensor, got {tuple(views.shape)} {views.dtype}")
    if not isinstance(resolution, int) or not 4 <= resolution <= 2048:
        raise ValueError(f"resolution must be an int in [4, 2048], got {resolution!r}")
    reference, views = reference.long(), views.long()
    if B:
        lo_r, hi_r, lo_v, hi_v = torch.stack([reference.min(), reference.max(),
                                              views.min() if views.numel() else reference.min(),
                                              views.max() if views.numel() else reference.min()]).tolist()
        if lo_r < 0 or hi_r >= M:
            raise ValueError(f"reference indices must lie in [0, {M}), got range [{lo_r}, {hi_r}]")
        if views.numel() and (lo_v < -1 or hi_v >= M):
            raise ValueError(f"views indices must lie in [0, {M}) or be -1 (unused), got range [{lo_v}, {hi_v}]")
    return reference, views


def _check_sdf(sdf, cameras) -> int:
    """Check plain ``(M, H, W)`` maps and their ``M`` cameras; returns ``M``."""
    if not isinstance(sdf, torch.Tensor) or sdf.dim() != 3 or not sdf.is_floating_point():
        raise ValueError(f"sdf must be a floating (M, H, W) tensor, got {getattr(sdf, 'shape', type(sdf))}")
    M, H, W = sdf.shape
    if M == 0 or H < 2 or W < 2:
        raise ValueError(f"sdf must hold at least one map of at least 2x2 pixels, got {tuple(sdf.shape)}")
    if not isinstance(cameras, ScaledOrthographic) or len(cameras) != M:
        raise ValueError(f"cameras must be a ScaledOrthographic of length {M} (one per map), got "
                         f"{len(cameras) if isinstance(cameras, ScaledOrthographic) else type(cameras)}")
    return M


def _as_maps(sdf, cameras, reference, views, resolution):
    """``(CarveMaps, reference, views)``: the given maps, or the maps of a plain ``sdf`` tensor.

    From a plain tensor only the maps the proposals use are prepared, and the indices are
    renumbered into them.
    """
    if isinstance(sdf, CarveMaps):
        if cameras is not None and cameras is not sdf.cameras:
            raise ValueError("pass cameras=None with prepared CarveMaps (they hold their cameras)")
        reference, views = _check_indices(len(sdf), reference, views, resolution, sdf.device)
        return sdf, reference, views
    M = _check_sdf(sdf, cameras)
    reference, views = _check_indices(M, reference, views, resolution, sdf.device)
    used, inverse = torch.unique(torch.cat([reference, views.clamp(min=0).flatten()]), return_inverse=True)
    if used.numel() == 0:
        used = torch.zeros(1, dtype=torch.long, device=sdf.device)
    maps = prepare_maps(sdf[used], cameras.to(sdf.device)[used])
    ref_u = inverse[: reference.shape[0]]
    views_u = torch.where(views >= 0, inverse[reference.shape[0]:].view_as(views), torch.full_like(views, -1))
    return maps, ref_u, views_u


# --------------------------------------------------------------------------- geometry


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Small matrix product ``a (..., n, k) @ b (..., k, m)`` written as elementwise sums.

    Unlike ``@`` (which may pick different BLAS kernels for different batch sizes),
    the result of each entry does not depend on the batch, so a proposal carved
    alone gets bit-identical coordinates to the same proposal carved in a batch.
    """
    out = a[..., :, 0, None] * b[..., None, 0, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k, None] * b[..., None, k, :]
    return out


def mask_geometry(sdf: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bounding boxes and radii of the masks ``sdf < 0``.

    Args:
        sdf: ``(K, H, W)`` float signed distance maps.
        t: ``(K, 2)`` image position of each camera's object origin.

    Returns:
        ``box (K, 4)`` float64 ``(x_lo, x_hi, y_lo, y_hi)``: the extent of the
        silhouette (foreground pixel centres extended by half a pixel; the whole
        canvas for an empty mask); ``nonempty (K,)`` bool; ``radius (K,)`` float64:
        largest distance from ``t`` to a foreground pixel centre plus one pixel
        diagonal (0 for an empty mask).
    """
    K, H, W = sdf.shape
    fg = sdf < 0
    cols = fg.any(dim=1)  # (K, W)
    rows = fg.any(dim=2)  # (K, H)
    nonempty = cols.any(dim=1)
    x_lo = cols.int().argmax(dim=1)
    x_hi = W - 1 - cols.flip(1).int().argmax(dim=1)
    y_lo = rows.int().argmax(dim=1)
    y_hi = H - 1 - rows.flip(1).int().argmax(dim=1)
    half = torch.tensor([-0.5, 0.5, -0.5, 0.5], device=sdf.device, dtype=torch.float64)
    box = torch.stack([x_lo, x_hi, y_lo, y_hi], dim=1).double() + half
    full = torch.tensor([-0.5, W - 0.5, -0.5, H - 0.5], device=sdf.device, dtype=torch.float64)
    box = torch.where(nonempty[:, None], box, full)
    xs = torch.arange(W, device=sdf.device, dtype=torch.float64)
    ys = torch.arange(H, device=sdf.device, dtype=torch.float64)
    t = t.to(torch.float64)
    d2 = (xs[None, None, :] - t[:, 0, None, None]) ** 2 + (ys[None, :, None] - t[:, 1, None, None]) ** 2
    far = torch.where(fg, d2, torch.zeros((), dtype=torch.float64, device=sdf.device)).flatten(1).amax(dim=1)
    radius = torch.where(nonempty, far.sqrt() + math.sqrt(2.0), torch.zeros_like(far))
    return box, nonempty, radius


def proposal_geometry(box: torch.Tensor, nonempty: torch.Tensor, radius: torch.Tensor, cams: ScaledOrthographic,
                      reference: torch.Tensor, views: torch.Tensor, resolution: int, map_size: tuple[int, int]):
    """Grid bounds and the index -> sampling-coordinate maps of a batch of proposals.

    Args:
        box, nonempty, radius: per map, from :func:`mask_geometry` (``(M, 4)``, ``(M,)``, ``(M,)``).
        cams: ``ScaledOrthographic (M)`` (float64 preferred).
        reference: ``(B,)`` long map indices; views: ``(B, V)`` long, ``-1`` = unused.
        resolution: voxels per axis.
        map_size: ``(Hp, Wp)`` size of the extended maps that are sampled
            (canvas plus ``PAD`` on each side).

    Returns:
        ``T (B, 4, 4)`` float64 voxel_to_camera; ``G (B, V, 2, 4)`` float64 mapping
        ``(d, h, w, 1)`` to the ``grid_sample`` coordinates (``align_corners=True``) of
        the view's extended map; ``G_ref (B, 2, 4)`` the same for the reference (its
        depth column is exactly 0); ``scale (B, V)`` float64 ``s_r / s_m`` (1 for
        unused slots).
    """
    dev = box.device
    f64 = dict(dtype=torch.float64, device=dev)
    B, V = views.shape
    n = resolution
    valid = views >= 0
    vi = views.clamp(min=0)
    R, s, t = cams.R.to(**f64), cams.s.to(**f64), cams.t.to(**f64)
    Rr, sr, tr = R[reference], s[reference], t[reference]

    # x, y: the reference box tiled by n - 2 voxel cells, plus one voxel each side.
    rb = box[reference]
    sx = (rb[:, 1] - rb[:, 0]) / (n - 2)
    sy = (rb[:, 3] - rb[:, 2]) / (n - 2)
    x0 = rb[:, 0] - sx / 2
    y0 = rb[:, 2] - sy / 2

    # u_m = A p + c, p in the reference camera frame.
    A = (s[vi] / sr[:, None])[..., None, None] * _mm(R[vi][:, :, :2, :], Rr.transpose(-1, -2)[:, None])  # (B, V, 2, 3)
    c = t[vi] - _mm(A[..., :2], tr[:, None, :, None])[..., 0]  # (B, V, 2)

    # Depth bounds from each view's box, one interval per image axis (interval arithmetic).
    vb = box[vi].reshape(B, V, 2, 2)  # (B, V, axis, lo/hi)
    a0, a1, a2 = A[..., 0], A[..., 1], A[..., 2]  # (B, V, 2)
    X0, X1 = rb[:, 0, None, None], rb[:, 1, None, None]
    Y0, Y1 = rb[:, 2, None, None], rb[:, 3, None, None]
    xy_lo = torch.minimum(a0 * X0, a0 * X1) + torch.minimum(a1 * Y0, a1 * Y1)
    xy_hi = torch.maximum(a0 * X0, a0 * X1) + torch.maximum(a1 * Y0, a1 * Y1)
    lo = vb[..., 0] - c - xy_hi  # a2 z >= lo
    hi = vb[..., 1] - c - xy_lo  # a2 z <= hi
    usable = valid[..., None] & nonempty[vi][..., None] & (a2.abs() > 1e-9)
    safe = torch.where(usable, a2, torch.ones_like(a2))
    z_a, z_b = lo / safe, hi / safe
    inf = torch.full_like(z_a, math.inf)
    unbounded = torch.full((B, 1), math.inf, **f64)  # so that V = 0 reduces too
    z_lo = torch.cat([torch.where(usable, torch.minimum(z_a, z_b), -inf).flatten(1), -unbounded], 1).amax(dim=1)
    z_hi = torch.cat([torch.where(usable, torch.maximum(z_a, z_b), inf).flatten(1), unbounded], 1).amin(dim=1)
    z_lo, z_hi = torch.minimum(z_lo, z_hi), torch.maximum(z_lo, z_hi)  # inconsistent views: span between them
    rho = torch.where(valid, radius[vi] / s[vi], torch.zeros_like(s[vi]))
    cap = sr * torch.maximum(radius[reference] / sr, rho.amax(dim=1) if V else torch.zeros_like(sr))
    z_lo = torch.minimum(torch.maximum(z_lo, -cap), cap)
    z_hi = torch.minimum(torch.maximum(z_hi, -cap), cap)
    mid, half = (z_lo + z_hi) / 2, torch.clamp((z_hi - z_lo) / 2, min=0.5)
    z_lo, z_hi = mid - half, mid + half
    sz = (z_hi - z_lo) / (n - 2)
    z0 = z_lo - sz / 2

    T = torch.zeros(B, 4, 4, **f64)
    T[:, 0, 2], T[:, 0, 3] = sx, x0
    T[:, 1, 1], T[:, 1, 3] = sy, y0
    T[:, 2, 0], T[:, 2, 3] = sz, z0
    T[:, 3, 3] = 1.0

    Hp, Wp = map_size
    norm = torch.tensor([2.0 / (Wp - 1), 2.0 / (Hp - 1)], **f64)

    def to_sampling(Am, cm):  # (..., 2, 3), (..., 2) -> (..., 2, 4)
        T3 = T[:, :3].reshape((B,) + (1,) * (Am.dim() - 3) + (3, 4))
        P = _mm(Am, T3)
        P[..., 3] = P[..., 3] + cm + PAD
        P = P * norm[:, None]
        P[..., 3] = P[..., 3] - 1.0
        return P

    G = to_sampling(A, c)
    eye = torch.eye(3, **f64)[:2].expand(B, 2, 3)
    G_ref = to_sampling(eye, torch.zeros(B, 2, **f64))
    scale = torch.where(valid, sr[:, None] / s[vi], torch.ones_like(s[vi]))
    return T, G, G_ref, scale


# --------------------------------------------------------------------------- sampling


def extend_maps(sdf: torch.Tensor, pad: int = PAD) -> torch.Tensor:
    """Extend distance maps beyond their canvas by a band of ``pad`` pixels.

    The band holds ``sdf(clamp(q)) + |q - clamp(q)|`` at pixel centre ``q``: the value of
    the nearest canvas pixel plus the distance to the canvas, so outside the canvas is
    outside the silhouette (a foreground pixel on the border has ``sdf = -0.5``).

    Args:
        sdf: ``(K, H, W)`` float.

    Returns:
        ``(K, H + 2 pad, W + 2 pad)`` float32; ``out[:, pad:-pad, pad:-pad] == sdf``.
    """
    K, H, W = sdf.shape
    rep = F.pad(sdf[:, None].to(torch.float32), (pad, pad, pad, pad), mode="replicate")[:, 0]
    q = lambda n: torch.arange(-pad, n + pad, device=sdf.device, dtype=torch.float32)  # noqa: E731
    dx = torch.clamp(-q(W), min=0) + torch.clamp(q(W) - (W - 1), min=0)
    dy = torch.clamp(-q(H), min=0) + torch.clamp(q(H) - (H - 1), min=0)
    return rep + torch.sqrt(dy[:, None] ** 2 + dx[None, :] ** 2)


def _column_hw(cols: torch.Tensor, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat column indices ``h * width + w`` (any shape, long, ``0 <= h, w < width <= 2048``) to float32 ``(h, w)``.

    In float32 arithmetic (about 3x faster than int64 division on the CPU in a scratch measurement)
    and exact: ``h = floor((c + 0.5) / width)``, where ``c + 0.5`` is exact (``c < 2**22``) and
    the exact quotient ``h + (w + 0.5) / width`` lies at least ``0.5 / width >= 2**-12`` from
    every integer, more than the error of either division a device may use: correctly rounded
    (the CPU) or a multiply by the rounded reciprocal (CUDA's tensor-by-scalar division), each
    within about an ulp of a value below 2048 (``2**-13``). ``tests/test_carve.py`` checks both
    forms at every width up to 2048.
    """
    c = cols.to(torch.float32)
    h = torch.floor((c + 0.5) / width)
    return h, c - h * width


def _column_terms(G: torch.Tensor, h: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """In-plane part of the sampling coordinates of columns, for any number of maps per proposal.

    Args:
        G: ``(N, ..., 2, 4)`` float32 index -> sampling maps (e.g. ``(N, 2, 4)``, or
            ``(N, V, 2, 4)`` for every view slot at once).
        h, w: ``(N, K)`` float32 row and column indices of the columns (:func:`_column_hw`).

    Returns:
        ``(N, ..., 2, K)`` float32: ``(G[..., i, 1] h + G[..., i, 2] w) + G[..., i, 3]``
        (elementwise, so a column's value depends neither on which other columns are present
        nor on how many maps are computed at once).
    """
    shape = (h.shape[0],) + (1,) * (G.dim() - 2) + (h.shape[1],)
    h, w = h.view(shape), w.view(shape)
    return (G[..., 1, None] * h + G[..., 2, None] * w) + G[..., 3, None]


def _column_coords(G: torch.Tensor, h: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_column_terms` of ``(N, 2, 4)`` maps as the pair ``x, y``, ``(N, K)`` each."""
    x, y = _column_terms(G, h, w).unbind(1)
    return x, y


#: The maps' interpolations :func:`carve_proposals` offers (``interpolation``).
INTERPOLATIONS = ("bilinear", "nearest")


def _grid_sample(maps: torch.Tensor, grid: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """The one call into ``grid_sample``: ``mode`` (:data:`INTERPOLATIONS`), ``padding_mode="border"``,
    ``align_corners=True``."""
    return F.grid_sample(maps, grid, mode=mode, padding_mode="border", align_corners=True)


def _sample_columns(maps: torch.Tensor, G: torch.Tensor, xy: torch.Tensor, depth: torch.Tensor,
                    out: torch.Tensor | None = None, mode: str = "bilinear") -> torch.Tensor:
    """Samples of ``maps`` (interpolated as ``mode``) at the voxels of some columns.

    The coordinates of voxel ``(d, column)`` are ``G[:, :, 0] d + xy[column]``
    (:func:`_sample_planes`).

    Args:
        maps: ``(N, 1, Hp, Wp)`` float32 extended maps (already scaled).
        G: ``(N, 2, 4)`` float32 index -> sampling maps.
        xy: ``(N, 2, K)`` column terms (:func:`_column_terms`).
        depth: ``(D,)`` float32 depth indices.
        out: optional float32 buffer of at least ``N * 2 * D * K`` elements for the coordinates.

    Returns:
        ``(N, D, K)`` float32 samples.
    """
    return _sample_planes(maps, G[:, :, 0, None] * depth, xy, out, mode)


def _sample_planes(maps: torch.Tensor, dz: torch.Tensor, xy: torch.Tensor, out: torch.Tensor | None = None,
                   mode: str = "bilinear") -> torch.Tensor:
    """Samples of ``maps`` at the coordinates ``dz[:, :, d] + xy[:, :, k]`` (depth term plus column term).

    The coordinates are written as two planes ``(N, 2, D, K)`` (one vectorised broadcast
    add) and handed to ``grid_sample`` as the view ``(N, D, K, 2)`` (it takes strided grids).

    Args:
        maps: ``(N, 1, Hp, Wp)`` float32 extended maps (already scaled).
        dz: ``(N, 2, D)`` float32 depth terms ``G[:, :, 0] d``.
        xy: ``(N, 2, K)`` float32 column terms (:func:`_column_terms`).
        out: optional float32 buffer of at least ``N * 2 * D * K`` elements for the coordinates.

    Returns:
        ``(N, D, K)`` float32 samples.
    """
    N, _, D = dz.shape
    K = xy.shape[2]
    if out is None:
        out = torch.empty(N * 2 * D * K, device=maps.device)
    planes = out.view(-1)[: N * 2 * D * K].view(N, 2, D, K)
    torch.add(dz[:, :, :, None], xy[:, :, None, :], out=planes)
    return _grid_sample(maps, planes.permute(0, 2, 3, 1), mode)[:, 0]


def _sample_columns_at(maps: torch.Tensor, G: torch.Tensor, xy: tuple[torch.Tensor, torch.Tensor], d: torch.Tensor,
                       out: torch.Tensor | None = None, mode: str = "bilinear") -> torch.Tensor:
    """Samples of ``maps`` (interpolated as ``mode``) at voxels ``(d[:, l, k], column k)``: each column its own depths.

    Same arithmetic as :func:`_sample_columns` (``G[:, :, 0] d``, then plus the column
    term), so a voxel gets the same value bit for bit.

    Args:
        maps: ``(N, 1, Hp, Wp)`` float32 extended maps (already scaled).
        G: ``(N, 2, 4)`` float32 index -> sampling maps.
        xy: from :func:`_column_coords`, ``(N, K)`` each.
        d: ``(N, L, K)`` float32 depth indices.
        out: optional float32 buffer of at least ``N * 2 * L * K`` elements.

    Returns:
        ``(N, L, K)`` float32 samples.
    """
    N, L, K = d.shape
    if out is None:
        out = torch.empty(N * 2 * L * K, device=maps.device)
    planes = out.view(-1)[: N * 2 * L * K].view(N, 2, L, K)
    for i in range(2):
        torch.mul(G[:, i, 0, None, None], d, out=planes[:, i])
        planes[:, i] += xy[i][:, None, :]
    return _grid_sample(maps, planes.permute(0, 2, 3, 1), mode)[:, 0]


def _sample_points(maps: torch.Tensor, G: torch.Tensor, d: torch.Tensor, h: torch.Tensor,
                   w: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Samples of ``maps`` (interpolated as ``mode``) at voxels ``(d, h, w)``, ``(N, K)`` float32 indices each.

    Same arithmetic as :func:`_sample_columns` (``G[:, :, 0] d`` plus the column term of
    :func:`_column_coords`), so a voxel gets the same value bit for bit. Returns ``(N, K)`` float32.
    """
    N, K = d.shape
    planes = torch.empty(N, 2, K, device=maps.device)
    xy = _column_coords(G, h, w)
    for i in range(2):
        torch.add(G[:, i, 0, None] * d, xy[i], out=planes[:, i])
    return _grid_sample(maps, planes.permute(0, 2, 1)[:, None], mode)[:, 0, 0]


def _label(cost: torch.Tensor, column_cost: torch.Tensor, imprint: bool
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Interior labels along axis 1 (depth), with or without imprinting.

    Args:
        cost: ``(N, D, K)`` float ``C`` of ``K`` columns.
        column_cost: ``(N, K)`` reference cost at the column centres (foreground iff ``< 0``).
        imprint: also label, in every foreground column with no voxel of ``C < 0``,
            the first voxel (lowest ``d``) of minimal ``C`` (``argmin``).

    Returns:
        ``inside (N, D, K)`` bool, ``nonempty (N,)`` bool (any interior voxel) and
        ``occupied (N, K)`` bool (the columns holding an interior voxel).
    """
    inside = cost < 0
    low = cost.amin(dim=1)  # (N, K)
    occupied = low < 0
    nonempty = occupied.any(dim=1)
    if imprint:
        need = (column_cost < 0) & ~occupied  # foreground, nothing inside
        n_idx, k_idx = need.nonzero(as_tuple=True)
        if n_idx.numel():
            d_idx = cost[n_idx, :, k_idx].argmin(dim=1)  # only the columns that need it
            inside[n_idx, d_idx, k_idx] = True
            nonempty = nonempty | need.any(dim=1)
            occupied = occupied | need
    return inside, nonempty, occupied


def _foreground_first(fg: torch.Tensor) -> torch.Tensor:
    """Stable partition of columns: ``(B, HW)`` bool -> ``(B, HW)`` long permutation of each row,
    its ``True`` columns first, each part in ascending order (``argsort(~fg, stable=True)``,
    computed by counting instead of sorting).

    Example:
        >>> _foreground_first(torch.tensor([[False, True, False, True]]))
        tensor([[1, 3, 0, 2]])
    """
    B, HW = fg.shape
    before = fg.cumsum(1)  # foreground columns up to and including each one
    j = torch.arange(HW, device=fg.device)
    pos = torch.where(fg, before - 1, before[:, -1:] + j - before)
    return torch.empty_like(pos).scatter_(1, pos, j.expand(B, -1))


def _pad_rows(row: torch.Tensor, values: torch.Tensor, n_rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Ragged lists to padded rows.

    Args:
        row: ``(P,)`` long row of each entry, sorted ascending.
        values: ``(C, P)`` values of the entries.
        n_rows: number of rows.

    Returns:
        ``valid (n_rows, K)`` bool (``K`` = longest row) and the values as
        ``(C, n_rows, K)``, entries in their original order along each row, padding 0.
    """
    P = row.numel()
    counts = torch.bincount(row, minlength=n_rows)
    K = int(counts.max()) if P else 0
    rank = torch.arange(P, device=row.device) - (torch.cumsum(counts, 0) - counts)[row]
    valid = torch.zeros(n_rows, K, dtype=torch.bool, device=row.device)
    valid[row, rank] = True
    out = torch.zeros(values.shape[0], n_rows, K, dtype=values.dtype, device=values.device)
    out[:, row, rank] = values
    return valid, out


# --------------------------------------------------------------------------- carving


def _prepare(maps: CarveMaps, reference: torch.Tensor, views: torch.Tensor, resolution: int, keep_double=False):
    """Maps and geometry shared by the batched and the loop implementations.

    Returns ``ext`` (the extended maps), ``ref_m (B,)`` and ``views_m (B, V)`` (rows of ``ext``;
    unused slots: the unused-slot map), and ``T, G, G_ref, scale`` of :func:`proposal_geometry`
    (``G_ref``, ``scale`` in float32, ``G`` too unless ``keep_double``).
    """
    ref_m = maps.entry_map[reference]
    views_m = torch.where(views >= 0, maps.entry_map[views.clamp(min=0)], maps.unused)
    T, G, G_ref, scale = proposal_geometry(maps.box, maps.nonempty, maps.radius, maps.cameras, reference, views,
                                           resolution, tuple(maps.ext.shape[1:]))
    return maps.ext, ref_m, views_m, T, (G if keep_double else G.float()), G_ref.float(), scale.float()


def _reference_columns(ext, ref_u, G_ref, H_grid, W_grid, mode="bilinear"):
    """``(B, H_grid * W_grid)`` reference cost at every column centre."""
    B = ref_u.shape[0]
    h, w = _column_hw(torch.arange(H_grid * W_grid, device=ext.device).expand(B, -1), W_grid)
    zero = torch.zeros(1, device=ext.device, dtype=torch.float32)
    return _sample_columns(torch.index_select(ext, 0, ref_u)[:, None], G_ref, _column_terms(G_ref, h, w), zero,
                           mode=mode)[:, 0]


def _pixel_differences(ext: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``lx, ly``: ``(K,)`` float64 largest absolute difference between neighbouring pixels of each
    map ``ext (K, H, W)``, along x (within rows) and along y (within columns).

    The bilinear interpolant's partial derivatives are convex combinations of such differences,
    so over a step ``(dx, dy)`` it changes by at most ``lx |dx| + ly |dy|``.
    """
    lx = (ext[:, :, 1:] - ext[:, :, :-1]).abs().flatten(1).amax(1)
    ly = (ext[:, 1:] - ext[:, :-1]).abs().flatten(1).amax(1)
    return lx.double(), ly.double()


def _lipschitz(ext: torch.Tensor) -> torch.Tensor:
    """``(K,)`` bound on the gradient norm of the bilinear interpolant of each map.

    The interpolant's partial derivatives are convex combinations of adjacent pixel
    differences, so ``|grad| <= sqrt(max|dx|^2 + max|dy|^2)``: ``sqrt 2`` for an exact
    signed distance map (adjacent values differ by at most one pixel), 0 for a constant.
    """
    lx, ly = _pixel_differences(ext)
    return torch.sqrt(lx ** 2 + ly ** 2)


class _Chunk:
    """The per-chunk state of the batched carving: maps per view slot, geometry, columns.

    Attributes: ``maps`` (list over slots of ``(N, 1, Hp, Wp)`` scaled maps or ``None``
    for a slot unused by every proposal), ``G (N, V, 2, 4)``, ``column_cost (N, HW)``.
    ``slots`` (host bools, one per slot): whether any proposal of the chunk uses the slot
    (known on the host, so building a chunk reads nothing back from the device).
    """

    def __init__(self, ext, views_c, scale_c, G_c, column_cost_c, n, slots, mode="bilinear"):
        # index_select copies whole maps (several times faster than advanced indexing on the CPU)
        self.maps = [torch.index_select(ext, 0, views_c[:, j]).mul_(scale_c[:, j, None, None])[:, None] if used
                     else None for j, used in enumerate(slots)]
        self.G, self.column_cost, self.n, self.mode = G_c, column_cost_c, n, mode

    def columns(self, cols: torch.Tensor, depth: torch.Tensor, buf=None) -> torch.Tensor:
        """Exact ``C`` at ``depth (D,)`` of flat columns ``cols (N, K)``: ``(N, D, K)`` float32."""
        h, w = _column_hw(cols, self.n)
        # the depth and column terms of every used slot at once (a few operations per chunk, not per slot)
        used = [j for j, maps in enumerate(self.maps) if maps is not None]
        G = self.G if len(used) == len(self.maps) else self.G[:, used]  # (N, U, 2, 4)
        dz = G[..., 0, None] * depth  # (N, U, 2, D)
        xy = _column_terms(G, h, w)  # (N, U, 2, K)
        acc = None
        for u, j in enumerate(used):
            sample = _sample_planes(self.maps[j], dz[:, u], xy[:, u], out=buf, mode=self.mode)
            acc = sample if acc is None else torch.maximum(acc, sample, out=acc)
        col = self.column_cost.gather(1, cols)[:, None, :]
        return col.expand(-1, depth.shape[0], -1).contiguous() if acc is None else torch.maximum(acc, col, out=acc)

    def columns_at(self, cols: torch.Tensor, d: torch.Tensor, buf=None) -> torch.Tensor:
        """Exact ``C`` at depths ``d (N, L, K)`` (float32) of flat columns ``cols (N, K)``: ``(N, L, K)`` float32."""
        h, w = _column_hw(cols, self.n)
        acc = None
        for j, maps in enumerate(self.maps):
            if maps is not None:
                sample = _sample_columns_at(maps, self.G[:, j], _column_coords(self.G[:, j], h, w), d, out=buf,
                                            mode=self.mode)
                acc = sample if acc is None else torch.maximum(acc, sample, out=acc)
        col = self.column_cost.gather(1, cols)[:, None, :]
        return col.expand_as(d).contiguous() if acc is None else torch.maximum(acc, col, out=acc)

    def points(self, d: torch.Tensor, h: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """Exact ``C`` at voxels ``(d, h, w)`` (``(N, K)`` long each): ``(N, K)`` float32."""
        df, hf, wf = d.float(), h.float(), w.float()
        acc = None
        for j, maps in enumerate(self.maps):
            if maps is not None:
                sample = _sample_points(maps, self.G[:, j], df, hf, wf, self.mode)
                acc = sample if acc is None else torch.maximum(acc, sample, out=acc)
        col = self.column_cost.gather(1, h * self.n + w)
        return col.clone() if acc is None else torch.maximum(acc, col, out=acc)


#: Column groups of the interval carving (columns sorted by interval length; each group is
#: sampled at the depths of its longest interval).
_INTERVAL_GROUPS = 4
#: Depth-slope (normalised sampling units per voxel) below which a view does not bound a column.
_FLAT = 1e-5


def _column_intervals(G: torch.Tensor, box: torch.Tensor, valid: torch.Tensor, cols: torch.Tensor, n: int,
                      map_size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth intervals outside which the voxels of some columns are provably exterior.

    The box of a view's mask (:func:`mask_geometry`: its negative pixels' centres extended by
    half a pixel) is widened by another half pixel: beyond it every bilinear neighbour is a
    pixel outside the box, where the map is not negative (any map, not only distance maps),
    so ``C >= 0`` there and the voxel is exterior. A side of the box on the canvas edge bounds
    nothing (the band beyond the canvas may continue a negative value). Along a column the
    projection into view ``m`` moves linearly with depth, so each view and image axis bounds
    the depth to an interval; they are intersected and widened by one voxel (float slack).

    Args:
        G: ``(N, V, 2, 4)`` index -> sampling maps (float64 preferred).
        box: ``(N, V, 4)`` float64 boxes of the views' masks (canvas pixels).
        valid: ``(N, V)`` bool used slots.
        cols: ``(N, K)`` long flat columns ``h * n + w``.
        n: resolution; map_size: ``(Hp, Wp)`` of the extended maps.

    Returns:
        ``lo, hi`` ``(N, K)`` long, clamped to ``[0, n - 1]``; ``lo > hi`` when no voxel of
        the column can be interior.
    """
    Hp, Wp = map_size
    size = (Wp - 2 * PAD, Hp - 2 * PAD)
    G = G.double()
    h = torch.div(cols, n, rounding_mode="floor").double()
    w = (cols % n).double()
    lo = torch.zeros(cols.shape, dtype=torch.float64, device=cols.device)
    hi = torch.full(cols.shape, float(n - 1), dtype=torch.float64, device=cols.device)
    scale = (2.0 / (Wp - 1), 2.0 / (Hp - 1))
    for j in range(G.shape[1]):
        for i in range(2):
            g = G[:, j, i]
            c = g[:, 1, None] * h + g[:, 2, None] * w + g[:, 3, None]
            first, last = box[:, j, 2 * i], box[:, j, 2 * i + 1]
            a = torch.where(first > -0.5, (first - 0.5 + PAD) * scale[i] - 1.0, -math.inf)[:, None]
            b = torch.where(last < size[i] - 0.5, (last + 0.5 + PAD) * scale[i] - 1.0, math.inf)[:, None]
            g0 = g[:, 0, None].expand_as(c)
            use = valid[:, j, None] & (g0.abs() > _FLAT)
            safe = torch.where(use, g0, torch.ones_like(g0))
            d1, d2 = (a - c) / safe, (b - c) / safe
            lo = torch.where(use, torch.maximum(lo, torch.minimum(d1, d2)), lo)
            hi = torch.where(use, torch.minimum(hi, torch.maximum(d1, d2)), hi)
            # a view that hardly moves along the column: the column is outside its box or not at all
            off = valid[:, j, None] & ~use & ((c < a - 1e-3) | (c > b + 1e-3))
            lo = torch.where(off, torch.full_like(lo, math.inf), lo)
    lo = torch.ceil(lo - 1.0).clamp(0, n)
    hi = torch.floor(hi + 1.0).clamp(-1, n - 1)
    return lo.long(), hi.long()


def _carve_chunk_intervals(chunk: "_Chunk", cols: torch.Tensor, fg: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                           imprint: bool, buf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Labels of a chunk sampling only the depth interval of every foreground column.

    Columns are sorted by interval length and split into :data:`_INTERVAL_GROUPS` groups, each
    sampled at ``L_g`` depths from its columns' ``lo`` (``L_g`` = the group's longest interval;
    depths past the grid are clamped, duplicate samples of one voxel agree). Voxels outside
    the intervals are exterior (:func:`_column_intervals`). A foreground column left without an
    interior voxel is imprinted at the first argmin of ``C`` over its *whole* depth, sampled
    for those columns only. Values are those of the full evaluation bit for bit, so the labels
    are identical.

    Args:
        chunk: ``N`` proposals; cols: ``(N, K)`` flat foreground columns first (padding columns
            are background); fg: ``(N, HW)`` bool; lo, hi: ``(N, K)`` from :func:`_column_intervals`.
        buf: float32 buffer of at least ``N * K * n * 2`` elements.

    Returns:
        ``occupancy (N, n, HW)`` bool, ``nonempty (N,)`` bool, ``columns (N, HW)`` bool occupied columns.
    """
    n, N, K = chunk.n, cols.shape[0], cols.shape[1]
    HW = n * n
    dev = cols.device
    length = (hi - lo + 1).clamp(min=0)
    length = torch.where(fg.gather(1, cols), length, torch.zeros_like(length))
    order = torch.argsort(length, dim=1, descending=True, stable=True)
    cols, lo, length = cols.gather(1, order), lo.gather(1, order), length.gather(1, order)
    bounds = [round(K * g / _INTERVAL_GROUPS) for g in range(_INTERVAL_GROUPS + 1)]
    bounds = sorted(set(bounds))
    starts = torch.tensor(bounds[:-1], device=dev)
    lengths = length[:, starts].amax(dim=0).tolist()  # one host read: the depths of each group
    occ = torch.zeros(N, n * HW, dtype=torch.bool, device=dev)
    occupied = torch.zeros(N, HW, dtype=torch.bool, device=dev)
    for (k0, k1), L in zip(zip(bounds[:-1], bounds[1:]), lengths):
        if L == 0:
            continue
        cg = cols[:, k0:k1]
        d = (lo[:, None, k0:k1] + torch.arange(L, device=dev)[None, :, None]).clamp_(max=n - 1)  # (N, L, Kg)
        acc = chunk.columns_at(cg, d.float(), buf)
        occ.scatter_(1, (d * HW + cg[:, None, :]).view(N, -1), (acc < 0).view(N, -1))
        occupied.scatter_(1, cg, acc.amin(dim=1) < 0)
    nonempty = occupied.any(dim=1)
    if imprint:
        need = fg & ~occupied
        b_n, c_n = need.nonzero(as_tuple=True)
        if b_n.numel():
            valid, (cn,) = _pad_rows(b_n, c_n[None], N)
            depth = torch.arange(n, device=dev, dtype=torch.float32)
            full = chunk.columns(cn, depth, buf)  # (N, n, Kn): whole columns
            best = full.argmin(dim=1)  # the first minimum
            rows = torch.arange(N, device=dev)[:, None].expand_as(cn)
            occ[rows[valid], best[valid] * HW + cn[valid]] = True
            nonempty = nonempty | need.any(dim=1)
            occupied = occupied | need
    return occ.view(N, n, HW), nonempty, occupied


#: The eight fine voxels of a coarse block, as offsets (d, h, w) from its representative.
_BLOCK = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]


def _carve_chunk_coarse_to_fine(chunk: _Chunk, fg: torch.Tensor, tol: torch.Tensor, slack: torch.Tensor,
                                imprint: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Labels of a chunk from exact costs at a subset of voxels, identical to sampling them all.

    Blocks of 2x2x2 voxels are represented by their voxel of even indices. ``C`` is
    ``L``-Lipschitz in reference pixels (``L`` = the largest :func:`_lipschitz` of the
    proposal's maps: each ``C_m`` is a map scaled by ``s_r / s_m`` composed with a
    projection of norm ``s_m / s_r``), and every voxel of a block lies within
    ``sqrt(sx^2 + sy^2 + sz^2)`` of the representative. So a representative with
    ``|C| > tol`` (``tol`` = that radius times ``L``, plus a float slack) fixes the sign
    of its whole block; the voxels of the other blocks are evaluated exactly. For
    imprinting, the columns left without an interior voxel need the first argmin of
    ``C`` along depth: each block bounds its voxels' costs within ``C_rep +- tol``, so
    only the blocks whose lower bound reaches the column's least upper bound can hold
    the minimum, and only their voxels are evaluated.

    Args:
        chunk: maps and geometry of ``N`` proposals.
        fg: ``(N, HW)`` bool foreground columns.
        tol: ``(N,)`` float32 block radius times the Lipschitz bound.
        slack: ``(N,)`` float32 absolute float slack added to every bound (plus ``1e-5 |C|``).
        imprint: as in :func:`carve_proposals`.

    Returns:
        ``occupancy (N, D, H, W)`` bool and ``nonempty (N,)`` bool.
    """
    n = chunk.n
    N = fg.shape[0]
    dev = fg.device
    n3 = n * n * n
    nb = (n + 1) // 2  # blocks per axis; representative of block i: voxel 2 i
    # Block columns holding a foreground column, first in each row.
    fg_sq = torch.zeros(N, 2 * nb, 2 * nb, dtype=torch.bool, device=dev)
    fg_sq[:, :n, :n] = fg.view(N, n, n)
    active_bc = fg_sq.view(N, nb, 2, nb, 2).any(dim=4).any(dim=2).view(N, nb * nb)
    n_active = active_bc.sum(dim=1)
    kc = max(int(n_active.max()), 1)
    bcols = torch.argsort((~active_bc).to(torch.uint8), dim=1, stable=True)[:, :kc]  # (N, kc)
    active = torch.arange(kc, device=dev) < n_active[:, None]
    bj, bk = torch.div(bcols, nb, rounding_mode="floor"), bcols % nb

    # 1. Exact cost at the representatives.
    depth_even = torch.arange(0, n, 2, device=dev, dtype=torch.float32)
    coarse = chunk.columns(2 * bj * n + 2 * bk, depth_even)  # (N, nb, kc)
    margin = tol[:, None, None] + slack[:, None, None] + 1e-5 * coarse.abs()
    sure_in = (coarse < -margin) & active[:, None, :]
    unsure = (coarse.abs() <= margin) & active[:, None, :]

    # Labels of the sure blocks, upsampled; one spare element at the end takes the
    # writes of padding entries below.
    blocks = torch.zeros(N, nb, nb * nb, dtype=torch.bool, device=dev)
    blocks.scatter_(2, bcols[:, None, :].expand(-1, nb, -1), sure_in)
    up = blocks.view(N, nb, 1, nb, 1, nb, 1).expand(N, nb, 2, nb, 2, nb, 2).reshape(N, 2 * nb, 2 * nb, 2 * nb)
    flat = torch.empty(N * n3 + 1, dtype=torch.bool, device=dev)
    occ = flat[:-1].view(N, n, n, n)
    occ.copy_(up[:, :n, :n, :n])
    nonempty = sure_in.flatten(1).any(dim=1)

    # 2. Exact cost of the voxels of unsure blocks (in foreground columns).
    b_i, i_i, k_i = unsure.nonzero(as_tuple=True)
    if b_i.numel():
        off = torch.tensor(_BLOCK, device=dev).T[:, None, :]  # (3, 1, 8)
        base = torch.stack([2 * i_i, 2 * bj[b_i, k_i], 2 * bk[b_i, k_i]])[:, :, None]  # (3, P, 1)
        dhw = (base + off).view(3, -1)  # (3, 8P): d, h, w
        row = b_i[:, None].expand(-1, 8).reshape(-1)
        keep = (dhw < n).all(dim=0)
        keep &= fg[row, (dhw[1] * n + dhw[2]).clamp(max=n * n - 1)]
        entries = torch.cat([dhw, row[None]])[:, keep]  # (4, P'): d, h, w, row
        d, h, w, row = entries
        valid, (dp, hp, wp, at) = _pad_rows(row, torch.cat([entries[:3], (((row * n + d) * n + h) * n + w)[None]]), N)
        inside = chunk.points(dp, hp, wp) < 0
        flat.index_put_((torch.where(valid, at, N * n3),), inside)
        nonempty |= (inside & valid).any(dim=1)

    if imprint:
        # 3. Columns without an interior voxel: evaluate the blocks that can hold the argmin.
        need = fg & ~occ.any(dim=1).view(N, n * n)
        b_n, c_n = need.nonzero(as_tuple=True)  # sorted by proposal
        if b_n.numel():
            hn, wn = torch.div(c_n, n, rounding_mode="floor"), c_n % n
            pos = torch.zeros(N, nb * nb, dtype=torch.long, device=dev)
            pos.scatter_(1, bcols, torch.arange(kc, device=dev).expand(N, -1))
            bc = torch.div(hn, 2, rounding_mode="floor") * nb + torch.div(wn, 2, rounding_mode="floor")
            cv = coarse[b_n, :, pos[b_n, bc]]  # (P, nb)
            mv = tol[b_n, None] + slack[b_n, None] + 1e-5 * cv.abs()
            least_upper = (cv + mv).amin(dim=1, keepdim=True)
            candidate = (cv - mv <= least_upper).repeat_interleave(2, dim=1)[:, :n]  # (P, n) fine depths
            p_i, d_c = candidate.nonzero(as_tuple=True)
            b_c, h_c, w_c = torch.stack([b_n, hn, wn])[:, p_i]
            valid, (d2, h2, w2) = _pad_rows(b_c, torch.stack([d_c, h_c, w_c]), N)
            table = torch.full((b_n.shape[0], n), math.inf, device=dev)
            table[p_i, d_c] = chunk.points(d2, h2, w2)[valid]  # row-major: the order of (p_i, d_c)
            best = table.argmin(dim=1)  # the first minimum, as a dense argmin
            flat[((b_n * n + best) * n + hn) * n + wn] = True
            nonempty |= need.any(dim=1)
    return occ, nonempty


def default_batch_voxels(device: torch.device | str) -> int:
    """Default ``max_batch_voxels`` of :func:`carve_proposals` on ``device``.

    CUDA: ``2**25``. CPU: ``2**19`` voxels per intra-op thread (``torch.get_num_threads()``),
    at most ``2**21``: a chunk's coordinates and samples then stay near the cores' caches,
    while the per-chunk work stays amortised. Measured on the pipeline's proposals
    (docs/benchmarks/README.md): with 1 thread ``2**19`` was 9% faster than ``2**20``
    (bilinear and nearest), with 2 threads ``2**20`` 7% faster than ``2**19`` (bilinear).

    Example:
        >>> default_batch_voxels("cuda")
        33554432
    """
    dev = torch.device(device)
    if dev.type != "cpu":
        return _DEFAULT_BATCH_VOXELS.get(dev.type, _DEFAULT_BATCH_VOXELS["cuda"])
    return min(_DEFAULT_BATCH_VOXELS["cpu"] * max(1, torch.get_num_threads()), _CPU_BATCH_VOXELS_MAX)


def _chunk_multiple(device: torch.device) -> int:
    """Chunks hold a multiple of this many proposals where the budget allows: the intra-op
    thread count on the CPU, 1 elsewhere.

    The CPU ``grid_sample`` shares a call's work among the threads by batch index, whole
    batch entries each, so a chunk of 7 proposals on 2 threads keeps one thread idle for a
    proposal's time (13% slower per proposal than 8 in a scratch measurement). With this
    rounding (and the per-chunk coordinate terms) the carving was 1.14x faster bilinear and
    1.24x nearest at 2 threads (docs/benchmarks/README.md, "Balanced threads"); splitting each
    proposal's depths into one batch entry per thread instead was slower (its maps are copied
    once per thread).
    """
    return max(1, torch.get_num_threads()) if device.type == "cpu" else 1


def _fused_inputs(maps: CarveMaps, reference: torch.Tensor, views: torch.Tensor, n: int):
    """What :func:`carvi_torch.carve_fused.carve_labels` takes for these proposals (bilinear maps).

    Returns:
        ``ext`` (the extended maps), ``slots (B, V)`` (row of ``ext`` per view slot, ``-1`` unused),
        ``scale (B, V)`` and ``G (B, V, 2, 4)`` float32, ``column_cost (B, n * n)``, and ``T (B, 4, 4)``
        the voxel-to-camera maps (float64).
    """
    ext, ref_u, views_u, T, G, G_ref, scale = _prepare(maps, reference, views, n)
    column_cost = _reference_columns(ext, ref_u, G_ref, n, n)
    return ext, torch.where(views >= 0, views_u, -1), scale, G, column_cost, T


def _use_fused(backend: str, device: torch.device, interpolation: str, return_cost: bool, coarse_to_fine: bool,
               depth_intervals: bool, V: int) -> bool:
    """Whether :func:`carve_proposals` runs the fused kernel (``backend="fused"`` where it cannot: an error)."""
    if backend == "torch":
        return False
    why = None
    if device.type != "cpu":
        why = f"it runs on the CPU, not {device.type}"
    elif interpolation != "bilinear":
        why = f"it reads the maps bilinearly, not {interpolation!r}"
    elif return_cost or coarse_to_fine or depth_intervals:
        why = "it computes labels only (no return_cost, coarse_to_fine or depth_intervals)"
    elif V > carve_fused.MAX_VIEWS:
        why = f"it takes at most {carve_fused.MAX_VIEWS} view slots, not {V}"
    elif not carve_fused.available():
        why = f"it is not available here: {carve_fused.unavailable_reason()}"
    if why is not None and backend == "fused":
        raise ValueError(f"backend='fused' cannot carve this call: {why}")
    return why is None


def resolve_backend(backend: str, device: torch.device | str, interpolation: str = "bilinear") -> dict:
    """What :func:`carve_proposals` runs for a labels-only call (the pipeline's) with these settings.

    Returns:
        ``{"backend": "fused" | "torch", "variant": "fma" | "plain" | None, "reason": str | None}``:
        the fused kernel's sample arithmetic when it runs, and why it does not when ``backend`` is
        ``"auto"`` on the CPU (no compiler, say). Raises ``ValueError`` as :func:`carve_proposals`
        does for ``backend="fused"`` where the kernel cannot run.

    Example:
        >>> resolve_backend("torch", "cpu")
        {'backend': 'torch', 'variant': None, 'reason': None}
    """
    if backend not in carve_fused.BACKENDS:
        raise ValueError(f"backend must be one of {carve_fused.BACKENDS}, got {backend!r}")
    dev = torch.device(device)
    if _use_fused(backend, dev, interpolation, False, False, False, 0):
        return {"backend": "fused", "variant": carve_fused.variant(), "reason": None}
    reason = None
    if backend == "auto" and dev.type == "cpu" and interpolation == "bilinear":
        reason = carve_fused.unavailable_reason()
    return {"backend": "torch", "variant": None, "reason": reason}


def carve_proposals(sdf: torch.Tensor, cameras: ScaledOrthographic, reference: torch.Tensor, views: torch.Tensor, *,
                    resolution: int = 60, imprint: bool = True, max_batch_voxels: int | None = None,
                    return_cost: bool = False, coarse_to_fine: bool = False,
                    depth_intervals: bool = False, interpolation: str = "bilinear",
                    backend: str = "auto") -> ProposalGrids:
    """Carve the imprinted visual hulls of ``B`` proposals in one batched computation.

    Proposal ``b`` carves reference map ``reference[b]`` with the maps ``views[b]``
    (``-1`` = unused slot) on a ``resolution^3`` grid in the reference camera frame
    (see the module docstring for frames, bounds and units). Proposals are processed
    in chunks of at most ``max_batch_voxels`` voxels (a loop over chunks and over the
    ``V`` view slots; everything else is batched, one ``grid_sample`` call per chunk,
    slot and stage). Views are sampled only along the reference's foreground columns;
    with ``depth_intervals`` only within each column's depth interval that the views'
    mask boxes leave (:func:`_carve_chunk_intervals`); with ``coarse_to_fine`` only where
    the sign of ``C`` or the imprinting argmin is not already decided by exact costs on a
    grid of half the resolution and the Lipschitz bound of the maps (see
    :func:`_carve_chunk_coarse_to_fine`). The labels are identical to evaluating every voxel.

    Args:
        sdf: ``(M, H, W)`` float signed distance maps (:func:`carvi_torch.sdf.signed_distance`),
            or :class:`CarveMaps` prepared once (:func:`prepare_maps`; then ``cameras`` is
            ``None`` and indices are its entries).
        cameras: ``ScaledOrthographic`` of length ``M``, in the maps' pixels.
        reference: ``(B,)`` long indices into ``sdf``.
        views: ``(B, V)`` long indices into ``sdf``, ``-1`` for an unused slot.
        resolution: voxels per axis (4 to 2048).
        imprint: fill every foreground column of the reference that has no interior
            voxel at its voxel of minimal cost.
        max_batch_voxels: bound on the voxels of the foreground columns of a chunk;
            default :func:`default_batch_voxels` (``2**19`` per thread on CPU, ``2**25`` on CUDA).
        return_cost: also return the full cost ``C (B, D, H, W)`` (samples every column
            at every depth; no coarse-to-fine).
        coarse_to_fine: skip the voxels whose labels exact coarse costs decide. Off
            by default: on the pipeline's proposals (60^3, CPU, ``tools/benchmark.py``) it
            sampled 45-47% fewer voxels but its bookkeeping made it 2.4-2.6x slower than sampling
            every voxel of the foreground columns; kept, exact and tested, for devices
            where sampling dominates.
        depth_intervals: sample each foreground column only within the depths its views'
            mask boxes allow (21-26% fewer samples on the pipeline's proposals). Off by
            default: on the CPU its bookkeeping costs more than the samples save (1.2-1.65x
            slower, ``docs/benchmarks/README.md``); to be measured on CUDA by the benchmark.
        interpolation: how the distance maps are read at a voxel's projection (:data:`INTERPOLATIONS`):
            ``"bilinear"`` (the default, the reference implementation's) or ``"nearest"`` (the
            pixel the voxel falls in: a cheaper sample, an approximation of the bilinear labels;
            measured in docs/benchmarks/README.md). Neither ``coarse_to_fine`` nor
            ``depth_intervals`` with ``"nearest"``: their bounds assume continuous maps.
        backend: who computes the labels (:data:`carvi_torch.carve_fused.BACKENDS`). ``"torch"``:
            the batched ``grid_sample`` carving described above. ``"fused"``: the compiled CPU
            kernel of :mod:`carvi_torch.carve_fused`, which samples, takes the maximum and labels
            in one pass and stops reading a voxel's views as soon as its labels are decided
            (same labels voxel for voxel; CPU, bilinear, without ``return_cost``,
            ``coarse_to_fine`` or ``depth_intervals``). ``"auto"`` (default): ``"fused"`` where
            it applies and the kernel is available, else ``"torch"``.

    Returns:
        :class:`ProposalGrids`; voxel for voxel equal to :func:`carve_proposals_loop` with the
        same ``interpolation``, whichever the backend.

    Example:
        >>> masks = torch.zeros(2, 32, 32, dtype=torch.bool); masks[:, 8:24, 10:22] = True
        >>> cams = ScaledOrthographic(torch.eye(3).expand(2, 3, 3), torch.ones(2), torch.full((2, 2), 16.0))
        >>> out = carve_proposals(signed_distance(masks), cams, torch.tensor([0]), torch.tensor([[1]]), resolution=16)
        >>> out.occupancy.shape, bool(out.empty[0])
        (torch.Size([1, 16, 16, 16]), False)
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    if interpolation != "bilinear" and (coarse_to_fine or depth_intervals):
        raise ValueError("coarse_to_fine and depth_intervals bound the bilinear maps; they do not take "
                         f"interpolation={interpolation!r}")
    if backend not in carve_fused.BACKENDS:
        raise ValueError(f"backend must be one of {carve_fused.BACKENDS}, got {backend!r}")
    maps, reference, views = _as_maps(sdf, cameras, reference, views, resolution)
    dev = maps.device
    # (resolutions: carve_proposals takes at most 2048, the kernel's MAX_RESOLUTION)
    fused = _use_fused(backend, dev, interpolation, return_cost, coarse_to_fine, depth_intervals, views.shape[1])
    if max_batch_voxels is None:
        max_batch_voxels = default_batch_voxels(dev)
    if not isinstance(max_batch_voxels, int) or max_batch_voxels < 1:
        raise ValueError(f"max_batch_voxels must be a positive int, got {max_batch_voxels!r}")
    B, V = views.shape
    n = resolution
    HW = n * n
    if B == 0:
        z = torch.zeros(0, n, n, n, dtype=torch.bool, device=dev)
        return ProposalGrids(z, torch.zeros(0, 4, 4, device=dev), torch.zeros(0, dtype=torch.bool, device=dev),
                             z[:, 0], torch.zeros(0, n, n, device=dev), z.float() if return_cost else None, z[:, 0])
    if fused:
        ext, slots, scale, G, column_cost, T = _fused_inputs(maps, reference, views, n)
        occ, columns, nonempty, _ = carve_fused.carve_labels(ext, slots, scale, G, column_cost, n, imprint)
        return ProposalGrids(occupancy=occ.view(B, n, n, n), voxel_to_camera=T.float(), empty=~nonempty,
                             reference_columns=(column_cost < 0).view(B, n, n), column_cost=column_cost.view(B, n, n),
                             cost=None, columns=columns.view(B, n, n))
    ext, ref_u, views_u, T, G, G_ref, scale = _prepare(maps, reference, views, resolution, keep_double=True)
    G64, G = G, G.float()
    column_cost = _reference_columns(ext, ref_u, G_ref, n, n, interpolation)  # (B, HW)
    fg = column_cost < 0
    depth = torch.arange(n, device=dev, dtype=torch.float32)
    coarse_to_fine = coarse_to_fine and not return_cost
    if coarse_to_fine:
        # Lipschitz bound of C over a block (reference pixels) and a float slack.
        lip = maps.lipschitz()
        used = torch.cat([ref_u[:, None], views_u], dim=1)
        L = lip[used].amax(dim=1)
        radius = T[:, :3, :3].abs().sum(dim=1).norm(dim=1)  # sqrt(sx^2 + sy^2 + sz^2)
        tol = (L * radius * (1 + 1e-5)).float()
        slack = (1e-3 + 1e-5 * 4 * L * torch.cat([scale.double(), torch.ones_like(L[:, None])], 1).amax(1)).float()

    # Proposals sorted by their number of foreground columns, so that a chunk pads little;
    # padding columns are background ones (never interior).
    count = torch.full((B,), HW, device=dev) if return_cost else fg.sum(dim=1)
    order = torch.argsort(count, descending=True, stable=True)
    col_order = _foreground_first(fg)
    # One host read for the chunking: the counts, and which view slots each proposal uses
    # (as bits; beyond 40 slots every slot counts as used).
    if V <= 40:
        packed = (count[order] * (1 << V) + ((views[order] >= 0).long() << torch.arange(V, device=dev)).sum(1)).tolist()
        count_sorted = [c >> V for c in packed]
    else:
        count_sorted = count[order].tolist()
        packed = [(1 << V) - 1] * B

    occ = torch.zeros(B, n, HW, dtype=torch.bool, device=dev)
    columns = torch.zeros(B, HW, dtype=torch.bool, device=dev)
    nonempty = torch.zeros(B, dtype=torch.bool, device=dev)
    cost = torch.empty(B, n, HW, device=dev) if return_cost else None
    per = _chunk_multiple(dev)
    buf = None
    start = 0
    while start < B:
        k = max(count_sorted[start], 1)
        # coarse-to-fine evaluates a fraction of the voxels: chunks of more proposals
        size = max(1, max_batch_voxels * (_C2F_CHUNK if coarse_to_fine else 1) // (k * n))
        size = min(B - start, size - size % per if size >= per else size)
        idx = order[start:start + size]
        start += size
        if count_sorted[start - size] == 0:
            continue  # empty references: nothing to carve
        bits = 0
        for c in packed[start - size:start]:
            bits |= c
        chunk = _Chunk(ext, views_u[idx], scale[idx], G[idx], torch.index_select(column_cost, 0, idx), n,
                       [bool(bits >> j & 1) for j in range(V)], interpolation)
        if coarse_to_fine:
            occ_c, nonempty[idx] = _carve_chunk_coarse_to_fine(chunk, fg[idx], tol[idx], slack[idx], imprint)
            occ[idx] = occ_c.view(-1, n, HW)
            columns[idx] = occ[idx].any(dim=1)
            continue
        cols = col_order[idx, :k]  # (b, k)
        if buf is None or buf.numel() < idx.shape[0] * k * n * 2:
            buf = torch.empty(idx.shape[0] * k * n * 2, device=dev)
        if depth_intervals and cost is None:
            lo, hi = _column_intervals(G64[idx], maps.box[views[idx].clamp(min=0)], views[idx] >= 0, cols, n,
                                       tuple(ext.shape[1:]))
            occ[idx], nonempty[idx], columns[idx] = _carve_chunk_intervals(chunk, cols, fg[idx], lo, hi, imprint, buf)
            continue
        acc = chunk.columns(cols, depth, buf)
        inside, nonempty[idx], col_occ = _label(acc, chunk.column_cost.gather(1, cols), imprint)
        columns[idx] = torch.zeros(idx.shape[0], HW, dtype=torch.bool, device=dev).scatter_(1, cols, col_occ)
        spread = cols[:, None, :].expand(-1, n, -1)
        occ[idx] = torch.zeros(idx.shape[0], n, HW, dtype=torch.bool, device=dev).scatter_(2, spread, inside)
        if cost is not None:
            cost[idx] = torch.empty(idx.shape[0], n, HW, device=dev).scatter_(2, spread, acc)

    occupancy = occ.view(B, n, n, n)
    return ProposalGrids(
        occupancy=occupancy,
        voxel_to_camera=T.float(),
        empty=~nonempty,
        reference_columns=fg.view(B, n, n),
        column_cost=column_cost.view(B, n, n),
        cost=None if cost is None else cost.view(B, n, n, n),
        columns=columns.view(B, n, n),
    )


def carve_proposals_loop(sdf: torch.Tensor, cameras: ScaledOrthographic, reference: torch.Tensor, views: torch.Tensor,
                         *, resolution: int = 60, imprint: bool = True,
                         reference_every_voxel: bool = False, interpolation: str = "bilinear") -> ProposalGrids:
    """Reference implementation of :func:`carve_proposals`: one proposal, one view at a time.

    The structure of a straightforward implementation: each proposal on its own, its
    silhouettes prepared for it, every voxel sampled (no column skipping, no depth
    intervals, no coarse-to-fine), unused slots skipped, and the same imprinting rule.
    Slow; for tests and benchmarks. Always returns the full cost. How much is redone per
    proposal depends on what is passed (the benchmark times each step of the ladder):

    * ``sdf`` **bool masks** ``(M, H, W)``: the distance maps of the proposal's silhouettes
      are computed for it (:func:`carvi_torch.sdf.signed_distance`), then extended and
      measured; nothing is shared between proposals (the reference implementation's structure).
    * float ``sdf`` maps: extended and measured per proposal.
    * :class:`CarveMaps`: taken as they are (prepared once per class).

    ``reference_every_voxel`` samples the reference map at every voxel like the other views
    (its projection does not move along depth, so the values equal the once-per-column
    samples bit for bit; only the work differs).

    Args and returns: as :func:`carve_proposals`.
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    prepared = isinstance(sdf, CarveMaps)
    from_masks = not prepared and isinstance(sdf, torch.Tensor) and sdf.dtype == torch.bool
    if from_masks and sdf.dim() != 3:
        raise ValueError(f"masks must be a (M, H, W) bool tensor, got {tuple(sdf.shape)}")
    maps, reference, views = _as_maps(sdf, cameras, reference, views, resolution) if prepared else \
        (None, *_check_indices(_check_sdf(sdf.float() if from_masks else sdf, cameras), reference, views,
                               resolution, sdf.device))
    dev = maps.device if prepared else sdf.device
    B, V = views.shape
    n = resolution
    depth = torch.arange(n, device=dev, dtype=torch.float32)
    h, w = _column_hw(torch.arange(n * n, device=dev)[None], n)
    grids = []
    for b in range(B):
        if prepared:
            one, ref_b, views_b = maps, reference[b:b + 1], views[b:b + 1]
        elif from_masks:
            used = torch.cat([reference[b:b + 1], views[b][views[b] >= 0]])
            mine = torch.where(views[b:b + 1] >= 0, torch.cumsum((views[b:b + 1] >= 0).long(), 1), -1)
            one, ref_b, views_b = _as_maps(signed_distance(sdf[used]), cameras.to(dev)[used],
                                           torch.zeros(1, dtype=torch.long, device=dev), mine, resolution)
        else:
            one, ref_b, views_b = _as_maps(sdf, cameras, reference[b:b + 1], views[b:b + 1], resolution)
        ext, ref_u, views_u, T, G, G_ref, scale = _prepare(one, ref_b, views_b, resolution)
        column_cost = _reference_columns(ext, ref_u, G_ref, n, n, interpolation)  # (1, HW)
        if reference_every_voxel:
            acc = _sample_columns(ext[ref_u][:, None], G_ref, _column_terms(G_ref, h, w), depth,
                                  mode=interpolation)  # (1, D, HW)
        else:
            acc = column_cost[:, None, :].expand(1, n, n * n).clone()  # (1, D, HW)
        for j in range(V):
            if int(views[b, j]) < 0:
                continue
            view_map = ext[views_u[:, j]][:, None] * scale[:, j, None, None, None]
            xy = _column_terms(G[:, j], h, w)
            acc = torch.maximum(acc, _sample_columns(view_map, G[:, j], xy, depth, mode=interpolation))
        occ, _, _ = _label(acc, column_cost, imprint)
        grids.append((occ, T.float(), column_cost, acc))
    if B == 0:
        return carve_proposals(signed_distance(sdf) if from_masks else sdf, cameras, reference, views,
                               resolution=resolution, return_cost=True, interpolation=interpolation)
    occ, T, column_cost, acc = (torch.cat(x) for x in zip(*grids))
    occupancy = occ.view(B, n, n, n)
    return ProposalGrids(
        occupancy=occupancy,
        voxel_to_camera=T,
        empty=~occupancy.flatten(1).any(dim=1),
        reference_columns=(column_cost < 0).view(B, n, n),
        column_cost=column_cost.view(B, n, n),
        cost=acc.view(B, n, n, n),
        columns=occupancy.any(dim=1),
    )


def imprinted_visual_hull(masks: torch.Tensor, cameras: ScaledOrthographic, reference: int = 0, resolution: int = 60,
                          imprint: bool = True) -> VoxelGrid:
    """Imprinted visual hull of the given silhouettes, in the reference camera frame.

    Carves exactly the given silhouettes: ``masks[reference]`` is the reference and
    every other mask a further view (the pipeline passes surrogates and mirrored
    copies here). The signed distance maps are computed here.

    Args:
        masks: ``(V, H, W)`` bool silhouettes on one canvas.
        cameras: ``ScaledOrthographic`` of length ``V``, in canvas pixels.
        reference: index of the reference silhouette.
        resolution: voxels per axis.
        imprint: fill the reference's foreground columns the hull misses.

    Returns:
        :class:`VoxelGrid` with ``occupancy (D, H, W)``, ``voxel_to_camera (4, 4)`` and
        the cost ``C (D, H, W)``.

    Example:
        >>> masks = torch.zeros(2, 32, 32, dtype=torch.bool); masks[:, 8:24, 10:22] = True
        >>> R = torch.stack([torch.eye(3), torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])])
        >>> cams = ScaledOrthographic(R, torch.ones(2), torch.tensor([[15.5, 15.5], [15.5, 15.5]]))
        >>> g = imprinted_visual_hull(masks, cams, resolution=24)   # a box 12 x 16 x 12 pixels
        >>> round(g.volume() / (12 * 16 * 12), 1)
        1.0
    """
    if not isinstance(masks, torch.Tensor) or masks.dim() != 3:
        raise ValueError(f"masks must be a (V, H, W) tensor, got {getattr(masks, 'shape', type(masks))}")
    V = masks.shape[0]
    if not isinstance(reference, int) or not 0 <= reference < V:
        raise ValueError(f"reference must be an int in [0, {V}), got {reference!r}")
    sdf = signed_distance(masks.bool())
    others = [i for i in range(V) if i != reference]
    dev = masks.device
    out = carve_proposals(sdf, cameras.to(dev), torch.tensor([reference], device=dev),
                          torch.tensor([others], dtype=torch.long, device=dev).view(1, V - 1), resolution=resolution,
                          imprint=imprint, return_cost=True)
    return out[0]
