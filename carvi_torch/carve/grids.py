"""The carving's results: one voxel grid in a camera frame, and a batch of proposal grids.

Example:
    >>> g = VoxelGrid(torch.ones(2, 2, 2, dtype=torch.bool), torch.diag(torch.tensor([2.0, 1.0, 1.0, 1.0])))
    >>> g.volume()
    16.0
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["VoxelGrid", "ProposalGrids"]


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
        from ..mesh import occupancy_to_mesh  # the public VoxelGrid.to_mesh(); the one import of a later stage

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
