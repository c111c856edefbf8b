"""The reference carving: one proposal, one view at a time (tests and benchmarks compare with it).

Example:
    >>> masks = torch.zeros(2, 32, 32, dtype=torch.bool); masks[:, 8:24, 10:22] = True
    >>> cams = ScaledOrthographic(torch.eye(3).expand(2, 3, 3), torch.ones(2), torch.full((2, 2), 16.0))
    >>> out = carve_proposals_loop(masks, cams, torch.tensor([0]), torch.tensor([[1]]), resolution=12)
    >>> out.occupancy.shape
    torch.Size([1, 12, 12, 12])
"""
from __future__ import annotations

import torch

from ..cameras import ScaledOrthographic
from ..sdf import signed_distance
from .geometry import CarveMaps, as_maps, check_indices, check_sdf, column_hw, column_terms
from .grids import ProposalGrids
from .torch_backend import (INTERPOLATIONS, empty_grids, label_columns, prepare_proposals, reference_columns,
                            sample_columns)

__all__ = ["carve_proposals_loop"]


def _proposal_maps(sdf: torch.Tensor, cameras: ScaledOrthographic, reference: torch.Tensor, views: torch.Tensor,
                   resolution: int, from_masks: bool) -> tuple[CarveMaps, torch.Tensor, torch.Tensor]:
    """One proposal's prepared maps and its reference ``(1,)`` and view ``(1, V)`` indices into them: with
    ``from_masks``, the distance maps of its own silhouettes alone, computed here; else the given maps."""
    if not from_masks:
        return as_maps(sdf, cameras, reference, views, resolution)
    dev = sdf.device
    used = torch.cat([reference, views[0][views[0] >= 0]])
    mine = torch.where(views >= 0, torch.cumsum((views >= 0).long(), 1), -1)
    return as_maps(signed_distance(sdf[used]), cameras.to(dev)[used], torch.zeros(1, dtype=torch.long, device=dev),
                   mine, resolution)


def carve_proposals_loop(sdf: torch.Tensor, cameras: ScaledOrthographic, reference: torch.Tensor, views: torch.Tensor,
                         *, resolution: int = 60, imprint: bool = True,
                         reference_every_voxel: bool = False, interpolation: str = "bilinear") -> ProposalGrids:
    """Reference implementation of :func:`carvi_torch.carve.carve_proposals`: one proposal, one view at a time.

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

    Args and returns: as :func:`carvi_torch.carve.carve_proposals`.
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    prepared = isinstance(sdf, CarveMaps)
    from_masks = not prepared and isinstance(sdf, torch.Tensor) and sdf.dtype == torch.bool
    if from_masks and sdf.dim() != 3:
        raise ValueError(f"masks must be a (M, H, W) bool tensor, got {tuple(sdf.shape)}")
    maps, reference, views = as_maps(sdf, cameras, reference, views, resolution) if prepared else \
        (None, *check_indices(check_sdf(sdf.float() if from_masks else sdf, cameras), reference, views,
                               resolution, sdf.device))
    dev = maps.device if prepared else sdf.device
    B, V = views.shape
    n = resolution
    depth = torch.arange(n, device=dev, dtype=torch.float32)
    h, w = column_hw(torch.arange(n * n, device=dev)[None], n)
    grids = []
    for b in range(B):
        one, ref_b, views_b = maps, reference[b:b + 1], views[b:b + 1]
        if not prepared:
            one, ref_b, views_b = _proposal_maps(sdf, cameras, ref_b, views_b, resolution, from_masks)
        ext, ref_u, views_u, T, G, G_ref, scale = prepare_proposals(one, ref_b, views_b, resolution)
        column_cost = reference_columns(ext, ref_u, G_ref, n, n, interpolation)  # (1, HW)
        if reference_every_voxel:
            acc = sample_columns(ext[ref_u][:, None], G_ref, column_terms(G_ref, h, w), depth,
                                  mode=interpolation)  # (1, D, HW)
        else:
            acc = column_cost[:, None, :].expand(1, n, n * n).clone()  # (1, D, HW)
        for j in range(V):
            if int(views[b, j]) < 0:
                continue
            view_map = ext[views_u[:, j]][:, None] * scale[:, j, None, None, None]
            xy = column_terms(G[:, j], h, w)
            acc = torch.maximum(acc, sample_columns(view_map, G[:, j], xy, depth, mode=interpolation))
        occ, _, _ = label_columns(acc, column_cost, imprint)
        grids.append((occ, T.float(), column_cost, acc))
    if B == 0:
        return empty_grids(n, dev, return_cost=True)
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
