"""Before / after: each optimised function and the whole pipeline, old revision vs working tree, same run.

The old revision's modules are read with ``git show REV:path`` and imported under a private
name, so both versions run in one process on the same inputs, interleaved (``--repeat``
rounds of old, new), with the same torch threads. Compared (seconds per object of 20
proposals, best of the rounds; ratio = old / new):

* ``carve``: the old ``carve_proposals`` as the old pipeline called it (plain distance maps
  of the whole class, prepared again at every call) vs the new one on maps prepared once
  (:func:`carvi_torch.carve.prepare_maps`); labels compared voxel for voxel;
* ``select``: ``project_proposals`` (old: max_pool3d boundary, batch-wide sub-sampling; new:
  boolean boundary, per-grid sub-sampling, cache-sized chunks), with the number of plane
  samples that differ;
* ``boundary``: the boundary voxels alone (must be identical);
* ``triplets``: ``sample_triplets`` (must be identical) and its peak memory at ``--big`` instances;
* ``pipeline`` (``--pipeline DATA``): ``python -m carvi_torch.reconstruct`` of both revisions on
  the same annotation file, one after the other, each in its own process; then the voxels of
  every object compared file by file.

Inputs for the function comparisons come from the first ``--objects`` references of a class
reconstructed by the pipeline itself (``prepare_class``, same seed as a run). Writes JSON
(``docs/benchmarks/changes.json``) and prints a table.

    python tools/bench_changes.py --data outputs/bench/data/car1000_s0/annotations.json \\
        [--rev f39c310] [--pipeline outputs/bench/data/car200/annotations.json]

``--carve-only --rev REV`` compares just the carving, both revisions called alike (see
:func:`carving_same_call`), e.g. ``--rev ec551be`` for the chunking and indexing changes.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from carvi_torch import carve as C  # noqa: E402
from carvi_torch import pipeline, select, surrogates  # noqa: E402
from carvi_torch.config import Config  # noqa: E402
from carvi_torch.io import coco  # noqa: E402
from carvi_torch.io.outputs import read_json, write_json  # noqa: E402


def old_module(rev: str, path: str, name: str):
    """Import ``path`` as it was at ``rev`` (git show) under the module name ``name``."""
    src = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    tmp = Path(tempfile.mkdtemp()) / f"{name}.py"
    tmp.write_text(src)
    # a submodule of the package, so its relative imports (``from .cameras import ...``) resolve,
    # registered before it runs (dataclasses look their module up in sys.modules)
    full = f"carvi_torch.{name}"
    spec = importlib.util.spec_from_file_location(full, tmp)
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "carvi_torch"
    sys.modules[full] = mod
    spec.loader.exec_module(mod)
    return mod


def interleaved(fns: dict, repeat: int, clock=time.process_time) -> dict:
    """Best time of each function over ``repeat`` interleaved rounds: process time (the default) or
    whatever ``clock`` reads (``time.perf_counter`` for wall time)."""
    best = {k: float("inf") for k in fns}
    for _ in range(repeat):
        for k, f in fns.items():
            t0 = clock()
            f()
            best[k] = min(best[k], clock() - t0)
    return best


def class_proposals(args, device: torch.device):
    """The class of ``args.data`` as a run prepares it (same seed) and the kept proposals of its first
    ``args.objects`` references: ``cfg, plan, coll, K, ref, views, valid`` (``valid`` before keeping)."""
    cfg = Config().override(dict(data=args.data, classes=[args.category], progress=False))
    loaded = coco.load_coco(args.data, canvas_size=cfg.canvas_size, margin=cfg.canvas_margin, device=device,
                            classes=[args.category])
    coll = loaded.collections[args.category]
    gen = torch.Generator().manual_seed(cfg.seed + pipeline._stable_hash(args.category))
    plan, todo, _ = pipeline.prepare_class(coll, cfg, device, gen)
    K = min(args.objects, len(todo))
    ref, views, valid = pipeline.proposals_of(plan, torch.tensor(todo[:K]))
    return cfg, plan, coll, K, ref[valid], views[valid], valid


def pipeline_call_bounds(cfg, valid: torch.Tensor, objects: int, device: torch.device) -> list[int]:
    """Where the pipeline's carving calls split the kept proposals of the first ``objects`` references.

    ``valid (objects * P,)`` bool marks the kept proposals (:func:`class_proposals`); a run on
    ``device`` carves ``pipeline._chunk_objects`` references per call, so call ``i`` takes the kept
    proposals ``bounds[i]:bounds[i + 1]``.
    """
    per_ref = valid.view(objects, -1).sum(1).tolist()
    step = pipeline._chunk_objects(cfg, device)
    return [sum(per_ref[:a]) for a in range(0, objects, step)] + [sum(per_ref)]


def functions(args) -> dict:
    old_carve = old_module(args.rev, "carvi_torch/carve.py", "_old_carve")
    old_select = old_module(args.rev, "carvi_torch/select.py", "_old_select")
    old_sur = old_module(args.rev, "carvi_torch/surrogates.py", "_old_surrogates")
    device = torch.device("cpu")
    cfg, plan, coll, K, ref, views, _ = class_proposals(args, device)
    maps = plan.maps
    sdf = maps.ext[:-1, C.PAD:-C.PAD, C.PAD:-C.PAD].contiguous()  # the class's maps, as the old pipeline held them
    cams = maps.cameras
    n = cfg.resolution
    out = {}

    # carving: the old pipeline called carve_proposals per chunk of 2 objects with the whole class's maps
    chunk = 2 * cfg.proposals

    def old_c():
        return [old_carve.carve_proposals(sdf, cams, ref[i:i + chunk], views[i:i + chunk], resolution=n,
                                          max_batch_voxels=cfg.max_batch_voxels) for i in range(0, len(ref), chunk)]

    def new_c():
        return C.carve_proposals(maps, None, ref, views, resolution=n,
                                 max_batch_voxels=pipeline._carve_batch_voxels(cfg, device))

    t = interleaved({"old": old_c, "new": new_c}, args.repeat)
    grids = new_c()
    same = torch.equal(torch.cat([g.occupancy for g in old_c()]), grids.occupancy)
    out["carve"] = {"old": t["old"] / K, "new": t["new"] / K, "ratio": t["old"] / t["new"], "identical": same}

    occ, T = grids.occupancy, grids.voxel_to_camera
    rc = plan.cams[ref]
    kw = dict(plane_size=cfg.plane_size, extent=plan.extent, centre=plan.centre)
    t = interleaved({"old": lambda: old_select._boundary(occ), "new": lambda: select._boundary(occ)}, args.repeat)
    out["boundary"] = {"old": t["old"] / K, "new": t["new"] / K, "ratio": t["old"] / t["new"],
                       "identical": bool(torch.equal(old_select._boundary(occ), select._boundary(occ)))}
    # the old pipeline projected chunks of 2 objects (its sub-sampling depended on the chunk)
    old_p = lambda: torch.cat([old_select.project_proposals(occ[i:i + chunk], T[i:i + chunk], rc[i:i + chunk],  # noqa
                                                            plan.axes, **kw) for i in range(0, len(ref), chunk)])
    new_p = lambda: select.project_proposals(occ, T, rc, plan.axes, **kw)  # noqa: E731
    t = interleaved({"old": old_p, "new": new_p}, args.repeat)
    a, b = old_p(), new_p()
    same_m = torch.equal(old_select.project_proposals(occ[:chunk], T[:chunk], rc[:chunk], plan.axes, supersample=2, **kw),
                         select.project_proposals(occ[:chunk], T[:chunk], rc[:chunk], plan.axes, supersample=2, **kw))
    out["select"] = {"old": t["old"] / K, "new": t["new"] / K, "ratio": t["old"] / t["new"],
                     "differing_plane_samples": int((a != b).sum()), "set_plane_samples": int(a.sum()),
                     "proposals_with_differences": int((a != b).flatten(1).any(1).sum()),
                     "identical_at_fixed_supersample_2": bool(same_m)}

    # triplets on the class, and memory at a large synthetic class
    labels = torch.randint(-1, 3, (len(coll),), generator=torch.Generator().manual_seed(1))
    refs = torch.arange(len(coll))
    f = {"old": lambda: old_sur.sample_triplets(labels, coll.object_ids, refs, cfg.proposals,
                                                torch.Generator().manual_seed(3)),
         "new": lambda: surrogates.sample_triplets(labels, coll.object_ids, refs, cfg.proposals,
                                                   torch.Generator().manual_seed(3))}
    t = interleaved(f, args.repeat)
    out["triplets"] = {"old": t["old"], "new": t["new"], "ratio": t["old"] / t["new"], "instances": len(coll),
                       "identical": bool(torch.equal(f["old"]().surrogates, f["new"]().surrogates))}
    out["triplets_memory"] = {"instances": args.big, **{k: _peak_child(k, args) for k in ("old", "new")}}
    out["objects"] = K
    return out


def carving_same_call(args) -> dict:
    """Old and new ``carve_proposals``, called alike: on the class's maps prepared once, per pipeline
    chunk of references (each chunk's grids released before the next), each revision with its own
    default chunk size; both interpolations; labels compared voxel for voxel.

    For revisions that already take prepared maps (from the performance work on); the old module's
    :class:`CarveMaps` is the new one, so both read the same object.
    """
    old_carve = old_module(args.rev, "carvi_torch/carve.py", "_old_carve")
    if not hasattr(old_carve, "prepare_maps"):
        raise SystemExit(f"--carve-only needs a revision whose carving takes prepared maps (carve.prepare_maps); "
                         f"{args.rev} has none: give --rev a later one (e.g. ec551be)")
    old_carve.CarveMaps = C.CarveMaps
    device = torch.device("cpu")
    cfg, plan, _, K, ref, views, valid = class_proposals(args, device)
    bounds = pipeline_call_bounds(cfg, valid, K, device)
    out = {"objects": K, "pipeline_chunk_objects": pipeline._chunk_objects(cfg, device)}
    for mode in ("bilinear", "nearest"):
        def run(mod, keep=False, mode=mode):
            grids = []
            for a, b in zip(bounds[:-1], bounds[1:]):
                g = mod.carve_proposals(plan.maps, None, ref[a:b], views[a:b], resolution=cfg.resolution,
                                        imprint=cfg.imprint, interpolation=mode)
                if keep:
                    grids.append(g.occupancy)
                del g
            return grids
        same = all(torch.equal(x, y) for x, y in zip(run(old_carve, True), run(C, True)))
        t = interleaved({"old": lambda: run(old_carve), "new": lambda: run(C)}, args.repeat,
                        time.perf_counter if args.clock == "wall" else time.process_time)
        out[mode] = {"old": t["old"] / K, "new": t["new"] / K, "ratio": t["old"] / t["new"], "identical": same}
    return out


def _peak_child(which: str, args) -> dict:
    """Seconds and peak memory of sample_triplets on ``--big`` instances, in a fresh process."""
    code = f"""
import resource, sys, time, torch
sys.path.insert(0, {str(ROOT)!r}); sys.path.insert(0, {str(ROOT / 'tools')!r})
from bench_changes import old_module
from carvi_torch import surrogates
mod = old_module({args.rev!r}, "carvi_torch/surrogates.py", "_old_s") if {which!r} == "old" else surrogates
N = {args.big}
labels = torch.randint(-1, 3, (N,), generator=torch.Generator().manual_seed(1))
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
mod.sample_triplets(labels, torch.arange(N), torch.arange(N), 20, torch.Generator().manual_seed(3))
print(time.perf_counter() - t, (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024)
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, CARVI_THREADS="1", OMP_NUM_THREADS="1"))
    if res.returncode != 0:
        return {"error": res.stderr[-500:]}
    secs, mb = map(float, res.stdout.split()[-2:])
    return {"seconds": secs, "peak_growth_mb": mb}


def pipelines(args) -> dict:
    """Both revisions' ``reconstruct`` on the same data (1 torch thread each), voxels compared."""
    work = Path(args.work_dir)
    old_src = work / f"src_{args.rev}"
    if not (old_src / "carvi_torch").is_dir():
        old_src.mkdir(parents=True, exist_ok=True)
        arch = subprocess.run(["git", "archive", args.rev, "carvi_torch"], cwd=ROOT, capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(old_src)], input=arch.stdout, check=True)
    res = {}
    for name, src in (("old", old_src), ("new", ROOT)):
        out = work / f"pipeline_{name}"
        env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS=str(args.threads), CARVI_THREADS=str(args.threads))
        cmd = [sys.executable, "-m", "carvi_torch.reconstruct", "--data", args.pipeline, "--out", str(out),
               "progress=false", "preview=false", "overwrite=true", f"classes={args.category}"]
        t0 = time.perf_counter()
        subprocess.run(cmd, cwd=work, env=env, check=True, capture_output=True)
        s = read_json(out / "summary.json")
        res[name] = {"wall_seconds": time.perf_counter() - t0, "total_seconds": s["total_seconds"],
                     "seconds": s["classes"][args.category]["seconds"], "load_seconds": s["load_seconds"],
                     "reconstructed": s["classes"][args.category]["reconstructed"], "peak_rss_mb": s["peak_rss_mb"],
                     "command": " ".join(shlex.quote(c) for c in cmd)}
    same = differ = 0
    for f in sorted((work / "pipeline_old" / args.category / "voxels").glob("*.npz")):
        g = work / "pipeline_new" / args.category / "voxels" / f.name
        if g.is_file() and np.array_equal(np.load(f)["occupancy"], np.load(g)["occupancy"]):
            same += 1
        else:
            differ += 1
    res["ratio_total"] = res["old"]["total_seconds"] / res["new"]["total_seconds"]
    res["objects_identical"], res["objects_different"] = same, differ
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="annotations.json of the class the inputs come from")
    ap.add_argument("--category", default="car")
    ap.add_argument("--rev", default="f39c310", help="the old revision")
    ap.add_argument("--objects", type=int, default=20, help="references whose proposals are compared")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--big", type=int, default=9087, help="instances of the triplet memory check")
    ap.add_argument("--pipeline", default=None, help="annotations.json for the end-to-end comparison")
    ap.add_argument("--work-dir", default=str(ROOT / "outputs" / "bench" / "changes"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "changes.json"))
    ap.add_argument("--carve-only", action="store_true",
                    help="only the carving, both revisions called alike on prepared maps, both interpolations "
                         "(for revisions from the performance work on)")
    ap.add_argument("--clock", choices=("process", "wall"), default="process",
                    help="--carve-only: time the carving in process (CPU) time, summed over threads, or in wall "
                         "time (what shows how well the threads share the work)")
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    if args.clock != "process" and not args.carve_only:
        ap.error("--clock applies to --carve-only; the full comparison times in process time")
    torch.set_num_threads(args.threads)
    load = os.getloadavg()
    if args.carve_only:
        result = {"command": " ".join(["python tools/bench_changes.py"] + [shlex.quote(a) for a in argv]),
                  "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
                              "threads": args.threads, "load_average_at_start": list(load),
                              "clock": args.clock},
                  "carving": carving_same_call(args)}
        result["machine"]["load_average_at_end"] = list(os.getloadavg())
        cv = result["carving"]
        print(f"load average at start {load[0]:.2f}, end {result['machine']['load_average_at_end'][0]:.2f}; "
              f"{args.threads} torch thread(s); {cv['objects']} objects; carving, old revision {args.rev}")
        print("seconds per object are " + ("wall time" if args.clock == "wall"
                                           else "process (CPU) time, summed over threads"))
        print(f"{'':12s} {'old s/obj':>10s} {'new s/obj':>10s} {'old/new':>8s}  identical")
        for mode in ("bilinear", "nearest"):
            r = cv[mode]
            print(f"{mode:12s} {r['old']:10.4f} {r['new']:10.4f} {r['ratio']:8.2f}  {r['identical']}")
        write_json(args.out, result)
        print(f"wrote {args.out}")
        return result
    result = {"command": " ".join(["python tools/bench_changes.py"] + [shlex.quote(a) for a in argv]),
              "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
                          "threads": args.threads, "load_average_at_start": list(load)},
              "functions": functions(args)}
    if args.pipeline:
        result["pipeline"] = pipelines(args)
    result["machine"]["load_average_at_end"] = list(os.getloadavg())
    fn = result["functions"]
    print(f"load average at start {load[0]:.2f}, end {result['machine']['load_average_at_end'][0]:.2f}; "
          f"{args.threads} torch thread(s); {fn['objects']} objects")
    print(f"{'':12s} {'old s/obj':>10s} {'new s/obj':>10s} {'old/new':>8s}  notes")
    for k in ("carve", "boundary", "select"):
        r = fn[k]
        notes = {kk: v for kk, v in r.items() if kk not in ("old", "new", "ratio")}
        print(f"{k:12s} {r['old']:10.4f} {r['new']:10.4f} {r['ratio']:8.1f}  {notes}")
    r = fn["triplets"]
    print(f"{'triplets':12s} {r['old']:10.4f} {r['new']:10.4f} {r['ratio']:8.1f}  (seconds for {r['instances']} "
          f"instances) identical {r['identical']}; at {args.big}: {fn['triplets_memory']}")
    if args.pipeline:
        p = result["pipeline"]
        print(f"pipeline: old {p['old']['total_seconds']:.1f} s, new {p['new']['total_seconds']:.1f} s, "
              f"old/new {p['ratio_total']:.2f}; objects identical {p['objects_identical']}, "
              f"different {p['objects_different']}")
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
