"""Benchmark of the reconstruction metric on real PASCAL3D+ CAD models.

For each model: the CAD mesh is put in a reference camera frame (canvas pixels, as the
pipeline's meshes are), a "60^3-voxel-like" reconstruction is made from it (solid
voxelisation with 60 voxels along its longest side, marching cubes, vertices jittered by
a quarter voxel, shifted 7 px in depth), and ``evaluate_reconstruction`` is timed for
several sampling steps and torch thread counts:

* ``cold``: everything built for the call (GT samples and distance index included);
* ``warm``: the GT wrapped once in an ``EvaluationMesh`` (as when the methods and
  baselines of one view are scored against the same GT), its cost left out.

It also times the exact ``point_to_mesh_distance`` of ~100k points near the surface, and
checks the depth search against the best of a dense scan of exact evaluations (61 offsets
within 3% of the diagonal). Prints tables and writes ``docs/benchmarks/metrics.json``.

    python tools/bench_metrics.py [--models aeroplane01 aeroplane02] [--steps 0.005 0.01]
                                  [--threads 1 2] [--repeats 3] [--out docs/benchmarks/metrics.json]

Data: ``../shared/data/pascal3d_cad`` (Xiang, Mottaghi, Savarese, "Beyond PASCAL",
WACV 2014).
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from skimage import measure

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from carvi_torch.cameras import ScaledOrthographic, rotation_from_azimuth_elevation_roll  # noqa: E402
from carvi_torch.io.outputs import write_json  # noqa: E402
from carvi_torch.metrics import (  # noqa: E402
    EvaluationMesh,
    MeshDistanceIndex,
    evaluate_reconstruction,
    rms_distance,
    sample_surface,
    voxelize_solid,
)

DATA = (ROOT / ".." / "shared" / "data" / "pascal3d_cad").resolve()


def camera_frame_gt(name: str, canvas: int = 128) -> tuple[trimesh.Trimesh, float]:
    """The CAD model in the camera frame of a 30 deg azimuth, 20 deg elevation view.

    Returns the mesh and its object-frame bounding-box diagonal times the camera scale
    (the diagonal to normalise by).
    """
    d = np.load(DATA / f"{name}.npz")
    v = torch.from_numpy(d["vertices"].astype(np.float64))
    f = d["faces"].astype(np.int64)
    R = rotation_from_azimuth_elevation_roll(torch.tensor(math.radians(30.0), dtype=torch.float64),
                                             torch.tensor(math.radians(20.0), dtype=torch.float64),
                                             torch.tensor(0.0, dtype=torch.float64))
    diag = float((v.amax(0) - v.amin(0)).norm())
    s = 0.8 * canvas / diag
    cam = ScaledOrthographic(R[None], torch.tensor([s], dtype=torch.float64),
                             torch.tensor([[canvas / 2, canvas / 2]], dtype=torch.float64))
    xyz = cam.to_camera_frame(v)[0].numpy()
    return trimesh.Trimesh(xyz, f, process=False), s * diag


def voxel_recon(gt: trimesh.Trimesh, resolution: int = 60, seed: int = 0) -> trimesh.Trimesh:
    """Marching-cubes mesh of a ``resolution``-voxel solid voxelisation, jittered and shifted in depth."""
    lo, hi = gt.bounds
    pitch = float((hi - lo).max()) / resolution
    origin = torch.tensor(lo - 2 * pitch)
    size = np.ceil((hi - lo) / pitch).astype(int) + 5  # (x, y, z)
    v = torch.from_numpy(np.asarray(gt.vertices))
    occ = voxelize_solid(v, torch.from_numpy(np.asarray(gt.faces)), pitch, origin, (size[2], size[1], size[0]))
    verts, faces, _, _ = measure.marching_cubes(np.pad(occ.numpy(), 1).astype(np.float32), 0.5)
    xyz = (verts[:, ::-1] - 1.0) * pitch + origin.numpy()  # (d, h, w) index -> (x, y, z)
    rng = np.random.default_rng(seed)
    xyz = xyz + rng.normal(0.0, 0.25 * pitch, xyz.shape) + np.array([0.0, 0.0, 7.0])
    return trimesh.Trimesh(xyz, faces[:, ::-1], process=False)  # reversed index order: keep outward faces


def timed(fn, repeats: int) -> tuple[float, float, object]:
    """Median wall time, minimum process CPU time (s) and the last result of ``fn()``."""
    walls, cpus = [], []
    out = None
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), min(cpus), out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", default=["aeroplane01", "aeroplane02"])
    ap.add_argument("--steps", nargs="+", type=float, default=[0.005, 0.0075, 0.01, 0.02],
                    help="sampling steps as fractions of the GT diagonal")
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scan-step", type=float, default=0.01,
                    help="sampling step (fraction of the diagonal) of the depth-search check")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "metrics.json"))
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"no CAD models at {DATA}; this benchmark needs ../shared/data", file=sys.stderr)
        return 2

    rows, dist_rows = [], []
    header = f"{'model':<12}{'faces':>7}{'recon':>7}{'step%':>7}{'thr':>4}{'samples':>9}{'cold s':>8}{'warm s':>8}" \
             f"{'warm cpu':>9}{'err %':>8}{'evals':>6}"
    print(header)
    for name in args.models:
        gt_mesh, diag = camera_frame_gt(name)
        recon = voxel_recon(gt_mesh)
        for threads in args.threads:
            torch.set_num_threads(threads)
            # exact distances of ~100k points near the surface
            V = torch.from_numpy(np.asarray(gt_mesh.vertices)).float()
            F = torch.from_numpy(np.asarray(gt_mesh.faces))
            pts, _ = sample_surface(V, F, 0.0024 * diag)
            g = torch.Generator().manual_seed(0)
            pts = pts + 0.01 * diag * torch.randn(pts.shape, generator=g)
            build_wall, build_cpu, index = timed(lambda: MeshDistanceIndex(V, F), args.repeats)
            q_wall, q_cpu, _ = timed(lambda: index.distance(pts), args.repeats)
            dist_rows.append({"model": name, "faces": len(gt_mesh.faces), "points": int(pts.shape[0]),
                              "threads": threads, "build_wall_s": build_wall, "build_cpu_s": build_cpu,
                              "query_wall_s": q_wall, "query_cpu_s": q_cpu,
                              "pairs_per_point": index.last_pairs / pts.shape[0]})
            for frac in args.steps:
                step = frac * diag
                cold_wall, cold_cpu, res = timed(
                    lambda: evaluate_reconstruction(recon, gt_mesh, step=step, diag=diag), args.repeats)
                gt = EvaluationMesh(gt_mesh, name="gt")
                gt.index, gt.samples(step), gt.samples(3 * step)  # built once per GT view
                warm_wall, warm_cpu, res = timed(
                    lambda: evaluate_reconstruction(recon, gt, step=step, diag=diag), args.repeats)
                n_gt = int(gt.samples(step)[0].shape[0])
                n_rec = int(sample_surface(torch.from_numpy(np.asarray(recon.vertices)).float(),
                                           torch.from_numpy(np.asarray(recon.faces)), step)[0].shape[0])
                row = {"model": name, "faces": len(gt_mesh.faces), "recon_faces": len(recon.faces),
                       "step_fraction": frac, "threads": threads, "samples_gt": n_gt, "samples_recon": n_rec,
                       "cold_wall_s": cold_wall, "cold_cpu_s": cold_cpu, "warm_wall_s": warm_wall,
                       "warm_cpu_s": warm_cpu, "error_percent": res["error_percent"], "offset": res["offset"],
                       "evaluations": res["evaluations"]}
                rows.append(row)
                print(f"{name:<12}{row['faces']:>7}{row['recon_faces']:>7}{100 * frac:>7.2f}{threads:>4}"
                      f"{n_gt + n_rec:>9}{cold_wall:>8.3f}{warm_wall:>8.3f}{warm_cpu:>9.3f}"
                      f"{res['error_percent']:>8.3f}{res['evaluations']:>6}")
    # quality of the depth search: its error against the best of a dense scan of exact evaluations
    scans = []
    torch.set_num_threads(args.threads[0])
    for name in args.models:
        gt_mesh, diag = camera_frame_gt(name)
        recon = voxel_recon(gt_mesh)
        gt, rec = EvaluationMesh(gt_mesh, name="gt"), EvaluationMesh(recon, name="recon")
        step = args.scan_step * diag
        res = evaluate_reconstruction(rec, gt, step=step, diag=diag)
        zs = res["offset"] + np.linspace(-0.03, 0.03, 61) * diag
        scan = [max(rms_distance(rec, gt, step, shift=[0, 0, z]), rms_distance(gt, rec, step, shift=[0, 0, -z]))
                for z in zs]
        best = int(np.argmin(scan))
        scans.append({"model": name, "step_fraction": args.scan_step, "search_error_percent": res["error_percent"],
                      "scan_best_error_percent": 100 * scan[best] / diag, "search_offset": res["offset"],
                      "scan_best_offset": float(zs[best]), "scan_spacing": float(zs[1] - zs[0]),
                      "search_evaluations": res["evaluations"]})
        print(f"{name}: search {res['error_percent']:.4f}% at z={res['offset']:.3f} ({res['evaluations']} evaluations), "
              f"dense scan best {100 * scan[best] / diag:.4f}% at z={zs[best]:.3f}")
    print()
    print(f"{'model':<12}{'faces':>7}{'points':>8}{'thr':>4}{'build s':>9}{'query s':>9}{'pairs/pt':>9}")
    for r in dist_rows:
        print(f"{r['model']:<12}{r['faces']:>7}{r['points']:>8}{r['threads']:>4}{r['build_wall_s']:>9.3f}"
              f"{r['query_wall_s']:>9.3f}{r['pairs_per_point']:>9.1f}")
    write_json(args.out, {
        "command": "python tools/bench_metrics.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                    "torch": torch.__version__},
        "note": "wall = median of repeats, cpu = minimum process time of repeats (the machine is shared); "
                "cold = GT index and samples built in the call, warm = GT wrapped once in an EvaluationMesh",
        "evaluate_reconstruction": rows,
        "point_to_mesh_distance": dist_rows,
        "depth_search_vs_dense_scan": scans,
    })
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
