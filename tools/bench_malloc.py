"""Page faults and time of the carving with glibc's malloc thresholds adaptive (its default) or fixed high.

A measured idea, not kept in the package (docs/benchmarks/README.md, "Page faults"). glibc hands
freed memory back to the kernel when a block exceeds its mmap threshold or free memory at the top
of the heap exceeds its trim threshold; both thresholds adapt to what the process freed before.
Memory handed back costs a minor page fault per 4 KiB page at its next use. The fixed setting is
``MALLOC_MMAP_THRESHOLD_=32 MiB`` (glibc's largest) and ``MALLOC_TRIM_THRESHOLD_=256 MiB`` in
the child's environment.

Each measurement runs in a fresh child process (every ``MALLOC_*`` variable and ``GLIBC_TUNABLES``
of the caller's environment removed, :data:`FIXED` added for the fixed setting; an allocator
preloaded with ``LD_PRELOAD`` would stay, so do not run the tool under one), alternating the two
settings round by round (the whole-pipeline pairs alternate from one thread count to the next):

* ``carve`` (the class prepared as a run prepares it, same seed, in the child): the proposals of
  the first ``--objects`` references carved as the pipeline calls the carving (one call per
  pipeline chunk of references, each chunk's grids released before the next), once to warm up
  and ``--calls`` more times, with ``--threads`` intra-op threads; minor page faults and wall
  time of those calls, per object.
* ``carve_loaded``: the same, but the child loads the prepared maps and proposals from a file
  (``torch.load``) instead of preparing them: a process that has freed no large block before the
  carving, as a short script may be.
* ``e2e`` (``--e2e``): the whole pipeline (:func:`carvi_torch.pipeline.run`, the class of
  ``--data``, one writer process), per ``--e2e-threads``: wall time, minor page faults and peak
  memory of the main process and of the writer.

Labels are not compared: where freed memory goes changes no value.

    python tools/bench_malloc.py --data outputs/bench/data/car1000_s0/annotations.json \\
        --threads 2 --rounds 3 --e2e --e2e-threads 1 2 --out docs/benchmarks/malloc.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from carvi_torch import pipeline  # noqa: E402
from carvi_torch import carve as C  # noqa: E402
from carvi_torch.config import Config  # noqa: E402
from carvi_torch.io.outputs import write_json  # noqa: E402


#: The fixed setting, as glibc reads it from the environment (the mmap threshold at its largest value).
FIXED = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(256 << 20)}
#: The two settings compared, as the JSON names them.
SETTINGS = ("adaptive", "fixed")


def _faults(who=resource.RUSAGE_SELF) -> int:
    """Minor page faults so far of this process (``RUSAGE_SELF``, every thread) or of its waited-for children."""
    return resource.getrusage(who).ru_minflt


def _prepare(args) -> dict:
    """The class prepared as a run prepares it (same seed) and the kept proposals of its first ``--objects``
    references, with the bounds of the pipeline's carving calls (``bench_changes``)."""
    sys.path.insert(0, str(ROOT / "tools"))
    from bench_changes import class_proposals, pipeline_call_bounds

    device = torch.device("cpu")
    ns = argparse.Namespace(data=args.data, category=args.category, objects=args.objects)
    cfg, plan, _, K, ref, views, valid = class_proposals(ns, device)
    return dict(maps=plan.maps, ref=ref, views=views, bounds=pipeline_call_bounds(cfg, valid, K, device), K=K,
                resolution=cfg.resolution, imprint=cfg.imprint)


def _seen() -> dict:
    """The malloc settings this process found in its environment."""
    return {k: os.environ.get(k) for k in FIXED}


def child_carve(args) -> dict:
    """In this (fresh) process: the carving's faults and seconds per object."""
    torch.set_num_threads(args.threads)
    if args.child == "carve_loaded":
        p = torch.load(Path(args.work_dir) / "proposals.pt", weights_only=False)
    else:
        p = _prepare(args)
    bounds, ref, views = p["bounds"], p["ref"], p["views"]

    def run():
        for a, b in zip(bounds[:-1], bounds[1:]):
            grids = C.carve_proposals(p["maps"], None, ref[a:b], views[a:b], resolution=p["resolution"],
                                      imprint=p["imprint"])
            del grids

    run()
    f0, t0 = _faults(), time.perf_counter()
    for _ in range(args.calls):
        run()
    wall, faults = time.perf_counter() - t0, _faults() - f0
    K = p["K"]
    return {"seconds_per_object": wall / (args.calls * K), "faults_per_object": faults / (args.calls * K),
            "objects": K, "calls": args.calls, "threads": torch.get_num_threads(), "environment": _seen()}


def child_e2e(args) -> dict:
    """In this (fresh) process: the whole pipeline (one writer process, forked: its faults are the children's)."""
    out = Path(args.work_dir) / f"e2e_{args.setting}_t{args.threads}"
    cfg = Config().override({"data": args.data, "classes": [args.category], "out": str(out), "overwrite": True,
                             "progress": False, "preview": False})
    f0, t0 = _faults(), time.perf_counter()
    summary = pipeline.run(cfg, workers=1, threads=args.threads)
    wall = time.perf_counter() - t0
    c = summary["classes"][args.category]
    return {"seconds": wall, "objects": c["reconstructed"],
            "faults_main": _faults() - f0, "faults_writer": _faults(resource.RUSAGE_CHILDREN),
            "peak_rss_main_mb": summary["peak_rss_mb"], "peak_rss_writer_mb": summary["peak_rss_workers_mb"],
            "carve_seconds": c["seconds"].get("carve"), "select_seconds": c["seconds"].get("select"),
            "threads": args.threads, "environment": _seen()}


def _child(kind: str, setting: str, threads: int, args) -> dict:
    """Run one measurement in a fresh process: every ``MALLOC_*`` variable and ``GLIBC_TUNABLES`` of this
    environment removed, then :data:`FIXED` added for the fixed setting (an allocator preloaded with
    ``LD_PRELOAD`` would stay: do not run the tool under one)."""
    cmd = [sys.executable, __file__, "--child", kind, "--setting", setting, "--threads", str(threads),
           "--data", args.data, "--category", args.category, "--objects", str(args.objects),
           "--calls", str(args.calls), "--work-dir", args.work_dir]
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    if setting == "fixed":
        env.update(FIXED)
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=args.timeout)
    if res.returncode != 0:
        raise SystemExit(f"child failed ({res.returncode}):\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _paired(rows: list[dict], key: str) -> dict:
    """Each setting's median of ``key`` over rounds, and the median and range of the rounds' adaptive / fixed.

    Example:
        >>> _paired([{"adaptive": {"s": 2.0}, "fixed": {"s": 1.0}}, {"adaptive": {"s": 3.0}, "fixed": {"s": 2.0}},
        ...          {"adaptive": {"s": 1.0}, "fixed": {"s": 1.0}}], "s")["adaptive_over_fixed_median"]
        1.5
    """
    a = [r["adaptive"][key] for r in rows]
    b = [r["fixed"][key] for r in rows]
    ratios = [x / y for x, y in zip(a, b) if y]
    return {"adaptive_median": statistics.median(a), "fixed_median": statistics.median(b),
            "adaptive_over_fixed_median": statistics.median(ratios) if ratios else None,
            "adaptive_over_fixed_min": min(ratios) if ratios else None,
            "adaptive_over_fixed_max": max(ratios) if ratios else None}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="annotations.json of the class")
    ap.add_argument("--category", default="car")
    ap.add_argument("--objects", type=int, default=50, help="references whose proposals are carved")
    ap.add_argument("--threads", type=int, default=2, help="intra-op threads of the carving measurement")
    ap.add_argument("--calls", type=int, default=3, help="timed carvings of those proposals per child")
    ap.add_argument("--rounds", type=int, default=3, help="child processes per setting (alternating)")
    ap.add_argument("--e2e", action="store_true", help="also run the whole pipeline both ways")
    ap.add_argument("--e2e-threads", type=int, nargs="+", default=[1], help="intra-op threads of the e2e runs")
    ap.add_argument("--work-dir", default=str(ROOT / "outputs" / "bench" / "malloc"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "malloc.json"))
    ap.add_argument("--child", choices=("carve", "carve_loaded", "e2e"), help=argparse.SUPPRESS)
    ap.add_argument("--timeout", type=int, default=3600, help="seconds a child process may take")
    ap.add_argument("--setting", choices=SETTINGS, help=argparse.SUPPRESS)
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child_e2e(args) if args.child == "e2e" else child_carve(args)))
        return None

    load = list(os.getloadavg())
    result = {"command": " ".join(["python tools/bench_malloc.py"] + [shlex.quote(a) for a in argv]),
              "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
                          "load_average_at_start": load}}
    Path(args.work_dir).mkdir(parents=True, exist_ok=True)
    torch.save(_prepare(args), Path(args.work_dir) / "proposals.pt")
    for kind in ("carve", "carve_loaded"):
        rows = []
        for r in range(args.rounds):
            order = SETTINGS if r % 2 == 0 else SETTINGS[::-1]
            rows.append({k: _child(kind, k, args.threads, args) for k in order})
            print(f"{kind} round {r + 1}: " + ", ".join(
                f"{k}: {v['seconds_per_object'] * 1000:.1f} ms/object, {v['faults_per_object']:.0f} faults/object"
                for k, v in rows[-1].items()), flush=True)
        result[kind] = {"threads": args.threads, "rounds": rows,
                        "seconds_per_object": _paired(rows, "seconds_per_object"),
                        "faults_per_object": {f"{k}_median": statistics.median(r[k]["faults_per_object"] for r in rows)
                                              for k in SETTINGS}}
    if args.e2e:
        result["e2e"] = {}
        for i, t in enumerate(args.e2e_threads):
            order = SETTINGS if i % 2 == 0 else SETTINGS[::-1]
            runs = {k: _child("e2e", k, t, args) for k in order}
            result["e2e"][str(t)] = {"order": list(order), **runs}
            print(f"e2e, {t} thread(s), in this order: " + ", ".join(
                f"{k}: {v['seconds']:.1f} s, {v['faults_main']} faults (writer {v['faults_writer']}), peak "
                f"{v['peak_rss_main_mb']:.0f} + {v['peak_rss_writer_mb']:.0f} MB" for k, v in runs.items()), flush=True)
    result["machine"]["load_average_at_end"] = list(os.getloadavg())

    print(f"\n| carving, {args.threads} thread(s), fresh process | adaptive (glibc's default) | fixed | "
          f"adaptive / fixed, median [min-max] |\n|---|---:|---:|---|")
    for kind, name in (("carve", "class prepared in the process"), ("carve_loaded", "maps loaded from a file")):
        s, f = result[kind]["seconds_per_object"], result[kind]["faults_per_object"]
        print(f"| {name}: ms per object | {1000 * s['adaptive_median']:.1f} | {1000 * s['fixed_median']:.1f} | "
              f"{s['adaptive_over_fixed_median']:.2f} [{s['adaptive_over_fixed_min']:.2f}-"
              f"{s['adaptive_over_fixed_max']:.2f}] |")
        print(f"| {name}: minor page faults per object | {f['adaptive_median']:.0f} | {f['fixed_median']:.0f} | |")
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
