"""Benchmark the training export (zarr store) and the dataset reader, or (``--report``) the HTML report.

    python tools/bench_export.py [--objects 1000] [--recon DIR] [--work outputs/bench_export]
                                 [--workers N] [--out PATH [--key KEY]]
    python tools/bench_export.py --report [--objects 160] [--recon DIR] [--out PATH [--key KEY]]
    python tools/bench_export.py --recon DIR --compare-with OTHER_TREE [--rounds 3] [--out PATH [--key KEY]]
    python tools/bench_export.py --quality EVAL_DIR [EVAL_DIR ...] [--method NAME] [--out PATH [--key KEY]]

Without ``--recon`` it first reconstructs an embedded procedural collection of ``--objects``
objects (equal parts of the four classes; default settings, 60^3 grid, 20 proposals) — that
part is not timed here (see tools/benchmark.py). Then it times, as separate processes:
``python -m carvi_torch.export`` (whole process, start-up included: objects per second, peak
memory of the process tree, bytes per object on disk, per field too), reading every sample with
``LiftedDataset`` on one worker (all fields, and three fields), and a ``DataLoader`` with 2
workers. Prints a table and writes ``--out`` (under ``--key`` when given, the file's other keys kept);
``--key`` without ``--out``: that key of ``docs/data/export.json``, the records of docs/export.md (the
commands the page gives name their key); neither: key ``export`` of ``outputs/export.json``, so that a plain
run leaves the committed records alone. The other modes' default keys below go the same way.

With ``--quality EVAL_DIR ...`` it times nothing: it ranks the true shape errors of ``evaluate`` runs
by the objects' ``quality`` (Spearman rho, pooled and per class, each signal alone, ``quality``
recombined without each factor; default record: key ``quality_shape_cad``).

With ``--compare-with`` it times the export of this tree's code and of another source tree's (say a
``git worktree`` or ``git archive`` of an earlier commit) back to back, alternating which goes first,
``--rounds`` times each; prints both rates, CPU times and their ratios, and whether the two stores hold
the same arrays (default record: key ``export_compare``).

With ``--report`` it times ``python -m carvi_torch.report`` instead (whole process), once with the
cards made in the report's own process and once in 2 worker processes: objects per
second, CPU time and peak memory of the report process (its workers are the forkserver's children:
neither is counted), and bytes per object (overlay and mesh data; the shared assets apart). Default
record: key ``report_<objects>`` of ``outputs/report.json`` (with ``--key`` alone: of ``docs/data/report.json``,
docs/report.md's records).
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from carvi_torch.runtime import child_pythonpath, cpu_seconds

ROOT = Path(__file__).resolve().parents[1]

READER = r"""
import json, sys, time
import torch
torch.set_num_threads(1)
from torch.utils.data import DataLoader
from carvi_torch.runtime import peak_rss_mb
from carvi_torch.training import LiftedDataset, collate_lifted
root, workers, fields = sys.argv[1], int(sys.argv[2]), (sys.argv[3].split(",") if sys.argv[3] else None)
ds = LiftedDataset(root, fields=fields)
t = time.perf_counter()
if workers == 0:
    for i in range(len(ds)):
        ds[i]
else:
    for b in DataLoader(ds, batch_size=64, num_workers=workers, collate_fn=collate_lifted):
        pass
dt = time.perf_counter() - t
print(json.dumps({"samples": len(ds), "seconds": dt, "peak_rss_mb": peak_rss_mb()}))
"""


def _tree_rss_mb(pid: int, cpu: dict | None = None) -> float | None:
    """Resident memory (MB) of ``pid`` and all its descendants (Linux /proc; None elsewhere); ``cpu`` gets
    each process's CPU seconds so far (user + system), by pid."""
    proc = Path("/proc")
    if not proc.is_dir():
        return None
    parent, rss, ticks = {}, {}, {}
    for d in proc.iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            fields = stat[stat.rindex(")") + 2:].split()
            parent[int(d.name)] = int(fields[1])
            rss[int(d.name)] = int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
            ticks[int(d.name)] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError):
            continue
    tree, frontier = {pid}, [pid]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parent.items() if pp == p and c not in tree]
        tree.update(kids)
        frontier.extend(kids)
    if cpu is not None:
        for p in tree:
            cpu[p] = max(cpu.get(p, 0.0), ticks.get(p, 0.0))
    return sum(rss.get(p, 0) for p in tree) / 2 ** 20


def _timed(cmd: list[str], cpu: dict | None = None, code: Path = ROOT, pids: list | None = None
           ) -> tuple[float, float | None, str]:
    """Wall seconds, peak memory of the process tree (sampled every 50 ms), stdout; ``cpu``: CPU seconds
    per process of the tree (as last sampled). ``code``: the source tree whose ``carvi_torch`` runs
    (working directory and ``PYTHONPATH``); ``pids`` gets the process id of ``cmd``."""
    env = {**os.environ, "PYTHONPATH": child_pythonpath(code)}
    t = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=code, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if pids is not None:
        pids.append(p.pid)
    peak = [0.0]

    def watch():
        while p.poll() is None:
            m = _tree_rss_mb(p.pid, cpu)
            if m is not None:
                peak[0] = max(peak[0], m)
            time.sleep(0.05)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    out, err = p.communicate()
    dt = time.perf_counter() - t
    th.join()
    if p.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{err[-2000:]}")
    return dt, (peak[0] or None), out


def _sizes(store: Path) -> dict[str, int]:
    """Bytes on disk per field (summed over classes) and in metadata."""
    out: dict[str, int] = {}
    for f in store.rglob("*"):
        if f.is_file():
            rel = f.relative_to(store).parts
            key = rel[1] if len(rel) > 2 else "metadata"
            out[key] = out.get(key, 0) + f.stat().st_size
    return out


def _reconstruct(py: str, work: Path, objects: int) -> Path:
    recon = work / f"recon_{objects}"
    per = max(1, objects // 4)
    if not (recon / "summary.json").is_file():
        print(f"reconstructing {4 * per} procedural objects into {recon} (not timed) ...")
        subprocess.run([py, "-m", "carvi_torch.reconstruct", "--out", str(recon), f"input.procedural_instances={per}",
                        "progress=false", "preview=false", "report=false"],
                       cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return recon


def time_export(py: str, recon: Path, exp: Path, workers: int | None, code: Path = ROOT) -> dict:
    """One export of ``recon`` into ``exp`` (replaced) as a whole process, with the ``carvi_torch`` of ``code``:
    wall and CPU seconds (user + system of every process of its tree, start-up included), peak memory."""
    if exp.exists():
        import shutil

        shutil.rmtree(exp)
    cmd = [py, "-m", "carvi_torch.export", "--recon", str(recon.resolve()), "--out", str(exp.resolve()), "--quiet"]
    cmd += ["--workers", str(workers)] if workers is not None else []
    cpu: dict = {}
    load = os.getloadavg()[0]
    pids: list = []
    t, peak, _ = _timed(cmd, cpu, code, pids)
    main_cpu = cpu.pop(pids[0], 0.0)
    import zarr

    n = sum(zarr.open_group(str(exp), mode="r").attrs["carvi_export"]["counts"].values())
    c = main_cpu + sum(cpu.values())
    return {"code": str(code), "objects": n, "seconds": round(t, 2), "objects_per_second": round(n / t, 2),
            "cpu_seconds": round(c, 2), "cpu_ms_per_object": round(1000 * c / max(n, 1), 2),
            "cpu_seconds_main_process": round(main_cpu, 2),
            "peak_tree_rss_mb": round(peak) if peak else None, "load_average_before": round(load, 2)}


def same_stores(a: Path, b: Path) -> dict[str, str]:
    """Every array of every class group of two exports compared: field -> ``identical`` (same shape,
    dtype and values, NaN equal to NaN) or what differs; class groups' attributes and the root's
    (but its ``seconds`` and ``recon``) under ``attributes``."""
    import numpy as np
    import zarr

    ra, rb = zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r")
    drop = ("seconds", "recon")
    attrs = [{k: v for k, v in r.attrs["carvi_export"].items() if k not in drop} for r in (ra, rb)]
    out: dict[str, str] = {"attributes": "identical" if attrs[0] == attrs[1] else "differ"}
    for cls in attrs[0]["classes"]:
        if dict(ra[cls].attrs) != dict(rb[cls].attrs):
            out["attributes"] = f"differ ({cls})"
        for name in sorted(set(ra[cls].array_keys()) | set(rb[cls].array_keys())):
            if name not in ra[cls] or name not in rb[cls]:
                out[name] = f"missing in one store ({cls})"
                continue
            x, y = ra[cls][name][...], rb[cls][name][...]
            if x.shape != y.shape or x.dtype != y.dtype:
                out[name] = f"{cls}: {x.shape} {x.dtype} against {y.shape} {y.dtype}"
            elif not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
                fin = np.isfinite(x) & np.isfinite(y) if x.dtype.kind == "f" else np.ones(x.shape, bool)
                diff = np.abs(x[fin].astype(np.float64) - y[fin].astype(np.float64))
                out[name] = (f"{cls}: {int((x != y).sum())} of {x.size} values differ, largest by "
                             f"{diff.max() if diff.size else float('nan'):.3g}")
            else:
                out.setdefault(name, "identical")
    return out


def compare_exports(py: str, recon: Path, work: Path, args, argv) -> int:
    """The export with this tree's code and with ``--compare-with``'s, alternating, ``--rounds`` times each
    (back to back, so both see the same load); prints each round, the ratios and whether the stores agree."""
    other = Path(args.compare_with).resolve()
    runs: dict[str, list] = {"new": [], "old": []}
    for r in range(max(1, args.rounds)):
        order = [("new", ROOT), ("old", other)]
        for name, code in order if r % 2 == 0 else order[::-1]:
            runs[name].append(time_export(py, recon, work / f"export_{name}", args.workers, code))
            x = runs[name][-1]
            print(f"round {r + 1} {name}: {x['objects']} objects, {x['seconds']:.1f} s, "
                  f"{x['objects_per_second']:.1f} objects/s, CPU {x['cpu_ms_per_object']:.1f} ms/object "
                  f"(main process {x['cpu_seconds_main_process']:.1f} s of {x['cpu_seconds']:.1f} s; load "
                  f"{x['load_average_before']:.1f})", flush=True)
    med = {k: {q: statistics.median(x[q] for x in v) for q in ("seconds", "cpu_seconds", "objects_per_second",
                                                              "cpu_ms_per_object")} for k, v in runs.items()}
    ratio = {"objects_per_second": med["new"]["objects_per_second"] / med["old"]["objects_per_second"],
             "cpu_seconds": med["new"]["cpu_seconds"] / med["old"]["cpu_seconds"],
             "per_round_objects_per_second": [n["objects_per_second"] / o["objects_per_second"]
                                              for n, o in zip(runs["new"], runs["old"])]}
    same = same_stores(work / "export_new", work / "export_old")
    print(f"median of {len(runs['new'])} rounds: new {med['new']['objects_per_second']:.1f} objects/s, "
          f"{med['new']['cpu_ms_per_object']:.1f} ms CPU/object; old {med['old']['objects_per_second']:.1f} "
          f"objects/s, {med['old']['cpu_ms_per_object']:.1f} ms CPU/object; new/old rate "
          f"{ratio['objects_per_second']:.2f}x, CPU {ratio['cpu_seconds']:.2f}x")
    differ = [f"{k} {v}" for k, v in same.items() if v != "identical"]
    print("stores: " + (", ".join(differ) if differ else "every field and attribute identical"))
    from carvi_torch.io.outputs import write_record

    write_record(args.out, {"command": "python tools/bench_export.py " + " ".join(shlex.quote(a) for a in argv),
                            "cpus": os.cpu_count(), "runs": runs, "median": med, "new_over_old": ratio,
                            "stores": same}, args.key)
    print(f"wrote {args.out}" + (f", key {args.key}" if args.key else ""))
    return 0


def _quality_rows(res: dict, method: str) -> list[dict]:
    """Per object with a quality and a shape error: class, shape error (%), quality and its signals."""
    from carvi_torch.io.outputs import read_json

    recon, rows, cams = Path(res["recons"][method]), [], {}
    if not recon.is_dir():  # evaluate records the --recon it was given, relative to where it ran
        raise SystemExit(f"{recon}: no such reconstruction folder (run from the folder evaluate ran in)")
    for aid, obj in res["objects"].items():
        err = (obj.get(method) or {}).get("error_percent") if isinstance(obj.get(method), dict) else None
        cls = obj["class"]
        if cls not in cams:
            p = recon / cls / "cameras.json"
            cams[cls] = read_json(p).get("cameras", {}) if p.is_file() else {}
        entry = cams[cls].get(aid) or {}
        if err is None or entry.get("quality") is None:
            continue
        rows.append({"class": cls, "shape_percent": float(err), "quality": float(entry["quality"]),
                     "signals": entry.get("quality_signals") or {}})
    return rows


def quality_study(eval_dirs: list[Path], method: str | None, out: str, key: str, argv) -> int:
    """Spearman rho of ``quality`` against the true shape error (symmetric RMS, % of the ground-truth
    diagonal) of ``evaluate`` runs without ``--viewpoints-only`` (their ``results.json`` in ``eval_dirs``,
    say one per group of classes, their objects pooled): pooled and per class; each signal alone;
    ``quality`` recombined without each of its factors (which term helps or hurts the ranking of shape
    errors); prints a table, writes the record."""
    import numpy as np

    from carvi_torch.evaluation.reliability import spearman
    from carvi_torch.io.outputs import read_json, write_record
    from carvi_torch.quality import combine

    rows, steps = [], set()
    for d in eval_dirs:
        res = read_json(d / "results.json")
        method = method or next(iter(res["recons"]))
        rows += _quality_rows(res, method)
        steps.add(res["step_percent"])
    if not rows:
        raise SystemExit(f"{eval_dirs}: no object has both a quality and a shape error (run evaluate without "
                         "--viewpoints-only on a reconstruction that wrote quality)")
    err = np.array([r["shape_percent"] for r in rows])
    classes = np.array([r["class"] for r in rows])
    numeric = ("keypoint_residual", "visible_keypoints", "refinement_deg", "mirror_deg", "reconstruction_iou",
               "silhouette_inside")
    keys = sorted({k for r in rows for k in r["signals"]})

    def rho(x, sel=slice(None)):
        return spearman(np.asarray(x, dtype=np.float64)[sel], err[sel])

    record = {"eval": [str(d) for d in eval_dirs], "step_percent": sorted(steps), "method": method,
              "objects": len(rows),
              "pooled": rho([r["quality"] for r in rows]),
              "recombined": rho([combine(r["signals"]) for r in rows]),  # = pooled (quality is combine's)
              "per_class": {c: rho([r["quality"] for r in rows], classes == c) for c in sorted(set(classes))},
              "signal_alone": {k: rho([float(r["signals"][k]) if r["signals"].get(k) is not None else np.nan
                                       for r in rows]) for k in numeric if k in keys},
              "factor_alone": {k: rho([combine({k: r["signals"][k]}) if k in r["signals"] else np.nan
                                       for r in rows]) for k in keys},
              "without_factor": {k: rho([combine({j: v for j, v in r["signals"].items() if j != k})
                                         for r in rows]) for k in keys}}
    hi = np.array([r["quality"] for r in rows]) >= np.median([r["quality"] for r in rows])
    record["median_shape_percent_top_bottom_half"] = [round(float(np.median(err[hi])), 3),
                                                      round(float(np.median(err[~hi])), 3)]
    record["command"] = "python tools/bench_export.py " + " ".join(shlex.quote(a) for a in argv)
    f = lambda d: "n/a" if d["rho"] is None else f"{d['rho']:+.2f}"  # noqa: E731
    print(f"{method}: {len(rows)} objects; rho(quality, shape error) pooled {f(record['pooled'])}; "
          f"median shape error top / bottom half of quality {record['median_shape_percent_top_bottom_half']}")
    print("per class: " + ", ".join(f"{c} {f(v)} (n={v['n']})" for c, v in record["per_class"].items()))
    print("signal alone: " + ", ".join(f"{k} {f(v)}" for k, v in record["signal_alone"].items()))
    print("factor alone: " + ", ".join(f"{k} {f(v)}" for k, v in record["factor_alone"].items()))
    print("quality without the factor: " + ", ".join(f"{k} {f(v)}" for k, v in record["without_factor"].items()))
    write_record(out, record, key)
    print(f"wrote {out}, key {key}")
    return 0


REPORT = r"""
import json, sys, time
t = time.perf_counter()
from carvi_torch.report import build_report
from carvi_torch.runtime import peak_rss_mb
r = build_report(sys.argv[1], sys.argv[2], workers=int(sys.argv[3]))
print(json.dumps({"cards": r.cards, "seconds_inside": time.perf_counter() - t, "peak_rss_mb": peak_rss_mb()}))
"""


def bench_report(recon: Path, work: Path, out: str, key: str | None, argv) -> int:
    """Time the report of ``recon`` as a whole process, without and with worker processes; print a table."""
    import shutil

    rows, record = [], {"runs": []}
    for workers in ("0", "2"):
        dest = work / f"report_{workers}"
        if dest.exists():
            shutil.rmtree(dest)
        c0, t = cpu_seconds(children=True), time.perf_counter()
        res = subprocess.run([sys.executable, "-c", REPORT, str(recon), str(dest), workers], cwd=ROOT,
                             capture_output=True, text=True)
        dt, cpu = time.perf_counter() - t, cpu_seconds(children=True) - c0  # the report process (not its workers)
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
    from carvi_torch.io.outputs import write_record

    record.update({"command": "python tools/bench_export.py " + " ".join(shlex.quote(a) for a in argv),
                   "load_average": round(os.getloadavg()[0], 2), "cpus": os.cpu_count()})
    write_record(out, record, key)
    print(f"wrote {out}" + (f", key {key}" if key else ""))
    return 0


def _record_target(args, name: str, default_key: str) -> tuple[Path, str | None]:
    """``--out`` (under ``--key``); ``--key`` alone: that key of ``docs/data/<name>``; neither: ``default_key`` of
    ``outputs/<name>`` (:func:`carvi_torch.io.outputs.record_target`)."""
    from carvi_torch.io.outputs import record_target

    return record_target(args.out, args.key, ROOT / "docs" / "data" / name, default_key, ROOT / "outputs" / name)


def build_parser() -> argparse.ArgumentParser:
    """The command line (the module docstring is its help)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", type=int, help="objects to reconstruct without --recon (default 1000; --report 160)")
    ap.add_argument("--recon", help="existing reconstruction directory (default: build one)")
    ap.add_argument("--work", default=str(ROOT / "outputs" / "bench_export"))
    ap.add_argument("--workers", type=int, default=None, help="export worker processes (default: its own)")
    ap.add_argument("--out", help="JSON record (default outputs/export.json, with --report outputs/report.json; "
                                  "with --key alone docs/data/export.json or docs/data/report.json, the pages' "
                                  "records)")
    ap.add_argument("--key", help="write the record under this key of --out's JSON object, its other keys kept "
                                  "(default with no --out: export; with --report report_<objects>)")
    ap.add_argument("--report", action="store_true", help="benchmark the HTML report instead of the export")
    ap.add_argument("--compare-with", metavar="DIR",
                    help="a source tree holding another carvi_torch (e.g. a checkout of an earlier commit): time "
                         "its export and this tree's back to back, alternating, and compare the stores "
                         "(the reader is not timed)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of each code with --compare-with (default 3)")
    ap.add_argument("--quality", metavar="EVAL_DIR", nargs="+",
                    help="instead of timing: rank the true shape errors of an evaluate run (its --out, without "
                         "--viewpoints-only) by quality: Spearman rho pooled, per class, per signal and with each "
                         "factor left out (default record: key quality_shape_cad)")
    ap.add_argument("--method", help="with --quality: the evaluated method (default: the first)")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)
    if args.quality:
        out, key = _record_target(args, "export.json", "quality_shape_cad")
        return quality_study([Path(d) for d in args.quality], args.method, str(out), key, argv)
    args.objects = args.objects or (160 if args.report else 1000)
    out, args.key = _record_target(args, "report.json" if args.report else "export.json",
                                   f"report_{args.objects}" if args.report else
                                   "export_compare" if args.compare_with else "export")
    args.out = str(out)
    work, py = Path(args.work), sys.executable
    recon = Path(args.recon) if args.recon else _reconstruct(py, work, args.objects)
    if args.report:
        return bench_report(recon, work, args.out, args.key, argv)
    if args.compare_with:
        return compare_exports(py, recon, work, args, argv)
    return bench_export(py, recon, work, args, argv)


def bench_export(py: str, recon: Path, work: Path, args, argv) -> int:
    """Time the export of ``recon`` and three reads of its store; print the table, write the record."""
    exp = work / "export"
    load0 = os.getloadavg()[0]
    run = time_export(py, recon, exp, args.workers)
    reads = {}
    for name, w, fields in (("all", 0, ""), ("three", 0, "mask,viewpoint,occupancy_canonical"), ("loader", 2, "")):
        _, _, out = _timed([py, "-c", READER, str(exp), str(w), fields])
        reads[name] = json.loads(out.strip().splitlines()[-1])
    sizes = _sizes(exp)
    _print_export(run, reads, sizes, load0)
    from carvi_torch.io.outputs import write_record

    write_record(args.out, _export_record(run, reads, sizes, load0, argv), args.key)
    print(f"wrote {args.out}" + (f", key {args.key}" if args.key else ""))
    return 0


def _print_export(run: dict, reads: dict, sizes: dict, load0: float) -> None:
    """The export's and the reads' table, bytes per object by field, CPU time, cores and load."""
    t_exp, peak_exp, cpu_s, n = run["seconds"], run["peak_tree_rss_mb"], run["cpu_seconds"], run["objects"]
    per_obj = sum(sizes.values()) / max(n, 1)

    def mb(v):
        return f"{v:.0f} MB" if v else "n/a"

    rows = [("export (whole process)", f"{n} objects", f"{t_exp:.1f} s", f"{n / t_exp:.1f} objects/s",
             mb(peak_exp), f"{per_obj / 1024:.1f} KB/object")]
    for name, what in (("all", "read, 1 worker, all fields"), ("three", "read, 1 worker, 3 fields"),
                       ("loader", "DataLoader, 2 workers, batch 64, all fields")):
        r = reads[name]
        rows.append((what, f"{r['samples']} samples", f"{r['seconds']:.2f} s",
                     f"{r['samples'] / r['seconds']:.0f} samples/s", mb(r["peak_rss_mb"]), ""))
    head = ("what", "size", "wall", "rate", "peak memory", "on disk")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
    for r in [head] + rows:
        print("  ".join(v.ljust(widths[i]) for i, v in enumerate(r)))
    print("bytes per object by field: " + ", ".join(f"{k} {v / max(n, 1):.0f}" for k, v in
                                                    sorted(sizes.items(), key=lambda kv: -kv[1])))
    print(f"export CPU time (process tree, user + system): {cpu_s:.1f} s = {1000 * cpu_s / max(n, 1):.1f} ms/object, "
          f"so at most {2 * n / cpu_s:.0f} objects/s on 2 idle cores (start-up included)")
    print(f"{os.cpu_count()} cores; load average {load0:.1f} before the export, {os.getloadavg()[0]:.1f} after")


def _export_record(run: dict, reads: dict, sizes: dict, load0: float, argv) -> dict:
    """The JSON record of an export benchmark (rates rounded; the load average now is the one after)."""
    t_exp, peak_exp, cpu_s, n = run["seconds"], run["peak_tree_rss_mb"], run["cpu_seconds"], run["objects"]
    per_obj = sum(sizes.values()) / max(n, 1)
    return {
        "command": "python tools/bench_export.py " + " ".join(shlex.quote(a) for a in argv),
        "objects": n, "export_seconds": round(t_exp, 2), "export_objects_per_second": round(n / t_exp, 2),
        "export_peak_tree_rss_mb": round(peak_exp) if peak_exp else None,
        "export_cpu_seconds": round(cpu_s, 2), "export_cpu_ms_per_object": round(1000 * cpu_s / max(n, 1), 2),
        "export_cpu_seconds_main_process": run["cpu_seconds_main_process"],
        "bytes_per_object": round(per_obj), "bytes_per_object_by_field": {k: round(v / max(n, 1)) for k, v in
                                                                          sorted(sizes.items())},
        "read_samples_per_second_1_worker_all_fields": round(reads["all"]["samples"] / reads["all"]["seconds"]),
        "read_samples_per_second_1_worker_3_fields": round(reads["three"]["samples"] / reads["three"]["seconds"]),
        "dataloader_samples_per_second_2_workers": round(reads["loader"]["samples"] / reads["loader"]["seconds"]),
        "load_average_before": round(load0, 2), "load_average_after": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count()}


if __name__ == "__main__":
    sys.exit(main())
