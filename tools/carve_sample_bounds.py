"""How many samples an exact coarse-to-fine carving along depth would still need (a bound, not a carving).

For each proposal of the first ``--objects`` references (the pipeline's own proposals, same
seed as a run), every view is sampled densely on the reference's foreground columns, as the
batched carving samples them. Then a scheme is *simulated* on those exact values: sample every
view at the depths ``0, b, 2b, ...`` and the last one; between two sampled depths ``r0 < r1`` a
view's cost lies within ``(C(r0) + C(r1)) / 2 +- (r1 - r0) t / 2`` for the view's bound ``t`` on
its change per depth step (the map's largest pixel differences along x and y, weighted by how
far one depth step moves the view's projection along x and y, times the view's scale, plus a
float slack), so

* a block is exterior when some view's lower bound is positive, interior when every view's upper
  bound is negative (and the column is a foreground one);
* in the other blocks only the views whose bounds straddle zero need their samples;
* a column that has no sampled interior voxel and no interior block may have to be imprinted,
  and needs its whole cost: every depth of every view.

``single bound`` uses one bound per proposal (the largest over its views of the map's gradient
bound times the view's step, as ``coarse_to_fine`` bounds a proposal: sqrt 2 per pixel for an
exact distance map) and samples every view in an undecided block. The result is the fraction of
the dense carving's samples each scheme needs: what it could save at best, before paying for
finding and gathering the undecided blocks. No labels are produced.

``--time`` also runs a prototype of that scheme (per-view bounds, ``--time-block`` depths per
block; kept here, not in the package) against the batched carving on the pipeline's proposals of
``--time-objects`` references: it finds the undecided blocks with ``nonzero``, pads them per
proposal, gathers their coordinates, samples them, and knocks out the voxels a straddling view
sees outside; candidate columns are carved whole. Its labels are compared with the batched
carving's voxel for voxel, and both are timed, with their ``grid_sample`` time alone.

    python tools/carve_sample_bounds.py --data outputs/bench/data/car1000_s0/annotations.json [--time]
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import bench_changes  # noqa: E402
from carvi_torch import carve as C  # noqa: E402
from carvi_torch.io.outputs import write_json  # noqa: E402


# --------------------------------------------------------------------------- the prototype (--time)


_LIP = {}


def lip_xy(ext):
    """``(lx, ly)``: each map's largest absolute difference between neighbouring pixels along x and y."""
    key = (ext.data_ptr(), ext.shape)
    if key in _LIP:
        return _LIP[key]
    lx = (ext[:, :, 1:] - ext[:, :, :-1]).abs().flatten(1).amax(1)
    ly = (ext[:, 1:] - ext[:, :-1]).abs().flatten(1).amax(1)
    _LIP[key] = (lx, ly)
    return lx, ly


def chunk_blocks(chunk, cols, colc, tv, n, b, imprint, buf=None):
    """One chunk of the depth-block prototype: ``chunk`` a ``carve._Chunk``, ``cols (N, K)`` its
    columns (foreground first), ``colc (N, K)`` their reference cost, ``tv (N, V)`` per-step bounds.
    Returns ``inside (N, n, K)`` bool, ``nonempty (N,)``, ``col_occ (N, K)``."""
    N, K = cols.shape
    dev = cols.device
    reps = list(range(0, n, b))
    if reps[-1] != n - 1:
        reps.append(n - 1)
    R = len(reps)
    rt = torch.tensor(reps, device=dev)
    Lb = (rt[1:] - rt[:-1]).float()  # (R-1,)
    h, w = C._column_hw(cols, n)
    used = [j for j, m in enumerate(chunk.maps) if m is not None]
    G = chunk.G[:, used]  # (N,U,2,4)
    depth = torch.arange(n, device=dev, dtype=torch.float32)
    dz = G[..., 0, None] * depth  # (N,U,2,n)
    xy = C._column_terms(G, h, w)  # (N,U,2,K)
    fgv = colc < 0  # (N,K) real foreground columns
    # phase 1: representatives
    S = []
    acc = None
    for u, j in enumerate(used):
        s = C._sample_planes(chunk.maps[j], dz[:, u][:, :, rt], xy[:, u], out=buf, mode=chunk.mode)
        S.append(s)
        acc = s.clone() if acc is None else torch.maximum(acc, s, out=acc)
    rep_in = (acc < 0) & fgv[:, None, :]  # (N,R,K)
    # phase 2: bounds
    E = None
    I = None
    M = []
    for u, j in enumerate(used):
        s = S[u]
        m = s[:, 1:] + s[:, :-1]  # (N,R-1,K) = 2 mid
        hl = (Lb[None, :, None] * tv[:, j, None, None])  # (N,R-1,1)
        sl = m.abs().mul_(1e-5).add_(hl)
        e = m > sl
        i = m < -sl
        E = e if E is None else E.logical_or_(e)
        I = i if I is None else I.logical_and_(i)
        M.append((m, sl))
    E |= ~fgv[:, None, :]
    I &= fgv[:, None, :]
    und = ~(E | I)
    occ_known = rep_in.any(1) | I.any(1)
    cand = fgv & ~occ_known  # (N,K)
    und &= ~cand[:, None, :]
    # labels: rep depths and block states
    src = torch.cat([rep_in, I | und], dim=1)  # (N, R + R-1, K)
    row = torch.empty(n, dtype=torch.long)
    for ri, d in enumerate(reps):
        row[d] = ri
    for bi in range(R - 1):
        for d in range(reps[bi] + 1, reps[bi + 1]):
            row[d] = R + bi
    inside = src.index_select(1, row.to(dev))  # (N,n,K)
    # phase 3: undecided blocks, per view
    offs = torch.arange(1, b, device=dev, dtype=torch.long)  # (b-1,)
    flat_in = inside.view(-1)
    for u, j in enumerate(used):
        m, sl = M[u]
        need = und & (m >= -sl)
        n_i, b_i, k_i = need.nonzero(as_tuple=True)
        if n_i.numel() == 0:
            continue
        valid, (bb, kk) = C._pad_rows(n_i, torch.stack([b_i, k_i]), N)  # (N,P)
        d = (rt[bb][:, :, None] + offs).clamp_(max=n - 1)  # (N,P,b-1)
        d = torch.minimum(d, rt[(bb + 1).clamp(max=R - 1)][:, :, None])
        P = bb.shape[1]
        df = d.float()
        Gu = G[:, u]  # (N,2,4)
        xyu = xy[:, u]  # (N,2,K)
        planes = torch.empty(N, 2, P, b - 1, device=dev)
        for a in range(2):
            torch.mul(Gu[:, a, 0, None, None], df, out=planes[:, a])
            planes[:, a] += xyu[:, a].gather(1, kk)[:, :, None]
        v = C._grid_sample(chunk.maps[j], planes.permute(0, 2, 3, 1), chunk.mode)[:, 0]  # (N,P,b-1)
        out = (v >= 0) & valid[:, :, None]
        nn, pp, oo = out.nonzero(as_tuple=True)
        if nn.numel():
            flat_in[(nn * n + d[nn, pp, oo]) * K + kk[nn, pp]] = False
    # candidates: whole columns
    col_occ = inside.any(1)
    nonempty = col_occ.any(1)
    if cand.any():
        cn_i, ck_i = cand.nonzero(as_tuple=True)
        valid, (kc,) = C._pad_rows(cn_i, ck_i[None], N)  # positions in cols
        cc = cols.gather(1, kc)
        full = chunk.columns(cc, depth)  # (N,n,Kc)
        padded_cost = torch.where(valid, colc.gather(1, kc), torch.ones_like(cc, dtype=torch.float32))
        ins, _, _ = C._label(full, padded_cost, imprint)  # padding entries count as background columns
        ins &= valid[:, None, :]
        rows = torch.arange(N, device=dev)[:, None].expand_as(kc)
        inside[rows[valid], :, kc[valid]] = ins.permute(0, 2, 1)[valid]
        col_occ = inside.any(1)
        nonempty = col_occ.any(1)
    return inside, nonempty, col_occ


def carve_blocks(maps, reference, views, n=60, b=4, imprint=True, max_batch_voxels=None):
    """The depth-block prototype over a batch of proposals (labels equal to ``carve_proposals``)."""
    maps, reference, views = C._as_maps(maps, None, reference, views, n)
    dev = maps.device
    if max_batch_voxels is None:
        max_batch_voxels = C.default_batch_voxels(dev)
    B = views.shape[0]
    HW = n * n
    ext, ref_u, views_u, _, G, G_ref, scale = C._prepare(maps, reference, views, n)
    column_cost = C._reference_columns(ext, ref_u, G_ref, n, n)
    fg = column_cost < 0
    lx, ly = lip_xy(ext)
    Hp, Wp = ext.shape[1:]
    # per view and proposal: how much its scaled map can change per depth step, plus a float slack
    moves = lx[views_u] * G[:, :, 0, 0].abs() * (Wp - 1) / 2 + ly[views_u] * G[:, :, 1, 0].abs() * (Hp - 1) / 2
    step = scale * moves * (1 + 1e-5) + 1e-3  # (B, V)
    count = fg.sum(1)
    order = torch.argsort(count, descending=True, stable=True)
    col_order = C._foreground_first(fg)
    cs = count[order].tolist()
    occ = torch.zeros(B, n, HW, dtype=torch.bool, device=dev)
    nonempty = torch.zeros(B, dtype=torch.bool, device=dev)
    per = C._chunk_multiple(dev)
    start = 0
    buf = None
    while start < B:
        k = max(cs[start], 1)
        size = max(1, 2 * max_batch_voxels // (k * n))  # it samples about half: chunks twice as large
        size = min(B - start, size - size % per if size >= per else size)
        idx = order[start:start + size]
        start += size
        if cs[start - size] == 0:
            continue
        slots = (views[idx] >= 0).any(0).tolist()
        chunk = C._Chunk(ext, views_u[idx], scale[idx], G[idx], torch.index_select(column_cost, 0, idx), n, slots)
        cols = col_order[idx, :k]
        if buf is None or buf.numel() < idx.shape[0] * k * n * 2:
            buf = torch.empty(idx.shape[0] * k * n * 2, device=dev)
        inside, nonempty[idx], _ = chunk_blocks(chunk, cols, chunk.column_cost.gather(1, cols), step[idx], n, b,
                                                imprint, buf)
        spread = cols[:, None, :].expand(-1, n, -1)
        occ[idx] = torch.zeros(idx.shape[0], n, HW, dtype=torch.bool, device=dev).scatter_(2, spread, inside)
    return occ.view(B, n, n, n), nonempty




def view_samples(maps, ref, views, n):
    """Per proposal: ``S (U, D, K)`` float64 costs of its used views on its foreground columns,
    ``t (U,)`` per-view bounds (directional) and ``t1`` the single bound."""
    ext, ref_u, views_u, T, G, G_ref, scale = C._prepare(maps, ref, views, n)
    column_cost = C._reference_columns(ext, ref_u, G_ref, n, n)
    Hp, Wp = ext.shape[1:]
    lx = (ext[:, :, 1:] - ext[:, :, :-1]).abs().flatten(1).amax(1).double()
    ly = (ext[:, 1:] - ext[:, :-1]).abs().flatten(1).amax(1).double()
    depth = torch.arange(n, dtype=torch.float32)
    for b in range(len(ref)):
        cols = (column_cost[b] < 0).nonzero()[:, 0][None]
        if cols.shape[1] == 0:
            continue
        h, w = C._column_hw(cols, n)
        S, t, t1 = [], [], 0.0
        for j in range(views.shape[1]):
            if int(views[b, j]) < 0:
                continue
            m = ext[views_u[b:b + 1, j]][:, None] * scale[b, j]
            xy = C._column_terms(G[b:b + 1, j], h, w)
            S.append(C._sample_planes(m, G[b:b + 1, j, :, 0, None] * depth, xy)[0].double())
            g0 = G[b, j, :, 0].double()
            dx, dy = float(g0[0].abs()) * (Wp - 1) / 2, float(g0[1].abs()) * (Hp - 1) / 2
            mi, sc = views_u[b, j], float(scale[b, j])
            t.append(sc * (float(lx[mi]) * dx + float(ly[mi]) * dy) * (1 + 1e-5) + 1e-3)
            lip = (float(lx[mi]) ** 2 + float(ly[mi]) ** 2) ** 0.5  # the map's bound, as coarse_to_fine takes it
            t1 = max(t1, sc * lip * (dx * dx + dy * dy) ** 0.5 * (1 + 1e-5) + 1e-3)
        if S:
            yield torch.stack(S), torch.tensor(t, dtype=torch.float64), t1


def simulate(S: torch.Tensor, t: torch.Tensor, block: int, per_view: bool) -> dict:
    """Samples the block scheme needs on one proposal (see the module docstring)."""
    U, n, K = S.shape
    reps = list(range(0, n, block))
    if reps[-1] != n - 1:
        reps.append(n - 1)
    rt = torch.tensor(reps)
    L = (rt[1:] - rt[:-1]).double()[None, :, None]  # (1, R-1, 1)
    Sr = S[:, rt]  # (U, R, K)
    mid = (Sr[:, 1:] + Sr[:, :-1]) / 2
    half = t[:, None, None] * L / 2
    exterior = ((mid - half) > 0).any(0)
    interior = ((mid + half) < 0).all(0)
    undecided = ~exterior & ~interior
    occupied = (Sr.amax(0) < 0).any(0) | interior.any(0)
    candidate = ~occupied  # may need imprinting: whole columns
    inner = L - 1
    if per_view:
        need = undecided[None] & (mid + half >= 0) & ~candidate[None, None]
        fine = float((need.double() * inner).sum())
    else:
        fine = float(((undecided & ~candidate[None]).double() * inner[0]).sum()) * U
    samples = U * len(reps) * K + int(candidate.sum()) * U * (n - len(reps)) + fine
    truth = (S.amax(0) < 0).any(0)
    return {"samples": samples, "dense": U * n * K, "columns": K, "candidates": int(candidate.sum()),
            "imprinted": int((~truth).sum()), "undecided_blocks": int((undecided & ~candidate[None]).sum()),
            "blocks": (len(reps) - 1) * K}


def time_prototype(args) -> dict:
    """Seconds per object of the batched carving and of the prototype on the pipeline's proposals of
    ``--time-objects`` references (one call per pipeline chunk of references), interleaved rounds;
    their ``grid_sample`` time (``bench_carve.GridSampleClock``); labels compared voxel for voxel."""
    import statistics
    import time

    from bench_carve import GridSampleClock
    from carvi_torch import pipeline

    torch.set_num_threads(args.threads)
    ns = argparse.Namespace(data=args.data, category=args.category, objects=args.time_objects)
    cfg, plan, _, K, ref, views, valid = bench_changes.class_proposals(ns, torch.device("cpu"))
    per_ref = valid.view(K, -1).sum(1).tolist()
    step = pipeline._chunk_objects(cfg, torch.device("cpu"))
    bounds = [sum(per_ref[:a]) for a in range(0, K, step)] + [len(ref)]
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
            occ, _ = carve_blocks(plan.maps, ref[a:z], views[a:z], n, b, cfg.imprint)
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
        with GridSampleClock(torch.device("cpu")) as clock:
            f()
        sampling[name] = {"seconds_per_object": clock.seconds / K, "samples_per_object": clock.samples / K}
    ratios = [x / y for x, y in zip(times["dense"], times["blocks"])]
    out = {"objects": K, "block": b, "threads": torch.get_num_threads(), "identical": identical,
           "seconds_per_object": {k: min(v) for k, v in times.items()},
           "dense_over_blocks_median": statistics.median(ratios), "grid_sample": sampling}
    s = out["seconds_per_object"]
    print(f"\ntiming, {K} objects, {out['threads']} thread(s), block {b}: batched carving {1000 * s['dense']:.1f} ms "
          f"per object, depth-block prototype {1000 * s['blocks']:.1f} (batched / prototype, median of rounds: "
          f"{out['dense_over_blocks_median']:.2f}); grid_sample {1000 * sampling['dense']['seconds_per_object']:.1f} "
          f"against {1000 * sampling['blocks']['seconds_per_object']:.1f} ms per object for "
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
    ns = argparse.Namespace(data=args.data, category=args.category, objects=args.objects)
    cfg, plan, _, K, ref, views, _ = bench_changes.class_proposals(ns, torch.device("cpu"))
    totals = {(b, pv): {} for b in args.blocks for pv in (True, False)}
    proposals = 0
    for S, t, t1 in view_samples(plan.maps, ref, views, cfg.resolution):
        proposals += 1
        for (b, pv), acc in totals.items():
            r = simulate(S, t if pv else torch.full_like(t, t1), b, pv)
            for k, v in r.items():
                acc[k] = acc.get(k, 0) + v
    rows = []
    print(f"{proposals} proposals of {K} references, {cfg.resolution}^3 voxels\n")
    print("| depth block | bounds | samples / dense | columns needing every depth (imprinted) | undecided blocks |")
    print("|---:|---|---:|---:|---:|")
    for (b, pv), a in totals.items():
        row = {"block": b, "per_view_bounds": pv, "sample_fraction": a["samples"] / a["dense"],
               "candidate_column_fraction": a["candidates"] / a["columns"],
               "imprinted_column_fraction": a["imprinted"] / a["columns"],
               "undecided_block_fraction": a["undecided_blocks"] / a["blocks"]}
        rows.append(row)
        print(f"| {b} | {'per view, directional' if pv else 'single'} | {row['sample_fraction']:.3f} | "
              f"{row['candidate_column_fraction']:.3f} ({row['imprinted_column_fraction']:.3f}) | "
              f"{row['undecided_block_fraction']:.3f} |")
    result = {"command": " ".join(["python tools/carve_sample_bounds.py"] + [shlex.quote(a) for a in argv]),
              "objects": K, "proposals": proposals, "resolution": cfg.resolution, "rows": rows}
    if args.time:
        result["timing"] = time_prototype(args)
    write_json(args.out, result)
    print(f"\nwrote {args.out}")
    return result


if __name__ == "__main__":
    main()
