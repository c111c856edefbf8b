"""The torch carving backend: batched ``grid_sample`` over proposals, maximum over views, labels.

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

Example:
    >>> foreground_first(torch.tensor([[False, True, False, True]]))
    tensor([[1, 3, 0, 2]])
"""
from __future__ import annotations

from typing import Literal, get_args

import torch
import torch.nn.functional as F

from .geometry import CarveMaps, column_hw, column_terms, proposal_geometry
from .grids import ProposalGrids

__all__ = ["Interpolation", "INTERPOLATIONS", "carve_torch", "default_batch_voxels", "grid_sample_maps",
           "sample_columns", "sample_planes", "label_columns", "foreground_first", "prepare_proposals",
           "reference_columns", "kernel_inputs", "chunk_multiple", "empty_grids", "plan_chunks"]

#: Default ``max_batch_voxels`` per device type (CPU: per intra-op thread, see :func:`default_batch_voxels`).
_DEFAULT_BATCH_VOXELS = {"cpu": 1 << 19, "cuda": 1 << 25}


#: Bound on the CPU default: chunks grow with the threads up to it (measured with 1 and 2 threads only).
_CPU_BATCH_VOXELS_MAX = 1 << 21


#: The maps' interpolations :func:`carve_proposals` offers (``interpolation``).
Interpolation = Literal["bilinear", "nearest"]
INTERPOLATIONS: tuple[str, ...] = get_args(Interpolation)


def grid_sample_maps(maps: torch.Tensor, grid: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """The one call into ``grid_sample``: ``mode`` (:data:`INTERPOLATIONS`), ``padding_mode="border"``,
    ``align_corners=True``."""
    return F.grid_sample(maps, grid, mode=mode, padding_mode="border", align_corners=True)


def sample_columns(maps: torch.Tensor, G: torch.Tensor, xy: torch.Tensor, depth: torch.Tensor,
                    out: torch.Tensor | None = None, mode: str = "bilinear") -> torch.Tensor:
    """Samples of ``maps`` (interpolated as ``mode``) at the voxels of some columns.

    The coordinates of voxel ``(d, column)`` are ``G[:, :, 0] d + xy[column]``
    (:func:`sample_planes`).

    Args:
        maps: ``(N, 1, Hp, Wp)`` float32 extended maps (already scaled).
        G: ``(N, 2, 4)`` float32 index -> sampling maps.
        xy: ``(N, 2, K)`` column terms (:func:`column_terms`).
        depth: ``(D,)`` float32 depth indices.
        out: optional float32 buffer of at least ``N * 2 * D * K`` elements for the coordinates.

    Returns:
        ``(N, D, K)`` float32 samples.
    """
    return sample_planes(maps, G[:, :, 0, None] * depth, xy, out, mode)


def sample_planes(maps: torch.Tensor, dz: torch.Tensor, xy: torch.Tensor, out: torch.Tensor | None = None,
                   mode: str = "bilinear") -> torch.Tensor:
    """Samples of ``maps`` at the coordinates ``dz[:, :, d] + xy[:, :, k]`` (depth term plus column term).

    The coordinates are written as two planes ``(N, 2, D, K)`` (one vectorised broadcast
    add) and handed to ``grid_sample`` as the view ``(N, D, K, 2)`` (it takes strided grids).

    Args:
        maps: ``(N, 1, Hp, Wp)`` float32 extended maps (already scaled).
        dz: ``(N, 2, D)`` float32 depth terms ``G[:, :, 0] d``.
        xy: ``(N, 2, K)`` float32 column terms (:func:`column_terms`).
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
    return grid_sample_maps(maps, planes.permute(0, 2, 3, 1), mode)[:, 0]


def label_columns(cost: torch.Tensor, column_cost: torch.Tensor, imprint: bool
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


def foreground_first(fg: torch.Tensor) -> torch.Tensor:
    """Stable partition of columns: ``(B, HW)`` bool -> ``(B, HW)`` long permutation of each row,
    its ``True`` columns first, each part in ascending order (``argsort(~fg, stable=True)``,
    computed by counting instead of sorting).

    Example:
        >>> foreground_first(torch.tensor([[False, True, False, True]]))
        tensor([[1, 3, 0, 2]])
    """
    B, HW = fg.shape
    before = fg.cumsum(1)  # foreground columns up to and including each one
    j = torch.arange(HW, device=fg.device)
    pos = torch.where(fg, before - 1, before[:, -1:] + j - before)
    return torch.empty_like(pos).scatter_(1, pos, j.expand(B, -1))


def prepare_proposals(maps: CarveMaps, reference: torch.Tensor, views: torch.Tensor, resolution: int):
    """Maps and geometry shared by the batched and the loop implementations.

    Returns ``ext`` (the extended maps), ``ref_m (B,)`` and ``views_m (B, V)`` (rows of ``ext``;
    unused slots: the unused-slot map), and ``T, G, G_ref, scale`` of :func:`proposal_geometry`
    (``G``, ``G_ref``, ``scale`` in float32).
    """
    ref_m = maps.entry_map[reference]
    views_m = torch.where(views >= 0, maps.entry_map[views.clamp(min=0)], maps.unused)
    T, G, G_ref, scale = proposal_geometry(maps.box, maps.nonempty, maps.radius, maps.cameras, reference, views,
                                           resolution, tuple(maps.ext.shape[1:]))
    return maps.ext, ref_m, views_m, T, G.float(), G_ref.float(), scale.float()


def reference_columns(ext, ref_u, G_ref, H_grid, W_grid, mode="bilinear"):
    """``(B, H_grid * W_grid)`` reference cost at every column centre."""
    B = ref_u.shape[0]
    h, w = column_hw(torch.arange(H_grid * W_grid, device=ext.device).expand(B, -1), W_grid)
    zero = torch.zeros(1, device=ext.device, dtype=torch.float32)
    return sample_columns(torch.index_select(ext, 0, ref_u)[:, None], G_ref, column_terms(G_ref, h, w), zero,
                           mode=mode)[:, 0]


def kernel_inputs(maps: CarveMaps, reference: torch.Tensor, views: torch.Tensor, n: int):
    """What :func:`carvi_torch.carve.native.carve_labels` takes for these proposals (bilinear maps).

    Returns:
        ``ext`` (the extended maps), ``slots (B, V)`` (row of ``ext`` per view slot, ``-1`` unused),
        ``scale (B, V)`` and ``G (B, V, 2, 4)`` float32, ``column_cost (B, n * n)``, and ``T (B, 4, 4)``
        the voxel-to-camera maps (float64).
    """
    ext, ref_u, views_u, T, G, G_ref, scale = prepare_proposals(maps, reference, views, n)
    column_cost = reference_columns(ext, ref_u, G_ref, n, n)
    return ext, torch.where(views >= 0, views_u, -1), scale, G, column_cost, T


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
        h, w = column_hw(cols, self.n)
        # the depth and column terms of every used slot at once (a few operations per chunk, not per slot)
        used = [j for j, maps in enumerate(self.maps) if maps is not None]
        G = self.G if len(used) == len(self.maps) else self.G[:, used]  # (N, U, 2, 4)
        dz = G[..., 0, None] * depth  # (N, U, 2, D)
        xy = column_terms(G, h, w)  # (N, U, 2, K)
        acc = None
        for u, j in enumerate(used):
            sample = sample_planes(self.maps[j], dz[:, u], xy[:, u], out=buf, mode=self.mode)
            acc = sample if acc is None else torch.maximum(acc, sample, out=acc)
        col = self.column_cost.gather(1, cols)[:, None, :]
        return col.expand(-1, depth.shape[0], -1).contiguous() if acc is None else torch.maximum(acc, col, out=acc)


def default_batch_voxels(device: torch.device | str) -> int:
    """Default ``max_batch_voxels`` of :func:`carve_proposals` on ``device``.

    CUDA: ``2**25``. CPU: ``2**19`` voxels per intra-op thread (``torch.get_num_threads()``),
    at most ``2**21``: a chunk's coordinates and samples then stay near the cores' caches,
    while the per-chunk work stays amortised. Measured on the pipeline's proposals
    (``git show bcd899f^:docs/benchmarks/README.md``, the records before docs/benchmarks.md): with 1
    thread ``2**19`` was 9% faster than ``2**20`` (bilinear and nearest), with 2
    threads ``2**20`` 7% faster than ``2**19`` (bilinear).

    Example:
        >>> default_batch_voxels("cuda")
        33554432
    """
    dev = torch.device(device)
    if dev.type != "cpu":
        return _DEFAULT_BATCH_VOXELS.get(dev.type, _DEFAULT_BATCH_VOXELS["cuda"])
    return min(_DEFAULT_BATCH_VOXELS["cpu"] * max(1, torch.get_num_threads()), _CPU_BATCH_VOXELS_MAX)


def chunk_multiple(device: torch.device) -> int:
    """Chunks hold a multiple of this many proposals where the budget allows: the intra-op
    thread count on the CPU, 1 elsewhere.

    The CPU ``grid_sample`` shares a call's work among the threads by batch index, whole
    batch entries each, so a chunk of 7 proposals on 2 threads keeps one thread idle for a
    proposal's time (13% slower per proposal than 8 in a scratch measurement). With this
    rounding (and the per-chunk coordinate terms) the carving was 1.14x faster bilinear and
    1.24x nearest at 2 threads (``git show bcd899f^:docs/benchmarks/README.md``, "Balanced threads"); splitting each
    proposal's depths into one batch entry per thread instead was slower (its maps are copied
    once per thread).
    """
    return max(1, torch.get_num_threads()) if device.type == "cpu" else 1


def empty_grids(n: int, device: torch.device, return_cost: bool) -> ProposalGrids:
    """Grids of no proposal at resolution ``n``."""
    z = torch.zeros(0, n, n, n, dtype=torch.bool, device=device)
    return ProposalGrids(z, torch.zeros(0, 4, 4, device=device), torch.zeros(0, dtype=torch.bool, device=device),
                         z[:, 0], torch.zeros(0, n, n, device=device), z.float() if return_cost else None, z[:, 0])


def plan_chunks(count: torch.Tensor, views: torch.Tensor, max_batch_voxels: int, n: int, per: int):
    """The chunks of a carving: ``(idx, k, slots)`` per chunk of proposals.

    Proposals are sorted by their number of foreground columns ``count (B,)``, so that a chunk
    pads little (padding columns are background ones, never interior); a chunk holds at most
    ``max_batch_voxels`` voxels of ``k`` columns each (a multiple of ``per`` proposals where the
    budget allows). ``slots``: host bools, whether any proposal of the chunk uses each view slot.
    One host read: the counts and the used slots (as bits; beyond 40 slots every slot counts).
    """
    B, V = views.shape
    order = torch.argsort(count, descending=True, stable=True)
    if V <= 40:
        packed = (count[order] * (1 << V) + ((views[order] >= 0).long() << torch.arange(V, device=views.device))
                  .sum(1)).tolist()
        count_sorted = [c >> V for c in packed]
    else:
        count_sorted = count[order].tolist()
        packed = [(1 << V) - 1] * B
    start = 0
    while start < B:
        k = max(count_sorted[start], 1)
        size = max(1, max_batch_voxels // (k * n))
        size = min(B - start, size - size % per if size >= per else size)
        first, start = start, start + size
        if count_sorted[first] == 0:
            continue  # empty references: nothing to carve
        bits = 0
        for c in packed[first:start]:
            bits |= c
        yield order[first:start], k, [bool(bits >> j & 1) for j in range(V)]


def carve_torch(maps: CarveMaps, reference: torch.Tensor, views: torch.Tensor, resolution: int, *,
                imprint: bool = True, max_batch_voxels: int | None = None, return_cost: bool = False,
                interpolation: str = "bilinear") -> ProposalGrids:
    """The torch backend of :func:`carvi_torch.carve.carve_proposals` on checked inputs.

    Proposals are carved in chunks of at most ``max_batch_voxels`` voxels of their foreground
    columns (:func:`plan_chunks`; one ``grid_sample`` call per chunk and used view slot), the views
    sampled only along the reference's foreground columns unless ``return_cost`` asks for
    every voxel.

    Args:
        maps: the prepared silhouettes; reference: ``(B,)`` long entries; views: ``(B, V)``
            long entries, ``-1`` unused (checked by :func:`~carvi_torch.carve.geometry.as_maps`).
        resolution, imprint, max_batch_voxels, return_cost, interpolation: as
            :func:`carvi_torch.carve.carve_proposals`.

    Returns:
        :class:`~carvi_torch.carve.grids.ProposalGrids`.
    """
    dev = maps.device
    if max_batch_voxels is None:
        max_batch_voxels = default_batch_voxels(dev)
    if not isinstance(max_batch_voxels, int) or max_batch_voxels < 1:
        raise ValueError(f"max_batch_voxels must be a positive int, got {max_batch_voxels!r}")
    B, n = views.shape[0], resolution
    HW = n * n
    if B == 0:
        return empty_grids(n, dev, return_cost)
    ext, ref_u, views_u, T, G, G_ref, scale = prepare_proposals(maps, reference, views, n)
    column_cost = reference_columns(ext, ref_u, G_ref, n, n, interpolation)  # (B, HW)
    fg = column_cost < 0
    depth = torch.arange(n, device=dev, dtype=torch.float32)
    count = torch.full((B,), HW, device=dev) if return_cost else fg.sum(dim=1)
    col_order = foreground_first(fg)
    occ = torch.zeros(B, n, HW, dtype=torch.bool, device=dev)
    columns = torch.zeros(B, HW, dtype=torch.bool, device=dev)
    nonempty = torch.zeros(B, dtype=torch.bool, device=dev)
    cost = torch.empty(B, n, HW, device=dev) if return_cost else None
    buf = None
    for idx, k, slots in plan_chunks(count, views, max_batch_voxels, n, chunk_multiple(dev)):
        chunk = _Chunk(ext, views_u[idx], scale[idx], G[idx], torch.index_select(column_cost, 0, idx), n, slots,
                       interpolation)
        cols = col_order[idx, :k]  # (b, k)
        if buf is None or buf.numel() < idx.shape[0] * k * n * 2:
            buf = torch.empty(idx.shape[0] * k * n * 2, device=dev)
        acc = chunk.columns(cols, depth, buf)
        inside, nonempty[idx], col_occ = label_columns(acc, chunk.column_cost.gather(1, cols), imprint)
        columns[idx] = torch.zeros(idx.shape[0], HW, dtype=torch.bool, device=dev).scatter_(1, cols, col_occ)
        spread = cols[:, None, :].expand(-1, n, -1)
        occ[idx] = torch.zeros(idx.shape[0], n, HW, dtype=torch.bool, device=dev).scatter_(2, spread, inside)
        if cost is not None:
            cost[idx] = torch.empty(idx.shape[0], n, HW, device=dev).scatter_(2, spread, acc)
    return ProposalGrids(occupancy=occ.view(B, n, n, n), voxel_to_camera=T.float(), empty=~nonempty,
                         reference_columns=fg.view(B, n, n), column_cost=column_cost.view(B, n, n),
                         cost=None if cost is None else cost.view(B, n, n, n), columns=columns.view(B, n, n))
