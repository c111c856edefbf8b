"""Benchmark the training export and the dataset reader, or (``--report``) the HTML report.

    python tools/bench_export.py [--objects 1000] [--recon DIR] [--work outputs/bench_export]
                                 [--out docs/data/export.json]
    python tools/bench_export.py --report [--objects 160] [--recon DIR] [--out docs/data/report.json]

Without ``--recon`` it first reconstructs an embedded procedural collection of ``--objects``
objects (equal parts of the four classes; default settings, 60^3 grid, 20 proposals) — that
part is not timed here (see tools/benchmark.py). Then it times, as separate processes:
``python -m carvi_torch.export`` (whole process: objects per second, peak memory) and reading
every sample, all fields, with ``LiftedDataset`` on one worker (samples per second), and a
``DataLoader`` with 2 workers. Prints a table and writes ``--out`` (default ``docs/data/export.json``,
docs/export.md).

With ``--report`` it times ``python -m carvi_torch.report`` instead (whole process), once with the
cards made in the report's own process and once in 2 worker processes: objects per
second, CPU time and peak memory of the report process (its workers are the forkserver's children:
neither is counted), and bytes per object (overlay and mesh data; the shared assets apart). Default
record ``docs/data/report.json`` (docs/report.md).
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


REPORT = r"""
import json, resource, sys, time
t = time.perf_counter()
from carvi_torch.report import build_report
r = build_report(sys.argv[1], sys.argv[2], workers=int(sys.argv[3]))
print(json.dumps({"cards": r.cards, "seconds_inside": time.perf_counter() - t,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def bench_report(recon: Path, work: Path, out: str, argv) -> int:
    """Time the report of ``recon`` as a whole process, without and with worker processes; print a table."""
    import shutil

    rows, record = [], {"runs": []}
    for workers in ("0", "2"):
        dest = work / f"report_{workers}"
        if dest.exists():
            shutil.rmtree(dest)
        r0, t = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
        res = subprocess.run([sys.executable, "-c", REPORT, str(recon), str(dest), workers], cwd=ROOT,
                             capture_output=True, text=True)
        dt, r1 = time.perf_counter() - t, resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)  # the report process (not its workers)
        if res.returncode != 0:
            raise SystemExit(f"report failed:\n{res.stderr[-2000:]}")
        got = json.loads(res.stdout.strip().splitlines()[-1])
        n = got["cards"]
        per_obj = sum(f.stat().st_size for f in (dest / "objects").rglob("*") if f.is_file()) / max(1, n)
        sizes = {}
        for f in (dest / "objects").rglob("*.*"):
            sizes[(f.parent, f.stem)] = sizes.get((f.parent, f.stem), 0) + f.stat().st_size
        biggest = max(sizes.values(), default=0)
        assets = sum(f.stat().st_size for f in dest.rglob("*") if f.is_file() and "objects" not in f.parts)
        w = int(workers)
        rows.append((f"report, {w} worker processes", f"{n} objects", f"{dt:.1f} s",
                     f"{cpu:.1f} s" + ("" if w == 0 else " + workers'"), f"{n / dt:.1f} objects/s",
                     f"{got['peak_rss_mb']:.0f} MB",
                     f"{per_obj / 1024:.1f} KB (max {biggest / 1024:.1f})"))
        record["runs"].append({"workers": w, "objects": n, "seconds": round(dt, 2), "cpu_seconds_main": round(cpu, 2),
                               "objects_per_second": round(n / dt, 2), "peak_rss_mb": round(got["peak_rss_mb"]),
                               "bytes_per_object": round(per_obj), "max_bytes_per_object": biggest,
                               "shared_bytes": assets})
    head = ("what", "size", "wall", "CPU", "rate (wall)", "peak memory (report process)", "per object")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
    for r in [head] + rows:
        print("  ".join(v.ljust(widths[i]) for i, v in enumerate(r)))
    print(f"shared files (page, assets, class figures): {assets / 1024:.0f} KB; {os.cpu_count()} cores; "
          f"load {os.getloadavg()[0]:.1f}")
    from carvi_torch.io.outputs import write_json

    record.update({"command": "python tools/bench_export.py " + " ".join(shlex.quote(a) for a in argv),
                   "load_average": round(os.getloadavg()[0], 2), "cpus": os.cpu_count()})
    write_json(out, record)
    print(f"wrote {out}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", type=int, help="objects to reconstruct without --recon (default 1000; --report 160)")
    ap.add_argument("--recon", help="existing reconstruction directory (default: build one)")
    ap.add_argument("--work", default=str(ROOT / "outputs" / "bench_export"))
    ap.add_argument("--out", help="JSON record (default docs/data/export.json; with --report docs/data/report.json)")
    ap.add_argument("--report", action="store_true", help="benchmark the HTML report instead of the export")
    args = ap.parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)
    args.objects = args.objects or (160 if args.report else 1000)
    args.out = args.out or str(ROOT / "docs" / "data" / ("report.json" if args.report else "export.json"))
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
    if args.report:
        return bench_report(recon, work, args.out, argv)
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
        "command": "python tools/bench_export.py " + " ".join(shlex.quote(a) for a in argv),
        "objects": n, "export_seconds": round(t_exp, 2), "export_objects_per_second": round(n / t_exp, 2),
        "export_peak_rss_mb": round(peak_exp), "read_samples_per_second_1_worker":
        round(reads[0]["samples"] / reads[0]["seconds"]), "dataloader_samples_per_second_2_workers":
        round(reads[2]["samples"] / reads[2]["seconds"]), "size_mb": round(size_mb), "load_average":
        round(os.getloadavg()[0], 2), "cpus": os.cpu_count()})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
