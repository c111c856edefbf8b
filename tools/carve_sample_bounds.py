"""How many samples an exact coarse-to-fine carving along depth would still need (a bound, not a carving).

For each proposal of the first ``--objects`` references (the pipeline's own proposals, same
seed as a run), every view is sampled densely on the reference's foreground columns, as the
batched carving samples them. Then a scheme is *simulated* on those exact values. Every view
is sampled at the depths ``0, b, 2b, ...`` and at the last one. Between two sampled depths
``r0 < r1``, a view's cost at any voxel lies within ``(C(r0) + C(r1)) / 2 +- (r1 - r0) t / 2``,
where ``t`` bounds its change per depth step (:func:`step_bounds`). So:

* a block is exterior when some view's lower bound is positive, and interior when every view's
  upper bound is negative (in a foreground column);
* in the other blocks only the views whose bounds straddle zero need their samples;
* a column with no sampled interior voxel and no interior block may have to be imprinted, and
  needs its whole cost: every depth of every view.

Two bounds are compared. ``per view, directional``: each view its own ``t``, from the map's
largest pixel differences along x and along y, weighted by how far a depth step moves the
view's projection along each axis. ``single``: one ``t`` per proposal, the largest over its views
of the isotropic form (the map's gradient bound times the step's length, the form
``coarse_to_fine`` uses), and every view sampled in an undecided block. The result is the fraction
of the dense carving's samples each scheme needs: what it could save at best, before paying for
finding and gathering the undecided blocks. The simulation also counts the blocks whose
decision the dense samples contradict (``violations``: must be 0, the bounds are sound).

``--time`` also runs a prototype of the scheme (per-view bounds, ``--time-block`` depths per
block; kept here, not in the package) against the batched carving on the pipeline's proposals
of ``--time-objects`` references. The prototype finds the undecided blocks with ``nonzero``,
pads them per proposal, gathers their coordinates, samples them, and knocks out the voxels a
straddling view sees outside; candidate columns are carved whole. Its labels are compared with
the batched carving's voxel for voxel, and both are timed, with their ``grid_sample`` time alone.

    python tools/carve_sample_bounds.py --data outputs/bench/data/car1000_s0/annotations.json [--time]
"""
from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from bench_carve import GridSampleClock  # noqa: E402
from bench_changes import class_proposals, pipeline_call_bounds  # noqa: E402
from carvi_torch import carve as C  # noqa: E402
from carvi_torch.io.outputs import write_json  # noqa: E402

#: Float slack of every per-step bound: relative, and absolute (reference pixels per step).
_REL, _ABS = 1e-5, 1e-3

# --------------------------------------------------------------------------- bounds


def rep_depths(n: int, block: int) -> list[int]:
    """The sampled depths ``0, block, 2 block, ...`` and ``n - 1``.

    Example:
        >>> rep_depths(10, 4)
        [0, 4, 8, 9]
    """
    reps = list(range(0, n, block))
    return reps if reps[-1] == n - 1 else reps + [n - 1]


def step_bounds(G: torch.Tensor, scale: torch.Tensor, maps: torch.Tensor, lx: torch.Tensor, ly: torch.Tensor,
                map_size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """How much each view's cost can change from one depth to the next along a column.

    Args:
        G: ``(B, V, 2, 4)`` index -> ``grid_sample`` coordinate maps (``align_corners=True``).
        scale: ``(B, V)`` the factor each view's map is multiplied by (``s_r / s_m``).
        maps: ``(B, V)`` long, the map (row of ``ext``) of each view slot.
        lx, ly: ``(M,)`` float64 largest pixel differences of the maps (``CarveMaps.pixel_differences``).
        map_size: ``(Hp, Wp)`` of the maps.

    Returns:
        ``directional, isotropic``: ``(B, V)`` float64, ``scale (lx |dx| + ly |dy|)`` and
        ``scale sqrt(lx^2 + ly^2) |(dx, dy)|`` for the view's move ``(dx, dy)`` in pixels per depth
        step, each times ``1 + 1e-5`` plus ``1e-3`` (float slack).
    """
    Hp, Wp = map_size
    dx = G[:, :, 0, 0].double().abs() * (Wp - 1) / 2
    dy = G[:, :, 1, 0].double().abs() * (Hp - 1) / 2
    s, mx, my = scale.double(), lx[maps], ly[maps]
    directional = s * (mx * dx + my * dy)
    isotropic = s * torch.sqrt(mx ** 2 + my ** 2) * torch.sqrt(dx ** 2 + dy ** 2)
    return directional * (1 + _REL) + _ABS, isotropic * (1 + _REL) + _ABS


# --------------------------------------------------------------------------- the simulation


def view_samples(maps: C.CarveMaps, ref: torch.Tensor, views: torch.Tensor, n: int):
    """Yields, per proposal with a foreground column and a used view: ``S (U, n, K)`` float64 costs
    of its ``U`` used views at every depth of its ``K`` foreground columns (the batched carving's
    samples), and their per-step bounds ``t (U,)`` (directional) and ``t_iso (U,)`` (isotropic)."""
    ext, ref_u, views_u, _, G, G_ref, scale = C._prepare(maps, ref, views, n)
    column_cost = C._reference_columns(ext, ref_u, G_ref, n, n)
    t_dir, t_iso = step_bounds(G, scale, views_u, *maps.pixel_differences(), tuple(ext.shape[1:]))
    depth = torch.arange(n, dtype=torch.float32)
    for b in range(len(ref)):
        cols = (column_cost[b] < 0).nonzero()[:, 0][None]
        used = (views[b] >= 0).nonzero()[:, 0].tolist()
        if cols.shape[1] == 0 or not used:
            continue
        h, w = C._column_hw(cols, n)
        S = []
        for j in used:
            m = ext[views_u[b:b + 1, j]][:, None] * scale[b, j]
            xy = C._column_terms(G[b:b + 1, j], h, w)
            S.append(C._sample_planes(m, G[b:b + 1, j, :, 0, None] * depth, xy)[0].double())
        yield torch.stack(S), t_dir[b, used], t_iso[b, used]


def simulate(S: torch.Tensor, t: torch.Tensor, block: int, per_view: bool) -> dict:
    """Samples the block scheme needs on one proposal (see the module docstring).

    Args:
        S: ``(U, n, K)`` float64 exact costs of the used views on the foreground columns.
        t: ``(U,)`` float64 per-step bound of each view.
        block: depths per block; per_view: sample only the straddling views of an undecided block.

    Returns:
        counts: ``samples`` (the scheme's), ``dense`` (``U n K``), ``columns``, ``candidates``
        (columns sampled whole), ``imprinted`` (columns with no interior voxel), ``blocks``,
        ``undecided_blocks`` (outside candidate columns) and ``violations``: blocks declared
        exterior or interior, or views skipped as surely negative, that the exact costs contradict.
    """
    U, n, K = S.shape
    reps = rep_depths(n, block)
    rt = torch.tensor(reps)
    L = (rt[1:] - rt[:-1]).double()[None, :, None]  # (1, R-1, 1) depth steps per block
    Sr = S[:, rt]  # (U, R, K)
    mid = (Sr[:, 1:] + Sr[:, :-1]) / 2
    half = t[:, None, None] * L / 2
    exterior = ((mid - half) > 0).any(0)  # (R-1, K)
    interior = ((mid + half) < 0).all(0)
    undecided = ~exterior & ~interior
    # a column with an interior block has interior representatives too: the second term adds nothing
    candidate = ~((Sr.amax(0) < 0).any(0) | interior.any(0))  # (K,) may need imprinting: sampled whole
    skipped = (mid + half < 0) & undecided[None] & ~candidate[None, None]  # (U, R-1, K) surely negative views
    inner = L - 1
    if per_view:
        fine = float(((undecided[None] & ~candidate[None, None] & ~skipped).double() * inner).sum())
    else:
        fine = float(((undecided & ~candidate[None]).double() * inner[0]).sum()) * U
    samples = U * len(reps) * K + int(candidate.sum()) * U * (n - len(reps)) + fine
    final = S.amax(0)  # (n, K): the sign of C on foreground columns
    violations = 0
    for i, (a, z) in enumerate(zip(reps[:-1], reps[1:])):
        if z - a < 2:
            continue
        inside = final[a + 1:z]  # (z - a - 1, K)
        violations += int((exterior[i] & (inside < 0).any(0)).sum())
        violations += int((interior[i] & (inside >= 0).any(0)).sum())
        violations += int((skipped[:, i] & (S[:, a + 1:z] >= 0).any(1)).sum())
    return {"samples": samples, "dense": U * n * K, "columns": K, "candidates": int(candidate.sum()),
            "imprinted": int((final >= 0).all(0).sum()), "undecided_blocks": int((undecided & ~candidate[None]).sum()),
            "blocks": (len(reps) - 1) * K, "violations": violations}


# --------------------------------------------------------------------------- the prototype (--time)


def chunk_blocks(chunk: "C._Chunk", cols: torch.Tensor, step: torch.Tensor, block: int, imprint: bool,
                 buf: torch.Tensor | None = None) -> torch.Tensor:
    """Interior labels of one chunk of ``N`` proposals by the depth-block scheme (per-view bounds).

    Args:
        chunk: the chunk's maps and geometry (``carve._Chunk``, ``n`` depths, at least one used slot).
        cols: ``(N, K)`` long flat columns, foreground first (padding columns are background ones).
        step: ``(N, V)`` float per-step bound of each view slot (:func:`step_bounds`, directional).
        block: depths per block; imprint: as in ``carve.carve_proposals``.
        buf: optional float32 buffer for the representatives' coordinates.

    Returns:
        ``inside (N, n, K)`` bool, equal to the batched carving's labels of those columns.
    """
    n, (N, K), dev = chunk.n, cols.shape, cols.device
    reps = rep_depths(n, block)
    R = len(reps)
    rt = torch.tensor(reps, device=dev)
    L = (rt[1:] - rt[:-1]).float()  # (R-1,)
    h, w = C._column_hw(cols, n)
    used = [j for j, m in enumerate(chunk.maps) if m is not None]
    G = chunk.G[:, used]  # (N, U, 2, 4)
    depth = torch.arange(n, device=dev, dtype=torch.float32)
    dz = G[..., 0, None] * depth  # (N, U, 2, n): the batched carving's depth terms
    xy = C._column_terms(G, h, w)  # (N, U, 2, K): and its column terms
    colc = chunk.column_cost.gather(1, cols)
    fg = colc < 0  # (N, K) real foreground columns
    # 1. every view at the representative depths
    S, acc = [], None
    for u, j in enumerate(used):
        s = C._sample_planes(chunk.maps[j], dz[:, u][:, :, rt], xy[:, u], out=buf, mode=chunk.mode)  # (N, R, K)
        S.append(s)
        acc = s.clone() if acc is None else torch.maximum(acc, s, out=acc)
    rep_in = (acc < 0) & fg[:, None, :]
    # 2. block decisions: sum = 2 x midpoint, compared with L t (plus a relative float slack)
    ext_, int_, sums = None, None, []
    for u, j in enumerate(used):
        m = S[u][:, 1:] + S[u][:, :-1]  # (N, R-1, K)
        bound = m.abs().mul_(_REL).add_(L[None, :, None] * step[:, j, None, None])
        e, i = m > bound, m < -bound
        ext_ = e if ext_ is None else ext_.logical_or_(e)
        int_ = i if int_ is None else int_.logical_and_(i)
        sums.append((m, bound))
    ext_ |= ~fg[:, None, :]
    int_ &= fg[:, None, :]
    undecided = ~(ext_ | int_)
    candidate = fg & ~(rep_in.any(1) | int_.any(1))  # (N, K)
    undecided &= ~candidate[:, None, :]
    # labels at every depth: the representatives' own, a block's for its inner depths
    # (undecided blocks start interior; step 3 knocks out what a straddling view sees outside)
    row = torch.empty(n, dtype=torch.long)
    for r, d in enumerate(reps):
        row[d] = r
        if r + 1 < R:
            row[d + 1:reps[r + 1]] = R + r
    inside = torch.cat([rep_in, int_ | undecided], dim=1).index_select(1, row.to(dev))  # (N, n, K)
    # 3. undecided blocks, view by view, at the depths inside the block
    offsets = torch.arange(1, block, device=dev)
    flat = inside.view(-1)
    for u, j in enumerate(used):
        m, bound = sums[u]
        n_i, b_i, k_i = (undecided & (m >= -bound)).nonzero(as_tuple=True)
        if n_i.numel() == 0:
            continue
        valid, (bb, kk) = C._pad_rows(n_i, torch.stack([b_i, k_i]), N)  # (N, P) each
        d = torch.minimum(rt[bb][:, :, None] + offsets, rt[(bb + 1).clamp(max=R - 1)][:, :, None])  # (N, P, b-1)
        planes = torch.empty(N, 2, bb.shape[1], block - 1, device=dev)
        for a in range(2):  # G0 d + column term: the batched carving's arithmetic, bit for bit
            torch.mul(G[:, u, a, 0, None, None], d.float(), out=planes[:, a])
            planes[:, a] += xy[:, u, a].gather(1, kk)[:, :, None]
        v = C._grid_sample(chunk.maps[j], planes.permute(0, 2, 3, 1), chunk.mode)[:, 0]  # (N, P, b-1)
        nn, pp, oo = ((v >= 0) & valid[:, :, None]).nonzero(as_tuple=True)
        flat[(nn * n + d[nn, pp, oo]) * K + kk[nn, pp]] = False
    # 4. candidate columns: every depth of every view, imprinted as the batched carving does
    if bool(candidate.any()):
        rows_c, pos_c = candidate.nonzero(as_tuple=True)
        valid, (kc,) = C._pad_rows(rows_c, pos_c[None], N)  # (N, Kc) positions in cols
        whole = chunk.columns(cols.gather(1, kc), depth)  # (N, n, Kc)
        cost = torch.where(valid, colc.gather(1, kc), torch.ones_like(whole[:, 0]))  # padding: background
        ins, _, _ = C._label(whole, cost, imprint)
        rows = torch.arange(N, device=dev)[:, None].expand_as(kc)
        inside[rows[valid], :, kc[valid]] = ins.permute(0, 2, 1)[valid]
    return inside


def carve_blocks(maps: C.CarveMaps, reference: torch.Tensor, views: torch.Tensor, n: int, block: int,
                 imprint: bool, max_batch_voxels: int | None = None) -> torch.Tensor:
    """The prototype over a batch of proposals, chunked like ``carve.carve_proposals``.

    Args:
        maps: prepared maps; reference ``(B,)``, views ``(B, V)`` long entries (``-1`` unused).
        n: resolution; block: depths per block; imprint: as in ``carve.carve_proposals``.
        max_batch_voxels: chunk bound (default ``carve.default_batch_voxels``, as the batched carving).

    Returns:
        ``(B, n, n, n)`` bool occupancy, equal to ``carve.carve_proposals(...).occupancy``.
    """
    maps, reference, views = C._as_maps(maps, None, reference, views, n)
    dev = maps.device
    max_batch_voxels = max_batch_voxels or C.default_batch_voxels(dev)
    B, HW = views.shape[0], n * n
    ext, ref_u, views_u, _, G, G_ref, scale = C._prepare(maps, reference, views, n)
    column_cost = C._reference_columns(ext, ref_u, G_ref, n, n)
    fg = column_cost < 0
    step, _ = step_bounds(G, scale, views_u, *maps.pixel_differences(), tuple(ext.shape[1:]))
    count = fg.sum(1)
    order = torch.argsort(count, descending=True, stable=True)
    col_order = C._foreground_first(fg)
    counts = count[order].tolist()
    occ = torch.zeros(B, n, HW, dtype=torch.bool, device=dev)
    per, start, buf = C._chunk_multiple(dev), 0, None
    while start < B:
        k = max(counts[start], 1)
        size = max(1, max_batch_voxels // (k * n))
        size = min(B - start, size - size % per if size >= per else size)
        idx, start = order[start:start + size], start + size
        slots = (views[idx] >= 0).any(0).tolist()
        if counts[start - size] == 0 or not any(slots):
            continue  # no foreground column, or no view: handled below as the batched carving does
        chunk = C._Chunk(ext, views_u[idx], scale[idx], G[idx], torch.index_select(column_cost, 0, idx), n, slots)
        cols = col_order[idx, :k]
        if buf is None or buf.numel() < idx.shape[0] * k * n * 2:
            buf = torch.empty(idx.shape[0] * k * n * 2, device=dev)
        inside = chunk_blocks(chunk, cols, step[idx], block, imprint, buf)
        spread = cols[:, None, :].expand(-1, n, -1)
        occ[idx] = torch.zeros(idx.shape[0], n, HW, dtype=torch.bool, device=dev).scatter_(2, spread, inside)
    # proposals without a used view: the reference alone (the batched carving's own path)
    alone = ((views < 0).all(1) & (count > 0)).nonzero()[:, 0]
    if alone.numel():
        occ[alone] = C.carve_proposals(maps, None, reference[alone], views[alone], resolution=n,
                                       imprint=imprint).occupancy.view(-1, n, HW)
    return occ.view(B, n, n, n)


def time_prototype(args) -> dict:
    """Seconds per object of the batched carving and of the prototype on the pipeline's proposals of
    ``--time-objects`` references (one call per pipeline chunk of references), interleaved rounds;
    their ``grid_sample`` time (``bench_carve.GridSampleClock``); labels compared voxel for voxel."""
    torch.set_num_threads(args.threads)
    device = torch.device("cpu")
    ns = argparse.Namespace(data=args.data, category=args.category, objects=args.time_objects)
    cfg, plan, _, K, ref, views, valid = class_proposals(ns, device)
    bounds = pipeline_call_bounds(cfg, valid, K, device)
    n, b = cfg.resolution, args.time_block

    def dense(keep=False):
        out = []
        for a, z in zip(bounds[:-1], bounds[1:]):
            g = C.carve_proposals(plan.maps, None, ref[a:z], views[a:z], resolution=n, imprint=cfg.imprint)
            out.append(g.occupancy if keep else None)
        return out

    def blocks(keep=False):
        out = []
        for a, z in zip(bounds[:-1], bounds[1:]):
            occ = carve_blocks(plan.maps, ref[a:z], views[a:z], n, b, cfg.imprint)
            out.append(occ if keep else None)
        return out

    identical = all(torch.equal(x, y) for x, y in zip(dense(True), blocks(True)))
    times = {"dense": [], "blocks": []}
    for _ in range(args.repeat):
        for name, f in (("dense", dense), ("blocks", blocks)):
            t0 = time.perf_counter()
            f()
            times[name].append((time.perf_counter() - t0) / K)
    sampling = {}
    for name, f in (("dense", dense), ("blocks", blocks)):
        with GridSampleClock(device) as clock:
            f()
        sampling[name] = {"seconds_per_object": clock.seconds / K, "samples_per_object": clock.samples / K}
    ratios = [x / y for x, y in zip(times["dense"], times["blocks"])]
    out = {"objects": K, "block": b, "threads": torch.get_num_threads(), "repeat": args.repeat,
           "identical": identical, "seconds_per_object": {k: min(v) for k, v in times.items()},
           "dense_over_blocks_median": statistics.median(ratios), "grid_sample": sampling}
    s = out["seconds_per_object"]
    print(f"\ntiming, {K} objects, {out['threads']} thread(s), block {b}: batched carving {1000 * s['dense']:.1f} ms "
          f"per object, depth-block prototype {1000 * s['blocks']:.1f} (best of {args.repeat}; batched / prototype, "
          f"median of the rounds: {out['dense_over_blocks_median']:.2f}); grid_sample "
          f"{1000 * sampling['dense']['seconds_per_object']:.1f} against "
          f"{1000 * sampling['blocks']['seconds_per_object']:.1f} ms per object for "
          f"{sampling['dense']['samples_per_object'] / 1e6:.2f} against "
          f"{sampling['blocks']['samples_per_object'] / 1e6:.2f} million samples; identical labels: {identical}")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="annotations.json of the class")
    ap.add_argument("--category", default="car")
    ap.add_argument("--objects", type=int, default=15, help="references whose proposals are simulated")
    ap.add_argument("--blocks", type=int, nargs="+", default=[2, 3, 4, 5, 6])
    ap.add_argument("--time", action="store_true",
                    help="also time the depth-block prototype against the batched carving (same proposals)")
    ap.add_argument("--time-objects", type=int, default=50, help="references of the timing")
    ap.add_argument("--time-block", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the timing")
    ap.add_argument("--repeat", type=int, default=3, help="interleaved rounds of the timing")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "carve_sample_bounds.json"))
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    if min(args.blocks + [args.time_block]) < 2:
        ap.error("blocks hold at least 2 depths")
    ns = argparse.Namespace(data=args.data, category=args.category, objects=args.objects)
    cfg, plan, _, K, ref, views, _ = class_proposals(ns, torch.device("cpu"))
    totals = {(b, pv): {} for b in args.blocks for pv in (True, False)}
    proposals = 0
    for S, t, t_iso in view_samples(plan.maps, ref, views, cfg.resolution):
        proposals += 1
        for (b, pv), acc in totals.items():
            r = simulate(S, t if pv else torch.full_like(t, float(t_iso.max())), b, pv)
            for k, v in r.items():
                acc[k] = acc.get(k, 0) + v
    rows = []
    print(f"{proposals} proposals of {K} references, {cfg.resolution}^3 voxels\n")
    print("| depth block | bounds | samples / dense | columns sampled whole (imprinted) | undecided blocks | "
          "violations |")
    print("|---:|---|---:|---:|---:|---:|")
    for (b, pv), a in totals.items():
        row = {"block": b, "per_view_bounds": pv, "sample_fraction": a["samples"] / a["dense"],
               "candidate_column_fraction": a["candidates"] / a["columns"],
               "imprinted_column_fraction": a["imprinted"] / a["columns"],
               "undecided_block_fraction": a["undecided_blocks"] / a["blocks"], "violations": a["violations"]}
        rows.append(row)
        print(f"| {b} | {'per view, directional' if pv else 'single'} | {row['sample_fraction']:.3f} | "
              f"{row['candidate_column_fraction']:.3f} ({row['imprinted_column_fraction']:.3f}) | "
              f"{row['undecided_block_fraction']:.3f} | {row['violations']} |")
    result = {"command": " ".join(["python tools/carve_sample_bounds.py"] + [shlex.quote(a) for a in argv]),
              "objects": K, "proposals": proposals, "resolution": cfg.resolution, "rows": rows}
    if args.time:
        result["timing"] = time_prototype(args)
    write_json(args.out, result)
    print(f"\nwrote {args.out}")
    return result


if __name__ == "__main__":
    main()
