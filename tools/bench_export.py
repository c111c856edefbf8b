"""Benchmark the training export and the dataset reader.

    python tools/bench_export.py [--objects 1000] [--recon DIR] [--work outputs/bench_export]
                                 [--out docs/data/export.json]

Without ``--recon`` it first reconstructs an embedded procedural collection of ``--objects``
objects (equal parts of the four classes; default settings, 60^3 grid, 20 proposals) — that
part is not timed here (see tools/benchmark.py). Then it times, as separate processes:
``python -m carvi_torch.export`` (whole process: objects per second, peak memory) and reading
every sample, all fields, with ``LiftedDataset`` on one worker (samples per second), and a
``DataLoader`` with 2 workers. Prints a table and writes ``--out`` (default ``docs/data/export.json``,
docs/export.md).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

READER = r"""
import json, resource, sys, time
import torch
from torch.utils.data import DataLoader
from carvi_torch.training import LiftedDataset, collate_lifted
root, workers = sys.argv[1], int(sys.argv[2])
ds = LiftedDataset(root)
t = time.perf_counter()
if workers == 0:
    for i in range(len(ds)):
        ds[i]
else:
    for b in DataLoader(ds, batch_size=64, num_workers=workers, collate_fn=collate_lifted):
        pass
dt = time.perf_counter() - t
print(json.dumps({"samples": len(ds), "seconds": dt,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _timed(cmd: list[str]) -> tuple[float, float, str]:
    t = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    dt = time.perf_counter() - t
    if res.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{res.stderr[-2000:]}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return dt, peak, res.stdout


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", type=int, default=1000)
    ap.add_argument("--recon", help="existing reconstruction directory (default: build one)")
    ap.add_argument("--work", default=str(ROOT / "outputs" / "bench_export"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "data" / "export.json"), help="JSON record")
    args = ap.parse_args(argv)
    work = Path(args.work)
    py = sys.executable
    if args.recon:
        recon = Path(args.recon)
    else:
        recon = work / f"recon_{args.objects}"
        per = max(1, args.objects // 4)
        if not (recon / "summary.json").is_file():
            print(f"reconstructing {4 * per} procedural objects into {recon} (not timed) ...")
            subprocess.run([py, "-m", "carvi_torch.reconstruct", "--out", str(recon),
                            f"input.procedural_instances={per}",
                            "progress=false", "preview=false", "report=false"],
                           cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    exp = work / "export"
    if exp.exists():
        import shutil

        shutil.rmtree(exp)
    t_exp, peak_exp, _ = _timed([py, "-m", "carvi_torch.export", "--recon", str(recon), "--out", str(exp)])
    index = json.loads((exp / "index.json").read_text())
    n = len(index["samples"])
    reads = {}
    for w in (0, 2):
        _, _, out = _timed([py, "-c", READER, str(exp), str(w)])
        reads[w] = json.loads(out.strip().splitlines()[-1])
    size_mb = sum(f.stat().st_size for f in exp.rglob("*") if f.is_file()) / 2 ** 20
    rows = [
        ("export (whole process)", f"{n} objects", f"{t_exp:.1f} s", f"{n / t_exp:.1f} objects/s",
         f"{peak_exp:.0f} MB"),
        ("read, 1 worker, all fields", f"{reads[0]['samples']} samples", f"{reads[0]['seconds']:.2f} s",
         f"{reads[0]['samples'] / reads[0]['seconds']:.0f} samples/s", f"{reads[0]['peak_rss_mb']:.0f} MB"),
        ("DataLoader, 2 workers, batch 64", f"{reads[2]['samples']} samples", f"{reads[2]['seconds']:.2f} s",
         f"{reads[2]['samples'] / reads[2]['seconds']:.0f} samples/s", f"{reads[2]['peak_rss_mb']:.0f} MB"),
    ]
    head = ("what", "size", "wall", "rate", "peak memory")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(5)]
    for r in [head] + rows:
        print("  ".join(v.ljust(widths[i]) for i, v in enumerate(r)))
    print(f"export size on disk: {size_mb:.0f} MB; threads {os.cpu_count()} cores; load {os.getloadavg()[0]:.1f}")
    from carvi_torch.io.outputs import write_json

    write_json(args.out, {
        "command": "python tools/bench_export.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:])),
        "objects": n, "export_seconds": round(t_exp, 2), "export_objects_per_second": round(n / t_exp, 2),
        "export_peak_rss_mb": round(peak_exp), "read_samples_per_second_1_worker":
        round(reads[0]["samples"] / reads[0]["seconds"]), "dataloader_samples_per_second_2_workers":
        round(reads[2]["samples"] / reads[2]["seconds"]), "size_mb": round(size_mb), "load_average":
        round(os.getloadavg()[0], 2), "cpus": os.cpu_count()})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
