"""Benchmark of imprinted visual hull carving: batched vs loop vs the bare grid_sample calls.

A synthetic class (random unions of ellipsoids, seen from random viewpoints, with
their mirrored copies) gives ``--references`` objects with ``--proposals`` proposals
each; every proposal carves the reference with 5 further views (two surrogates,
their mirrored copies and the mirrored reference), as the pipeline does. Timed:

* ``batched``: :func:`carvi_torch.carve.carve_proposals` on all proposals at once, on
  maps prepared once (:func:`carvi_torch.carve.prepare_maps`, timed apart, as the
  pipeline does per class);
* ``loop``: :func:`carvi_torch.carve.carve_proposals_loop` (one proposal, one view
  at a time, its maps prepared per proposal) on the first ``--loop-references``
  objects, and checked voxel for voxel against the batched result;
* ``batched, depth_intervals=True`` and ``batched, coarse_to_fine=True``: the same with
  the optional per-column depth intervals or coarse-to-fine evaluation (fewer samples,
  more bookkeeping);
* ``floor``: the time spent inside the ``grid_sample`` calls alone, measured in situ
  (``carve._grid_sample`` wrapped by a clock) for each of those runs; the loop's floor
  is the cost of sampling every voxel of every proposal.

Times are the best of ``--repeat`` runs, reported in seconds per object (one
reference with all its proposals). Writes ``docs/benchmarks/carve.json``.

    python tools/bench_carve.py [--device cpu|cuda] [--threads N] [--out docs/benchmarks/carve.json]
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import torch

from carvi_torch import carve as C
from carvi_torch.cameras import ScaledOrthographic, random_rotations
from carvi_torch.io.outputs import write_json
from carvi_torch.sdf import signed_distance

ROOT = Path(__file__).resolve().parents[1]


def synthetic_class(n: int, size: int, gen: torch.Generator):
    """``n`` objects (unions of 3 ellipsoids) seen from random viewpoints, and their mirrored copies.

    Returns masks ``(2n, size, size)`` bool (copies at ``n + i``) and their cameras.
    """
    R = random_rotations(n, gen)
    s = 0.32 * size * (0.8 + 0.4 * torch.rand(n, generator=gen))
    t = (size - 1) / 2 + 0.05 * size * torch.randn(n, 2, generator=gen)
    cams = ScaledOrthographic(R, s, t)
    centres = 0.5 * torch.randn(n, 3, 3, generator=gen).clamp(-1.5, 1.5)
    axes = 0.25 + 0.6 * torch.rand(n, 3, 3, generator=gen)
    parts = random_rotations(3 * n, gen).view(n, 3, 3, 3)
    sigma = parts.transpose(-1, -2) @ torch.diag_embed(axes ** 2) @ parts  # (n, part, 3, 3)
    M = cams.M[:, None]  # (n, 1, 2, 3)
    cov = M @ sigma @ M.transpose(-1, -2)  # (n, part, 2, 2)
    mu = (M @ centres[..., None])[..., 0] + t[:, None]  # (n, part, 2)
    ys, xs = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                            indexing="ij")
    d = torch.stack([xs, ys], -1)[None, None] - mu[:, :, None, None]  # (n, part, H, W, 2)
    q = torch.einsum("npyxi,npij,npyxj->npyx", d, torch.linalg.inv(cov), d)
    masks = (q <= 1).any(dim=1)
    mirrored = cams.mirror(size)
    return torch.cat([masks, masks.flip(-1)]), ScaledOrthographic.cat([cams, mirrored])


def proposals(n: int, per: int, gen: torch.Generator):
    """Reference ``r`` with surrogates ``a, b`` and mirrors: views ``[a, b, a', b', r']``."""
    reference = torch.arange(n).repeat_interleave(per)
    a = (reference + 1 + torch.randint(0, n - 1, (n * per,), generator=gen)) % n
    b = (reference + 1 + torch.randint(0, n - 1, (n * per,), generator=gen)) % n
    views = torch.stack([a, b, a + n, b + n, reference + n], dim=1)
    return reference, views


def sync(device: torch.device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def best_of(fn, repeat: int, device: torch.device) -> float:
    times = []
    for _ in range(repeat):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return min(times)


class GridSampleClock:
    """Times the ``grid_sample`` calls of a carving in situ (wraps ``carve._grid_sample``)."""

    def __init__(self, device: torch.device):
        self.device, self.seconds, self.samples = device, 0.0, 0

    def __enter__(self):
        self._orig = C._grid_sample

        def timed(maps, grid, mode="bilinear"):
            sync(self.device)
            t0 = time.perf_counter()
            out = self._orig(maps, grid, mode)
            sync(self.device)
            self.seconds += time.perf_counter() - t0
            self.samples += grid.numel() // 2
            return out

        C._grid_sample = timed
        return self

    def __exit__(self, *exc):
        C._grid_sample = self._orig


def floor(fn, repeat: int, device: torch.device) -> tuple[float, int]:
    """Best total time of the grid_sample calls of ``fn()`` over ``repeat`` runs, and their sample count."""
    best, samples = math.inf, 0
    for _ in range(repeat):
        with GridSampleClock(device) as clock:
            fn()
        best, samples = min(best, clock.seconds), clock.samples
    return best, samples


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument("--references", type=int, default=50)
    ap.add_argument("--proposals", type=int, default=20)
    ap.add_argument("--resolution", type=int, default=60)
    ap.add_argument("--canvas", type=int, default=128)
    ap.add_argument("--loop-references", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--max-batch-voxels", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "carve.json"))
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    gen = torch.Generator().manual_seed(args.seed)
    n_obj, per, n = args.references, args.proposals, args.resolution
    masks, cams = synthetic_class(n_obj, args.canvas, gen)
    reference, views = proposals(n_obj, per, gen)
    sdf = signed_distance(masks).to(device)
    cams, reference, views = cams.to(device), reference.to(device), views.to(device)
    mbv = args.max_batch_voxels or C.default_batch_voxels(device)

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    t_prepare = best_of(lambda: C.prepare_maps(sdf, cams), args.repeat, device)
    maps = C.prepare_maps(sdf, cams)
    carve = lambda: C.carve_proposals(maps, None, reference, views, resolution=n, max_batch_voxels=mbv)  # noqa: E731
    out = carve()  # warm-up
    t_batched = best_of(carve, args.repeat, device)
    intervals = lambda: C.carve_proposals(maps, None, reference, views, resolution=n,  # noqa: E731
                                          max_batch_voxels=mbv, depth_intervals=True)
    identical_intervals = bool(torch.equal(intervals().occupancy, out.occupancy))
    t_int = best_of(intervals, args.repeat, device)
    t_int_floor, int_samples = floor(intervals, args.repeat, device)

    n_loop = min(args.loop_references, n_obj) * per
    loop = lambda: C.carve_proposals_loop(sdf, cams, reference[:n_loop], views[:n_loop], resolution=n)  # noqa: E731
    ref_loop = loop()
    t_loop = best_of(loop, max(1, min(args.repeat, 2)), device) * n_obj * per / n_loop  # extrapolated to all objects
    identical = bool(torch.equal(ref_loop.occupancy, out.occupancy[:n_loop]))

    t_floor, samples = floor(carve, args.repeat, device)
    c2f = lambda: C.carve_proposals(maps, None, reference, views, resolution=n, max_batch_voxels=mbv,  # noqa: E731
                                    coarse_to_fine=True)
    t_c2f = best_of(c2f, args.repeat, device)
    t_c2f_floor, c2f_samples = floor(c2f, args.repeat, device)
    t_loop_floor, loop_samples = floor(loop, 1, device)
    t_loop_floor *= n_obj * per / n_loop
    loop_samples = loop_samples * n_obj * per // n_loop

    per_obj = lambda t: t / n_obj  # noqa: E731
    rows = [
        ("prepare maps (once per class)", t_prepare, 0),
        ("batched (foreground columns)", t_batched, samples),
        ("batched, depth_intervals=True", t_int, int_samples),
        ("batched, coarse_to_fine=True", t_c2f, c2f_samples),
        ("loop (every voxel)", t_loop, loop_samples),
        ("floor: grid_sample of batched", t_floor, samples),
        ("floor: grid_sample of depth intervals", t_int_floor, int_samples),
        ("floor: grid_sample of coarse-to-fine", t_c2f_floor, c2f_samples),
        ("floor: grid_sample of loop", t_loop_floor, loop_samples),
    ]
    print(f"device {device}, threads {torch.get_num_threads()}, load average at start {load:.2f}")
    print(f"{n_obj} objects x {per} proposals, {views.shape[1]} further views, {n}^3 voxels, canvas {args.canvas}")
    print(f"{'':40s} {'s/object':>10s} {'total s':>9s} {'Msamples':>9s}")
    for name, t, s_ in rows:
        print(f"{name:40s} {per_obj(t):10.4f} {t:9.3f} {s_ / 1e6:9.1f}")
    print(f"batched vs loop: {t_loop / t_batched:.1f}x faster; batched / its floor: {t_batched / t_floor:.2f}; "
          f"batched / loop's floor: {t_batched / t_loop_floor:.2f}; "
          f"identical to loop on {n_loop} proposals: {identical}; depth intervals identical: {identical_intervals}")
    occupied = float(out.occupancy.float().mean())
    result = {
        "command": " ".join(["python tools/bench_carve.py"] + argv),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count(),
                    "torch": torch.__version__, "threads": torch.get_num_threads(), "device": str(device),
                    "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
                    "load_average_at_start": load},
        "config": {"references": n_obj, "proposals_per_reference": per, "further_views": int(views.shape[1]),
                   "resolution": n, "canvas": args.canvas, "max_batch_voxels": mbv, "repeat": args.repeat,
                   "loop_proposals_timed": n_loop, "seed": args.seed},
        "seconds_per_object": {"prepare_maps": per_obj(t_prepare), "batched": per_obj(t_batched),
                               "batched_depth_intervals": per_obj(t_int), "batched_coarse_to_fine": per_obj(t_c2f),
                               "loop": per_obj(t_loop), "floor_batched": per_obj(t_floor),
                               "floor_depth_intervals": per_obj(t_int_floor),
                               "floor_coarse_to_fine": per_obj(t_c2f_floor), "floor_loop": per_obj(t_loop_floor)},
        "samples_per_object": {"batched": samples / n_obj, "depth_intervals": int_samples / n_obj,
                               "coarse_to_fine": c2f_samples / n_obj, "loop": loop_samples / n_obj},
        "speedup_vs_loop": t_loop / t_batched,
        "batched_over_its_floor": t_batched / t_floor,
        "batched_over_loop_floor": t_batched / t_loop_floor,
        "identical_to_loop": identical,
        "depth_intervals_identical": identical_intervals,
        "occupied_fraction": occupied,
        "foreground_column_fraction": float(out.reference_columns.float().mean()),
    }
    if args.out:
        write_json(args.out, result)
        print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
