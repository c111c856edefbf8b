"""Imprinted visual hulls on voxel grids, batched over proposals (the carving stage).

A *proposal* is a reference silhouette ``r`` plus further views ``m`` (surrogate
silhouettes, their mirrored copies, the mirrored reference...). Its shape is carved on
a voxel grid in the reference camera frame: voxel ``v`` gets the cone cost
``C(v) = max_m C_m(v)`` over the reference and the views, is *interior* iff
``C(v) < 0``, and, with imprinting, every foreground column of the reference that has
no interior voxel gets its voxel of minimal ``C`` (Carreira et al., "Lifting Object
Detection Datasets into 3D", section "Imprinted visual hull reconstruction").

Modules, in the order data flows through them:

* :mod:`~carvi_torch.carve.geometry`: silhouettes prepared once per class
  (:class:`CarveMaps`), grid bounds and the voxel -> sampling maps of proposals;
* :mod:`~carvi_torch.carve.torch_backend`: the batched ``grid_sample`` carving (any device);
* :mod:`~carvi_torch.carve.native`: the compiled CPU kernel that samples, takes the maximum
  and labels in one pass, with early exit (same labels voxel for voxel);
* :mod:`~carvi_torch.carve.reference`: the one-proposal-at-a-time loop the tests compare with;
* :mod:`~carvi_torch.carve.dispatch`: :func:`carve_proposals`, which picks the backend, and
  :func:`imprinted_visual_hull`;
* :mod:`~carvi_torch.carve.grids`: the results, :class:`VoxelGrid` and :class:`ProposalGrids`;
* :mod:`~carvi_torch.carve.chunks`: how many references the pipeline carves together;
* :mod:`~carvi_torch.carve.puffball`: the last fallback, a shape from one silhouette, on the
  carving's grids.

Example:
    >>> import torch
    >>> from carvi_torch.cameras import ScaledOrthographic
    >>> masks = torch.zeros(1, 32, 32, dtype=torch.bool); masks[0, 8:24, 10:22] = True
    >>> cams = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.full((1, 2), 16.0))
    >>> grid = imprinted_visual_hull(masks, cams, resolution=20)
    >>> grid.occupancy.shape
    torch.Size([20, 20, 20])
"""
from .chunks import chunk_objects
from .dispatch import BACKENDS, Backend, carve_proposals, imprinted_visual_hull, resolve_backend
from .geometry import BIG, PAD, CarveMaps, extend_maps, mask_geometry, prepare_maps, proposal_geometry
from .grids import ProposalGrids, VoxelGrid
from .reference import carve_proposals_loop
from .torch_backend import INTERPOLATIONS, Interpolation, default_batch_voxels

__all__ = ["imprinted_visual_hull", "carve_proposals", "carve_proposals_loop", "resolve_backend", "prepare_maps",
           "CarveMaps", "VoxelGrid", "ProposalGrids", "BACKENDS", "Backend", "INTERPOLATIONS", "Interpolation",
           "default_batch_voxels", "chunk_objects", "extend_maps", "mask_geometry", "proposal_geometry", "PAD", "BIG"]
