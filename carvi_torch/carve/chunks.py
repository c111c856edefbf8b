"""How many references the pipeline carves and selects together (one chunk of a class).

Example:
    >>> import torch
    >>> chunk_objects(proposals=20, resolution=60, device=torch.device("cpu"))
    4
"""
from __future__ import annotations

import torch

__all__ = ["chunk_objects", "CPU_CHUNK_OBJECTS", "CUDA_CHUNK_FRACTION", "CUDA_BYTES_PER_VOXEL"]

#: Objects per pipeline chunk on the CPU: small enough that a chunk's grids stay in the
#: caches between carving and selection, large enough that per-chunk overheads vanish.
CPU_CHUNK_OBJECTS = 4
#: Fraction of the free CUDA memory a pipeline chunk may take (grids, costs, projections).
CUDA_CHUNK_FRACTION = 0.25
#: Bytes per voxel of one proposal held during a chunk on CUDA (occupancy, boundary, sampling temporaries).
CUDA_BYTES_PER_VOXEL = 16


def chunk_objects(proposals: int, resolution: int, device: torch.device) -> int:
    """References carved and selected together, each with ``proposals`` grids of ``resolution^3`` voxels: a few
    on the CPU (the carving chunks further for its caches); on CUDA as many as a quarter of the free device
    memory holds (few, large kernels)."""
    per_object = max(1, proposals) * resolution ** 3
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        return max(1, int(free * CUDA_CHUNK_FRACTION) // (per_object * CUDA_BYTES_PER_VOXEL))
    return CPU_CHUNK_OBJECTS
