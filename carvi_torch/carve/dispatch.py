"""One dispatch for the carving: which backend carves a call, and the public carving functions.

Example:
    >>> resolve_backend("torch", "cpu")
    {'backend': 'torch', 'variant': None, 'reason': None}
"""
from __future__ import annotations

from typing import Literal, get_args

import torch

from ..cameras import ScaledOrthographic
from ..sdf import signed_distance
from . import native
from .geometry import as_maps
from .grids import ProposalGrids, VoxelGrid
from .torch_backend import INTERPOLATIONS, carve_torch, kernel_inputs

__all__ = ["BACKENDS", "Backend", "carve_proposals", "resolve_backend", "imprinted_visual_hull"]

#: Who computes the labels: ``"auto"`` (the native kernel on the CPU where it applies and is
#: available, else torch), ``"torch"`` (batched ``grid_sample``), ``"fused"`` (the native kernel;
#: an error where it cannot run).
Backend = Literal["auto", "torch", "fused"]
BACKENDS: tuple[str, ...] = get_args(Backend)


def _use_native(backend: str, device: torch.device, interpolation: str, return_cost: bool, V: int) -> bool:
    """Whether :func:`carve_proposals` runs the native kernel (``backend="fused"`` where it cannot: an error)."""
    if backend == "torch":
        return False
    why = None
    if device.type != "cpu":
        why = f"it runs on the CPU, not {device.type}"
    elif interpolation != "bilinear":
        why = f"it reads the maps bilinearly, not {interpolation!r}"
    elif return_cost:
        why = "it computes labels only (no return_cost)"
    elif V > native.MAX_VIEWS:
        why = f"it takes at most {native.MAX_VIEWS} view slots, not {V}"
    elif not native.available():
        why = f"it is not available here: {native.unavailable_reason()}"
    if why is not None and backend == "fused":
        raise ValueError(f"backend='fused' cannot carve this call: {why}")
    return why is None


def _check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def resolve_backend(backend: str, device: torch.device | str, interpolation: str = "bilinear") -> dict:
    """What :func:`carve_proposals` runs for a labels-only call (the pipeline's) with these settings.

    Returns:
        ``{"backend": "fused" | "torch", "variant": "fma" | "plain" | None, "reason": str | None}``:
        the native kernel's sample arithmetic when it runs, and why it does not when ``backend`` is
        ``"auto"`` on the CPU (no compiler, say). Raises ``ValueError`` as :func:`carve_proposals`
        does for ``backend="fused"`` where the kernel cannot run.

    Example:
        >>> resolve_backend("torch", "cpu")
        {'backend': 'torch', 'variant': None, 'reason': None}
    """
    _check_backend(backend)
    dev = torch.device(device)
    if _use_native(backend, dev, interpolation, False, 0):
        return {"backend": "fused", "variant": native.variant(), "reason": None}
    reason = None
    if backend == "auto" and dev.type == "cpu" and interpolation == "bilinear":
        reason = native.unavailable_reason()
    return {"backend": "torch", "variant": None, "reason": reason}


def carve_proposals(sdf: torch.Tensor, cameras: ScaledOrthographic, reference: torch.Tensor, views: torch.Tensor, *,
                    resolution: int = 60, imprint: bool = True, max_batch_voxels: int | None = None,
                    return_cost: bool = False, interpolation: str = "bilinear",
                    backend: str = "auto") -> ProposalGrids:
    """Carve the imprinted visual hulls of ``B`` proposals in one batched computation.

    Proposal ``b`` carves reference map ``reference[b]`` with the maps ``views[b]``
    (``-1`` = unused slot) on a ``resolution^3`` grid in the reference camera frame
    (:mod:`carvi_torch.carve.geometry` for frames, bounds and units). The labels are those
    of evaluating every voxel (:func:`carvi_torch.carve.reference.carve_proposals_loop`),
    voxel for voxel, whichever backend computes them.

    Args:
        sdf: ``(M, H, W)`` float signed distance maps (:func:`carvi_torch.sdf.signed_distance`),
            or :class:`~carvi_torch.carve.geometry.CarveMaps` prepared once
            (:func:`~carvi_torch.carve.geometry.prepare_maps`; then ``cameras`` is ``None`` and
            indices are its entries).
        cameras: ``ScaledOrthographic`` of length ``M``, in the maps' pixels.
        reference: ``(B,)`` long indices into ``sdf``.
        views: ``(B, V)`` long indices into ``sdf``, ``-1`` for an unused slot.
        resolution: voxels per axis (4 to 2048).
        imprint: fill every foreground column of the reference that has no interior
            voxel at its voxel of minimal cost.
        max_batch_voxels: torch backend: bound on the voxels of the foreground columns of a
            chunk; default :func:`~carvi_torch.carve.torch_backend.default_batch_voxels`.
        return_cost: also return the full cost ``C (B, D, H, W)`` (torch backend, every voxel).
        interpolation: how the distance maps are read at a voxel's projection
            (:data:`~carvi_torch.carve.torch_backend.INTERPOLATIONS`): ``"bilinear"`` (the
            default, the reference implementation's) or ``"nearest"`` (the pixel the voxel
            falls in: a cheaper sample, an approximation of the bilinear labels).
        backend: :data:`Backend`. ``"torch"``: the batched ``grid_sample`` carving of
            :mod:`carvi_torch.carve.torch_backend`. ``"fused"``: the native CPU kernel of
            :mod:`carvi_torch.carve.native`, which samples, takes the maximum and labels in one
            pass and stops reading a voxel's views once its labels are decided (CPU, bilinear,
            labels only). ``"auto"`` (default): ``"fused"`` where it applies and is available.

    Returns:
        :class:`~carvi_torch.carve.grids.ProposalGrids`.

    Example:
        >>> masks = torch.zeros(2, 32, 32, dtype=torch.bool); masks[:, 8:24, 10:22] = True
        >>> cams = ScaledOrthographic(torch.eye(3).expand(2, 3, 3), torch.ones(2), torch.full((2, 2), 16.0))
        >>> out = carve_proposals(signed_distance(masks), cams, torch.tensor([0]), torch.tensor([[1]]), resolution=16)
        >>> out.occupancy.shape, bool(out.empty[0])
        (torch.Size([1, 16, 16, 16]), False)
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    _check_backend(backend)
    if max_batch_voxels is not None and (not isinstance(max_batch_voxels, int) or max_batch_voxels < 1):
        raise ValueError(f"max_batch_voxels must be a positive int, got {max_batch_voxels!r}")
    maps, reference, views = as_maps(sdf, cameras, reference, views, resolution)
    B, n = views.shape[0], resolution
    if B and _use_native(backend, maps.device, interpolation, return_cost, views.shape[1]):
        ext, slots, scale, G, column_cost, T = kernel_inputs(maps, reference, views, n)
        occ, columns, nonempty, _ = native.carve_labels(ext, slots, scale, G, column_cost, n, imprint)
        return ProposalGrids(occupancy=occ.view(B, n, n, n), voxel_to_camera=T.float(), empty=~nonempty,
                             reference_columns=(column_cost < 0).view(B, n, n), column_cost=column_cost.view(B, n, n),
                             cost=None, columns=columns.view(B, n, n))
    return carve_torch(maps, reference, views, n, imprint=imprint, max_batch_voxels=max_batch_voxels,
                       return_cost=return_cost, interpolation=interpolation)


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
