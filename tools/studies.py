"""Studies of the synthetic benchmark (after ``tools/benchmark_synthetic.py``), and the frames figure.

    python tools/studies.py {frames,canonical,ranking,threshold,viewpoints,clusters,step,misses,own-shapes} [options]

Figures go to ``docs/figures/<name>.png`` (docs/results.md and docs/conventions.md show them),
JSON records to ``outputs/studies/studies_<name>.json`` (``own-shapes``: ``studies_own_shapes.json``), or
with ``--out FILE --key KEY`` (``misses``, ``own-shapes``, ``ranking``) under a key of a records file of
docs/data/ whose other keys are kept. Subcommands (``--bench`` is the benchmark's working directory, default
outputs/benchmark):

* ``frames``: the image, camera and voxel-grid frames of carvi_torch (``frames.png``,
  docs/conventions.md; ``--out`` moves it). Needs no benchmark.
* ``canonical``: the canonical object frame with the shipped aeroplane template and one
  camera's azimuth and elevation (``canonical_frame.png``, docs/conventions.md).
* ``ranking`` (a, b): every saved proposal of the Full run (``<class>/proposals/<id>.npz``) is
  meshed (:func:`carvi_torch.mesh.occupancy_to_mesh`) and scored against the ground truth
  (:func:`carvi_torch.evaluation.metrics.evaluate_reconstruction`, step ``--step-percent`` of the GT
  bbox diagonal, coarser than the table's to keep the ~7000 evaluations affordable; the
  difference is measured on the selected proposals and written to the JSON). Per class: the
  top-ranked, random (expected error of a uniform pick among the valid proposals) and best
  available proposal (``ranking.png``); over all classes: the same against the size of the
  proposal pool, 1..P, the top-ranked among the first k (``pool_size.png``). ``--figures`` and
  ``--record`` put the figures and the record elsewhere (the 8-view study of docs/results.md); ``--out FILE
  [--key KEY]`` writes the record under a key of a records file instead (docs/data/benchmark_synthetic.json).
* ``threshold`` (c): Full rerun on ``--classes`` with ``surrogates.cluster_threshold_deg`` in
  ``--thresholds``; mean error per class and threshold (``threshold.png``).
* ``viewpoints`` (d): median geodesic viewpoint error per class, SfM vs refined cameras, from
  the benchmark's record ``docs/data/benchmark_synthetic.json`` (``viewpoints.png``).
* ``step``: the metric's sampling step, the paper's 0.5% against the table's 1% of the GT
  bbox diagonal, on ``--classes`` (Full and the baselines): per-object differences, CPU times.
* ``clusters``: per class, the Full reconstructions brought into the class's object frame
  (refined cameras), ``--points`` surface samples each, centred and scaled to unit RMS radius,
  a symmetric RMS chamfer distance matrix (:func:`carvi_torch.evaluation.studies.chamfer_matrix`), K-medoids
  into 5 clusters, the medoids drawn ordered by cluster size (``shape_clusters.png``).
* ``own-shapes``: whether the misses are the shapes' (docs/viewpoints.md, *Small classes*): on rendered sets
  (``--data``), each view's final camera (one shape per class) refined again under its object's own keypoints and
  under the mean shape stretched along the CAD frame's three axes onto them; medians per class and CAD model.
* ``misses``: where the viewpoint misses come from (docs/viewpoints.md, *Small classes*), on rendered sets
  (``--data``: ``annotations.json`` with ``gt.json`` beside it, e.g. tools/viewpoints_cad.py's renders): per class
  (default settings, :func:`carvi_torch.viewpoints.estimate_viewpoints`) each object's true camera is put in the
  SfM frame by the class's fitted rotation (:func:`carvi_torch.evaluation.viewpoint_metrics.viewpoint_report` of
  the final cameras; scale by the median ratio, offset from the visible keypoints) and refined with the same
  energy (:func:`carvi_torch.viewpoints.refine.refine_with_shape`); the final camera's depth-reversed mirror
  through the symmetry plane is scored beside it. Per CAD model: the errors of the final, true, true-refined and
  mirror cameras, the angle from the true-refined camera to the final one, and each camera's energy, hull
  agreement (:func:`carvi_torch.viewpoints.choice.hull_agreement`) and keypoint RMS. ``--out``/``--key`` put the
  record under a key of a records file (docs/data/viewpoints.json).

Example:
    python tools/studies.py frames
    python tools/studies.py ranking --jobs 2
    python tools/studies.py ranking --bench outputs/final_t2_one/seed0 --views-per-model 2 \\
        --figures outputs/ranking_cad8 --record ranking_cad8_seed0
    python tools/studies.py threshold --classes aeroplane,car,chair,sofa
    python tools/studies.py viewpoints
    python tools/studies.py clusters
    python tools/studies.py misses --data outputs/viewpoints_cad/renders_v8_s{0,1,2}/annotations.json \\
        --out docs/data/viewpoints.json --key viewpoints_cad8_misses
    python tools/studies.py own-shapes --data outputs/viewpoints_cad/renders_v8_s{0,1,2}/annotations.json \
        --out docs/data/viewpoints.json --key viewpoints_cad8_own_shapes
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from carvi_torch.io.layout import object_mesh
from carvi_torch.runtime import cpu_seconds

ROOT = Path(__file__).resolve().parents[1]
#: Where the figures go (docs/results.md, docs/conventions.md show them).
FIGURES = ROOT / "docs" / "figures"
#: Where the studies' JSON records go.
RECORDS = ROOT / "outputs" / "studies"
#: The synthetic benchmark's record (docs/results.md), read by ``viewpoints`` and ``ranking``.
BENCHMARK_JSON = ROOT / "docs" / "data" / "benchmark_synthetic.json"


def _command() -> str:
    return "python tools/studies.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def _record(name: str) -> Path:
    """``outputs/studies/studies_<name>.json`` (its folder made)."""
    RECORDS.mkdir(parents=True, exist_ok=True)
    return RECORDS / f"studies_{name}.json"


def _figure(name: str, folder: Path = FIGURES) -> Path:
    """``<folder>/<name>.png`` (default ``docs/figures``; the folder made)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return folder / f"{name}.png"


def _data_dir(bench: Path) -> Path:
    cands = sorted(bench.glob("data_pool*"))
    if not cands:
        raise SystemExit(f"error: no rendered data in {bench} (run tools/benchmark_synthetic.py first)")
    return cands[0]


def _run_mesh_format(run: Path) -> str:
    """The ``mesh.format`` the run ``run`` wrote its meshes in (its ``config.yaml``; the default without one, or
    without the run: :func:`~carvi_torch.io.layout.object_mesh` looks in the other formats too)."""
    from carvi_torch.config import Config, read_run_config

    cfg = run / "config.yaml"
    return (read_run_config(cfg) if cfg.is_file() else Config()).mesh.format


def _classes_of(ann: dict) -> dict[int, str]:
    cat = {int(c["id"]): c["name"] for c in ann["categories"]}
    return {int(a["id"]): cat[int(a["category_id"])] for a in ann["annotations"]}


# =========================================================================== (a, b) ranking


def _proposal_errors(job):
    """Worker: errors of every proposal of one reference (list, NaN where invalid or empty)."""
    import torch

    torch.set_num_threads(1)
    from carvi_torch.evaluation import metrics
    from carvi_torch.evaluate import posed_gt_mesh
    from carvi_torch.mesh import occupancy_to_mesh
    from carvi_torch.evaluation.studies import load_proposals

    path, entry, gt_root, step_percent, selected_mesh, table_step = job
    props = load_proposals(path)
    posed, diag = posed_gt_mesh(entry, Path(gt_root))
    gt = metrics.EvaluationMesh(posed, name="gt").with_diag(diag)
    step = step_percent / 100.0 * diag
    P = len(props["valid"])
    errs = [math.nan] * P
    nonempty = [bool(props["occupancy"][p].any()) for p in range(P)]
    for p in range(P):
        if not (props["valid"][p] and nonempty[p]):
            continue
        m = occupancy_to_mesh(props["occupancy"][p], props["voxel_to_camera"][p])
        r = metrics.evaluate_reconstruction(m, gt, step=step)
        errs[p] = float(r["error_percent"])
    fine = None
    if selected_mesh is not None:  # the selected proposal at the table's step, to measure the approximation
        import trimesh

        m = trimesh.load(selected_mesh, force="mesh", process=False)
        fine = float(metrics.evaluate_reconstruction(m, gt, step=table_step / 100.0 * diag)["error_percent"])
    return {"errors": errs, "scores": props["scores"].tolist(), "misses": props["misses"].tolist(),
            "valid": [bool(v) and ne for v, ne in zip(props["valid"], nonempty)], "best": props["best"],
            "selected_fine": fine}


def ranking(args) -> int:
    """(a, b): every saved proposal of the Full run scored against the ground truth (module docstring)."""
    bench = Path(args.bench)
    data = _data_dir(bench)
    ann = json.loads((data / "annotations.json").read_text())
    gt = json.loads((data / "gt.json").read_text())["annotations"]
    cls_of = _classes_of(ann)
    chosen = _test_views(ann, args.views_per_model)
    classes = set(args.classes.split(",")) if args.classes else None
    full = bench / "run_full"
    table_step = json.loads(BENCHMARK_JSON.read_text())["settings"]["step_percent"] \
        if BENCHMARK_JSON.is_file() else 1.0
    fmt = _run_mesh_format(full)
    jobs = []
    for aid in chosen:
        c = cls_of[aid]
        if classes and c not in classes:
            continue
        p = full / c / "proposals" / f"{aid}.npz"
        if not p.is_file():
            continue
        mesh = object_mesh(full / c, aid, fmt)
        jobs.append((str(p), gt[str(aid)], str(data), args.step_percent,
                     str(mesh) if mesh is not None else None, table_step))
    raw = bench / "ranking" / f"errors_step{args.step_percent:g}_v{args.views_per_model}.json"
    if raw.is_file() and not args.fresh:
        cached = json.loads(raw.read_text())
        per_ref, seconds = cached["per_reference"], cached["seconds"]
        per_ref = {k: v for k, v in per_ref.items() if not classes or v["class"] in classes}
        print(f"ranking: reusing {raw} ({len(per_ref)} references)", flush=True)
    else:
        print(f"ranking: {len(jobs)} references, step {args.step_percent}% ({args.jobs} processes)", flush=True)
        per_ref, seconds = _errors_of_jobs(jobs, args.jobs, cls_of, raw)
    out = _ranking_summary(per_ref)
    out.update({"command": _command(), "step_percent": args.step_percent, "table_step_percent": table_step,
                "views_per_model": args.views_per_model, "references": len(per_ref), "seconds": round(seconds, 1),
                "per_reference": per_ref})
    _write_ranking(args, out)
    _plot_ranking(out, Path(args.figures))
    print(json.dumps({k: out[k] for k in ("mean", "selected_vs_table")}, indent=1))
    return 0


def _test_views(ann: dict, views_per_model: int) -> list[int]:
    """The sorted ids of the first ``views_per_model`` test views (by id) of every model."""
    by_model: dict[int, list[int]] = {}
    for a in sorted((a for a in ann["annotations"] if a.get("split") == "test"), key=lambda a: a["id"]):
        by_model.setdefault(int(a["object_id"]), []).append(int(a["id"]))
    return sorted(i for ids in by_model.values() for i in ids[:views_per_model])


def _errors_of_jobs(jobs: list, processes: int, cls_of: dict, raw: Path) -> tuple[dict, float]:
    """:func:`_proposal_errors` of every job on ``processes`` forked processes, per reference id (with its class),
    and their seconds; both cached in ``raw``."""
    from multiprocessing import get_context

    from carvi_torch.io.outputs import write_json

    t0 = time.perf_counter()
    with get_context("fork").Pool(processes) as pool:
        rows = []
        for i, r in enumerate(pool.imap(_proposal_errors, jobs, chunksize=1)):
            rows.append(r)
            if (i + 1) % 25 == 0:
                print(f"  {i + 1}/{len(jobs)} ({time.perf_counter() - t0:.0f} s)", flush=True)
    seconds = time.perf_counter() - t0
    per_ref = {}
    for job, r in zip(jobs, rows):
        aid = int(Path(job[0]).stem)
        per_ref[str(aid)] = {"class": cls_of[aid], **r}
    write_json(raw, {"per_reference": per_ref, "seconds": seconds}, indent=None)
    return per_ref, seconds


def _write_ranking(args, out: dict) -> None:
    """The ranking record: under a key of ``--out`` (a records file such as docs/data/benchmark_synthetic.json, its
    other keys kept), else ``outputs/studies/studies_<--record>.json``."""
    from carvi_torch.io.outputs import write_json, write_record

    if args.out:
        write_record(args.out, out, args.key or args.record)
        print(f"wrote {args.out}, key {args.key or args.record}")
    else:
        write_json(_record(args.record), out)


def _ranking_summary(per_ref: dict) -> dict:
    import torch

    from carvi_torch.select import rank_proposals
    from carvi_torch.evaluation.studies import ranking_curves

    classes = sorted({r["class"] for r in per_ref.values()})
    P = max(len(r["errors"]) for r in per_ref.values())
    per_class, curves = {}, {}
    agree, n_ref = 0, 0
    fine_pairs = []
    for c in classes:
        rows = [r for r in per_ref.values() if r["class"] == c]
        E = torch.tensor([[math.nan if v is None else v for v in r["errors"]] for r in rows], dtype=torch.float64)
        S = torch.tensor([[math.inf if v is None else v for v in r["scores"]] for r in rows], dtype=torch.float64)
        M = torch.tensor([r["misses"] for r in rows], dtype=torch.long)
        V = torch.tensor([r["valid"] for r in rows], dtype=torch.bool)
        order, best = rank_proposals(S, M, V)
        agree += int((best == torch.tensor([r["best"] for r in rows])).sum())
        n_ref += len(rows)
        cur = ranking_curves(E, order)
        curves[c] = {k: np.nanmean(v.numpy(), axis=0).tolist() for k, v in cur.items()}
        per_class[c] = {k: float(np.nanmean(v[:, -1].numpy())) for k, v in cur.items()}
        per_class[c]["references"] = len(rows)
        per_class[c]["valid_proposals_mean"] = float(V.sum(1).double().mean())
        for r, t in zip(rows, cur["top"][:, -1].tolist()):
            if r.get("selected_fine") is not None and math.isfinite(t):
                fine_pairs.append((t, r["selected_fine"]))
    mean = {k: float(np.mean([per_class[c][k] for c in classes])) for k in ("top", "random", "best")}
    # the pool-size curve: classes with a pool of P proposals (rotationally symmetric classes have one)
    pooled = [c for c in classes if len(curves[c]["top"]) == P]
    pool = {k: np.nanmean(np.array([curves[c][k] for c in pooled]), axis=0).tolist() for k in ("top", "random", "best")}
    diffs = np.array([a - b for a, b in fine_pairs]) if fine_pairs else np.zeros(0)
    return {"classes": per_class, "mean": mean, "pool_size": {"k": list(range(1, P + 1)), "classes": pooled, **pool},
            "ranking_agrees_with_pipeline": f"{agree}/{n_ref}",
            "selected_vs_table": {"n": int(len(diffs)),
                                  "mean_difference_pp": float(diffs.mean()) if len(diffs) else None,
                                  "mean_abs_difference_pp": float(np.abs(diffs).mean()) if len(diffs) else None,
                                  "note": "top-ranked proposal's error at the study's step minus the selected "
                                          "mesh's error at the table's step"}}


def _plot_ranking(out: dict, folder: Path = FIGURES) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    classes = list(out["classes"])
    x = np.arange(len(classes) + 1)
    fig, ax = plt.subplots(figsize=(11, 4))
    w = 0.27
    for i, (k, label, col) in enumerate((("top", "top ranked", "tab:blue"), ("random", "random", "tab:gray"),
                                         ("best", "best available", "tab:green"))):
        vals = [out["classes"][c][k] for c in classes] + [out["mean"][k]]
        ax.bar(x + (i - 1) * w, vals, w, label=label, color=col)
    ax.set_xticks(x, classes + ["mean"], rotation=30, ha="right")
    ax.set_ylabel("symmetric RMS error (% of GT bbox diagonal)")
    ax.set_title(f"Proposal ranking (Full, {out['references']} references, metric step {out['step_percent']}%)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(_figure("ranking", folder), dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.5, 4))
    k = out["pool_size"]["k"]
    for key, label, col in (("top", "top ranked", "tab:blue"), ("random", "random", "tab:gray"),
                            ("best", "best available", "tab:green")):
        ax.plot(k, out["pool_size"][key], "o-", ms=3, label=label, color=col)
    ax.set_xlabel("proposals in the pool (the first k)")
    ax.set_ylabel("mean error over classes (%)")
    ax.set_xticks([1, 5, 10, 15, 20])
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(f"Error against the size of the proposal pool ({len(out['pool_size']['classes'])} classes)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(_figure("pool_size", folder), dpi=110)
    plt.close(fig)


# =========================================================================== (c) threshold


def threshold(args) -> int:
    bench = Path(args.bench)
    data = _data_dir(bench)
    classes = args.classes.split(",")
    thresholds = [float(v) for v in args.thresholds.split(",")]
    env = dict(os.environ, OMP_NUM_THREADS=str(max(1, (os.cpu_count() or 1) // args.jobs)))
    runs = {}
    cmds = []
    for thr in thresholds:
        d = bench / "threshold" / f"t{thr:g}"
        runs[thr] = d
        if (d / "summary.json").is_file() and "total_seconds" in json.loads((d / "summary.json").read_text()):
            continue
        cmds.append([sys.executable, "-m", "carvi_torch.reconstruct", "--data", str(data / "annotations.json"),
                     "--out", str(d), "references=test", f"seed={args.seed}", "progress=false", "preview=false",
                     "report=false",
                     f"surrogates.cluster_threshold_deg={thr:g}", "classes=" + ",".join(classes)])
    t0 = time.perf_counter()
    _run_all(cmds, args.jobs, env)
    ev = [sys.executable, "-m", "carvi_torch.evaluate", "--data", str(data / "annotations.json"), "--split", "test",
          "--quiet", "--step-percent", str(args.step_percent), "--classes", ",".join(classes),
          "--out", str(bench / "threshold" / "eval")]
    for thr in thresholds:
        ev += ["--recon", f"t{thr:g}={runs[thr]}"]
    _run_all([ev], 1, dict(env, OMP_NUM_THREADS=str(os.cpu_count() or 1)))
    res = json.loads((bench / "threshold" / "eval" / "results.json").read_text())
    table = {c: {f"{thr:g}": res["classes"][c][f"t{thr:g}"]["mean"] for thr in thresholds} for c in classes}
    used = {}
    for thr in thresholds:
        s = json.loads((runs[thr] / "summary.json").read_text())
        used[f"{thr:g}"] = {c: s["classes"][c].get("clusters") for c in classes if c in s["classes"]}
    mean = {f"{thr:g}": float(np.mean([table[c][f"{thr:g}"] for c in classes])) for thr in thresholds}
    out = {"command": _command(), "classes": classes, "thresholds": thresholds, "step_percent": args.step_percent,
           "error": table, "mean": mean, "clusters": used, "seconds": round(time.perf_counter() - t0, 1)}
    from carvi_torch.io.outputs import write_json

    write_json(_record("threshold"), out)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for c in classes:
        ax.plot(thresholds, [table[c][f"{t:g}"] for t in thresholds], "o-", ms=3, label=c, alpha=0.7)
    ax.plot(thresholds, [mean[f"{t:g}"] for t in thresholds], "k-", lw=2.5, label="mean")
    ax.set_xlabel("principal-direction clustering threshold (degrees)")
    ax.set_ylabel("mean error (% of GT bbox diagonal)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Error against the clustering threshold (Full)")
    fig.tight_layout()
    fig.savefig(_figure("threshold"), dpi=110)
    plt.close(fig)
    print(json.dumps({"error": table, "mean": mean}, indent=1))
    return 0


def _run_all(cmds: list[list[str]], jobs: int, env: dict) -> None:
    running = []
    pending = list(cmds)
    while pending or running:
        while pending and len(running) < jobs:
            argv = pending.pop(0)
            print("  " + " ".join(shlex.quote(a) for a in argv), flush=True)
            running.append((subprocess.Popen(argv, env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                                             stderr=subprocess.PIPE, text=True), argv))
        time.sleep(0.5)
        for item in list(running):
            proc, argv = item
            if proc.poll() is None:
                continue
            running.remove(item)
            if proc.returncode != 0:
                raise SystemExit(f"failed ({proc.returncode}): {' '.join(argv)}\n{proc.stderr.read()[-3000:]}")


# =========================================================================== (d) viewpoints


def viewpoints(args) -> int:
    bench_json = Path(args.bench_json)
    res = json.loads(bench_json.read_text())["evaluation"]
    rows = {}
    for c, per in sorted(res["viewpoints"].items()):
        full = per.get("Full", {})
        rows[c] = {st: {"median_geodesic": full[st]["geodesic"]["median"],
                        "acc_at_30": full[st]["geodesic"]["acc_at_30"],
                        "median_azimuth": full[st]["azimuth"]["median"],
                        "median_elevation": full[st]["elevation"]["median"]}
                   for st in ("sfm", "refined") if st in full}
    missing = [c for c, r in rows.items() if not ("sfm" in r and "refined" in r)]
    rows = {c: r for c, r in rows.items() if c not in missing}
    out = {"command": _command(), "source": str(bench_json), "classes": rows, "classes_without_cameras": missing,
           "median_of_class_medians": {
               st: float(np.median([r[st]["median_geodesic"] for r in rows.values() if st in r]))
               for st in ("sfm", "refined")}}
    from carvi_torch.io.outputs import write_json

    write_json(_record("viewpoints"), out)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    classes = list(rows)
    x = np.arange(len(classes))
    fig, ax = plt.subplots(figsize=(10, 4))
    for i, (st, col) in enumerate((("sfm", "tab:orange"), ("refined", "tab:blue"))):
        ax.bar(x + (i - 0.5) * 0.38, [rows[c][st]["median_geodesic"] for c in classes], 0.38, label=st, color=col)
    ax.set_xticks(x, classes, rotation=30, ha="right")
    ax.set_ylabel("median geodesic error (degrees)")
    ax.set_title("Viewpoint error of the test renders (Full run), SfM vs refined cameras")
    ax.axhline(10, color="k", lw=0.5, ls="--")
    ax.legend()
    fig.tight_layout()
    fig.savefig(_figure("viewpoints"), dpi=110)
    plt.close(fig)
    print(json.dumps(out["median_of_class_medians"]))
    return 0


# =========================================================================== shape clusters


def clusters(args) -> int:
    import torch
    import trimesh

    from carvi_torch.cameras import ScaledOrthographic
    from carvi_torch.evaluation.studies import (chamfer_matrix, k_medoids, normalise_points, order_clusters_by_size,
                                     sample_points)

    bench = Path(args.bench)
    data = _data_dir(bench)
    ann = json.loads((data / "annotations.json").read_text())
    model_of = {str(a["id"]): a["source"] for a in ann["annotations"]}
    full = bench / "run_full"
    fmt = _run_mesh_format(full)
    t0 = time.perf_counter()
    out, figs = {}, {}
    for cdir in sorted(p for p in full.iterdir() if (p / "cameras.json").is_file()):
        c = cdir.name
        cams = json.loads((cdir / "cameras.json").read_text())["cameras"]
        files = {int(a): object_mesh(cdir, a, fmt) for a, e in cams.items() if e.get("refined")}
        ids = sorted(a for a, f in files.items() if f is not None)
        if len(ids) < args.k:
            continue
        meshes = [trimesh.load(files[a], force="mesh", process=False) for a in ids]
        pts = torch.stack([sample_points(m, args.points, seed=args.seed) for m in meshes])  # (N, M, 3)
        cam = ScaledOrthographic.from_list([cams[str(a)]["refined"] for a in ids], dtype=torch.float64)
        obj = normalise_points(cam.from_camera_frame(pts)).float()
        D = chamfer_matrix(obj, chunk_pairs=16).double()
        med, labels, cost = k_medoids(D, args.k)
        med, labels, sizes = order_clusters_by_size(med, labels)
        models = [model_of[str(a)] for a in ids]
        # purity: share of items whose cluster's most common source model is their own
        pure = 0
        for j in range(args.k):
            mem = [models[i] for i in range(len(ids)) if int(labels[i]) == j]
            if mem:
                pure += max(mem.count(m) for m in set(mem))
        out[c] = {"objects": len(ids), "medoids": [ids[int(m)] for m in med], "sizes": sizes.tolist(),
                  "cost": cost, "purity_by_model": pure / len(ids),
                  "members": {str(ids[int(m)]): sorted({models[i] for i in range(len(ids)) if int(labels[i]) == j})
                              for j, m in enumerate(med)},
                  "medoid_models": [models[int(m)] for m in med]}
        # every medoid drawn in the class frame, seen by the camera of the largest cluster's medoid
        view = cam.R[int(med[0])]
        figs[c] = [(_object_frame_mesh(meshes[int(m)], cam[int(m)]), view, int(sizes[j]), models[int(m)])
                   for j, m in enumerate(med)]
        print(f"  {c}: sizes {sizes.tolist()}, purity {out[c]['purity_by_model']:.2f}", flush=True)
    seconds = time.perf_counter() - t0
    from carvi_torch.io.outputs import write_json

    write_json(_record("shape_clusters"), {
        "command": _command(), "k": args.k, "points": args.points, "seconds": round(seconds, 1),
        "distance": "symmetric RMS chamfer (max of the two directions) between area-uniform point samples of the "
                    "Full meshes, in the class's SfM object frame (refined cameras), each centred and scaled to unit "
                    "RMS radius", "classes": out})
    _plot_clusters(figs, args.k)
    return 0


def _object_frame_mesh(mesh, cam):
    """A reference-frame mesh (image pixels) in the class's object frame, centred (``(V, 3)``, faces)."""
    import torch

    V = cam.from_camera_frame(torch.from_numpy(np.asarray(mesh.vertices, dtype=np.float64))[None])[0].numpy()
    return V - V.mean(axis=0), np.asarray(mesh.faces)


def _draw_mesh(ax, mesh, view, turn_deg: float = 35.0, lift_deg: float = 20.0) -> None:
    """Shaded object-frame mesh ``(V, F)`` seen by rotation ``view (3, 3)`` turned by ``turn_deg``
    about the image's vertical axis and ``lift_deg`` about its horizontal axis."""
    from matplotlib.collections import PolyCollection

    V, F = mesh
    V = V @ np.asarray(view, dtype=np.float64).T  # camera frame: x right, y down, z into the scene
    a, b = math.radians(turn_deg), math.radians(lift_deg)
    Ry = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    P = V @ (Rx @ Ry).T
    tri = P[F]  # (F, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    light = np.array([-0.4, -0.6, -0.7])
    light /= np.linalg.norm(light)
    shade = np.clip(n @ light, 0, 1) * 0.75 + 0.2
    depth = tri[:, :, 2].mean(axis=1)
    order = np.argsort(-depth)  # far first (depth grows into the scene)
    cols = np.stack([0.35 * shade, 0.55 * shade, 0.85 * shade], axis=1)
    polys = tri[order][:, :, :2] * np.array([1, -1])  # y down -> up
    ax.add_collection(PolyCollection(polys, facecolors=cols[order], edgecolors="none"))
    lo, hi = polys.reshape(-1, 2).min(0), polys.reshape(-1, 2).max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2 * 1.05
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_aspect("equal")
    ax.axis("off")


def _plot_clusters(figs: dict, k: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    classes = list(figs)
    fig, axes = plt.subplots(len(classes), k, figsize=(2.0 * k, 1.9 * len(classes)))
    axes = np.atleast_2d(axes)
    for i, c in enumerate(classes):
        for j, (mesh, cam, size, model) in enumerate(figs[c]):
            ax = axes[i, j]
            _draw_mesh(ax, mesh, cam)
            ax.set_title(f"{size} objects ({model.replace('.npz', '')})", fontsize=7)
        axes[i, 0].text(-0.15, 0.5, c, transform=axes[i, 0].transAxes, rotation=90, va="center", ha="center",
                        fontsize=10)
    fig.suptitle("Medoids of 5 shape clusters per class (Full reconstructions), largest cluster first", fontsize=11)
    fig.tight_layout(rect=(0.02, 0, 1, 0.98))
    fig.savefig(_figure("shape_clusters"), dpi=100)
    plt.close(fig)


# =========================================================================== where the viewpoint misses come from


def _rendered_set(ann: Path) -> tuple[dict, dict]:
    """``gt.json``'s content beside a rendered set's ``annotations.json``, and its annotation id -> CAD model.

    Raises:
        SystemExit: either file is missing (one line).
    """
    if not (ann.is_file() and (ann.parent / "gt.json").is_file()):
        raise SystemExit(f"error: {ann} and a gt.json beside it are needed (render them with tools/viewpoints_cad.py)")
    return json.loads((ann.parent / "gt.json").read_text()), _model_of(ann)


def _model_of(annotations: Path) -> dict:
    """Annotation id -> CAD model name (the stem of its ``source``, else its ``object_id``)."""
    anns = json.loads(Path(annotations).read_text())["annotations"]
    return {a["id"]: Path(str(a.get("source") or a.get("object_id"))).stem for a in anns}


def _energy(S, cams, both, dist, cfg):
    """``(M,)`` the refinement's energy of ``cams`` on the rows of ``both`` (its terms and weights as configured)."""
    from carvi_torch.viewpoints import camera_fit

    return camera_fit.refinement_energy(cams.s[:, None, None] * cams.R[:, :2], cams.t, S, both.keypoints, both.visible,
                                        dist, silhouette_weight=cfg.silhouette_weight,
                                        silhouette_robust=cfg.silhouette_robust or None)


def _true_in_sfm_frame(true, final, ok, G, S, both):
    """The true cameras ``true (2N, canvas pixels)`` put in the SfM frame: rotation ``R_gt G^T`` (``G`` the class's
    fitted rotation, ``R_final G ~ R_gt``), scale over the median ratio of true to final scales (``ok`` rows), the
    offset that centres the projected shape on the visible keypoints; rows outside ``ok`` keep ``final``."""
    import torch

    from carvi_torch.cameras import ScaledOrthographic

    R = true.R @ G.to(true.R).T
    s = true.s / (true.s[ok] / final.s[ok]).median()
    w = (both.visible & torch.isfinite(S).all(-1)).to(R.dtype)
    P = ScaledOrthographic(R, s, torch.zeros_like(true.t)).project(torch.nan_to_num(S).to(R.dtype))
    t = ((torch.nan_to_num(both.keypoints).to(R.dtype) - P) * w[..., None]).sum(1) / w.sum(1).clamp(min=1)[:, None]
    keep = ok & (w.sum(1) > 0)
    return ScaledOrthographic(torch.where(keep[:, None, None], R, final.R), torch.where(keep, s, final.s),
                              torch.where(keep[:, None], t, final.t))


def _class_misses(coll, gt: dict, cfg, seed: int) -> dict | None:
    """Per original with a camera and a true one, under the class's one mean shape (degrees; energies; hull IoU):
    the final camera, the true camera in the SfM frame before (``true``) and after (``true_refined``) the
    refinement, and the depth-reversed mirror of the final camera through the symmetry plane (``mirror``)."""
    import torch

    from carvi_torch.cameras import ScaledOrthographic, geodesic_angle, geodesic_errors
    from carvi_torch.evaluation.viewpoint_metrics import viewpoint_report
    from carvi_torch.viewpoints import camera_fit, estimate_viewpoints, ground_truth_cameras, true_canvas_cameras
    from carvi_torch.viewpoints.choice import box_diagonal, hull_agreement, keypoint_rms
    from carvi_torch.viewpoints.refine import refine_with_shape

    gtc, _why = ground_truth_cameras(gt, coll)
    if gtc is None:
        return None
    n = len(coll)
    vp = estimate_viewpoints(coll, cfg, seed=seed)
    true = true_canvas_cameras(coll, vp.both, gtc)  # in canvas pixels, the mirrored copies' too
    ok = (vp.has_camera[:n] & torch.isfinite(gtc.R).flatten(1).all(1)).cpu()
    if int(ok.sum()) < 3:
        return None
    final, both, dist = vp.cameras, vp.both, vp.distances
    rep = viewpoint_report(final.R[:n].cpu(), gtc.R.cpu(), valid=ok)
    G = torch.tensor(rep["alignment"], dtype=final.R.dtype)
    S = camera_fit.supported_shape(vp.shape, both.visible, cfg.refine_min_support)
    ok2 = torch.cat([ok, ok]) & vp.has_camera.cpu() & torch.isfinite(true.R).flatten(1).all(1).cpu()
    start = _true_in_sfm_frame(true, final, ok2.to(final.R.device), G.to(final.R.device), S, both)
    refined = refine_with_shape(vp.shape, start, both, dist, cfg).cameras
    cams = {"final": final, "true": start, "true_refined": refined}
    if vp.reflection is not None:  # F R P: the mirrored shape as R sees it, depths reversed (a proper rotation)
        f = torch.tensor([1.0, 1.0, -1.0], dtype=final.R.dtype, device=final.R.device)
        cams["mirror"] = ScaledOrthographic(f[:, None] * (final.R @ vp.reflection.to(final.R)), final.s, final.t)
    idx = ok.nonzero().squeeze(1)
    dev = final.R.device
    part, part_dist, Rg = both[idx], dist[idx.to(dev)], gtc.R.cpu()[idx]
    diag = box_diagonal(part.masks).double().cpu()
    out = {"annotation_ids": [coll.annotation_ids[i] for i in idx.tolist()]}
    for name, c in cams.items():
        c = c[idx.to(dev)]
        out[name] = {"error": geodesic_errors(c.R.cpu(), Rg, G).double(),
                     "energy": _energy(S, c, part, part_dist, cfg).double().cpu(),
                     "hull": hull_agreement(S, c, part.masks),
                     "keypoint_rms": keypoint_rms(S, c, part.keypoints, part.visible).double().cpu() / diag}
    at = idx.to(dev)
    out["true_refined"]["to_final_deg"] = torch.rad2deg(geodesic_angle(refined.R[at].double(),
                                                                       final.R[at].double())).cpu()
    return out


def _spread(v) -> list:
    """``[min, median, max]`` of a 1-D tensor, 2 decimals (NaNs left out; ``[]`` when none is left); the median of
    an even count is the mean of the middle two (numpy's, as ``evaluate``'s summaries; torch's takes the lower)."""
    v = v.numpy()
    v = v[np.isfinite(v)]
    return [round(float(x), 2) for x in (v.min(), np.median(v), v.max())] if len(v) else []


def _misses_per_model(rows: dict, model: dict) -> dict:
    """Per CAD model of a class: the errors' ``[min, median, max]`` (degrees), the median angle between the
    camera refined from the truth and the final one, and the median energy, hull agreement (IoU) and keypoint RMS
    (over the box diagonal) of every camera."""
    import torch

    names = [model[a] for a in rows["annotation_ids"]]
    out = {}
    for m in sorted(set(names)):
        at = torch.tensor([i for i, x in enumerate(names) if x == m])
        med = lambda v: round(float(np.median(v[at].numpy())), 4)  # noqa: E731
        cams = [c for c in ("final", "true", "true_refined", "mirror") if c in rows]
        out[m] = {"n": len(at), **{f"{c}_deg": _spread(rows[c]["error"][at]) for c in cams},
                  "true_refined_to_final_deg": _spread(rows["true_refined"]["to_final_deg"][at]),
                  **{q: {c: med(rows[c][q]) for c in cams} for q in ("energy", "hull", "keypoint_rms")}}
    return out


def misses(args) -> int:
    """Where the viewpoint misses come from: per class of each rendered set (``--data``), the final cameras against
    the true cameras put in the SfM frame and refined with the same energy, and the mirrors of the final cameras;
    one mean shape per class (``sfm_groups=1``), under which every camera is scored."""
    import torch

    from carvi_torch.config import ViewpointConfig
    from carvi_torch.io.coco import load_coco

    torch.set_num_threads(1)
    cfg = ViewpointConfig(sfm_groups=1)  # the study is of one mean shape per class: every camera scored under it
    wanted = set(args.classes.split(",")) if args.classes else None
    record = {"command": _command(), "viewpoints": {"sfm_groups": cfg.sfm_groups},
              "note": "per CAD model: errors [min, median, max] in degrees after the class's "
              "fitted rotation; energy, hull (IoU of mask and projected hull of the mean shape), keypoint_rms (over "
              "the box diagonal): medians; cameras: final, true (the true camera in the SfM frame), true_refined "
              "(refined from it), mirror (the final camera's depth-reversed mirror through the symmetry plane)",
              "sets": {}}
    for ann in map(Path, args.data):
        gt, model = _rendered_set(ann)
        per_set = record["sets"][ann.parent.name] = {}
        print(f"{ann.parent.name}: models with a final median over {args.threshold:g} degrees\n"
              "| class | model | views | final | true refined | true refined to final | energy final / true / "
              "true refined | hull final / true / true refined | mirror: error, energy, hull |\n" + "|---" * 9 + "|")
        for cls, coll in sorted(load_coco(ann).collections.items()):
            if wanted and cls not in wanted:
                continue
            rows = _class_misses(coll, gt, cfg, args.seed)
            if rows is None:
                print(f"{cls}: fewer than 3 objects with a camera and a true one: left out")
                continue
            per_set[cls] = _misses_per_model(rows, model)
            for m, r in per_set[cls].items():
                if r["final_deg"] and r["final_deg"][1] > args.threshold:
                    e, h = r["energy"], r["hull"]
                    mirror = (f"{r['mirror_deg'][1]:.1f}, {e['mirror']:.0f}, {h['mirror']:.2f}" if "mirror" in e
                              else "-")
                    print(f"| {cls} | {m} | {r['n']} | {r['final_deg'][1]:.1f} | {r['true_refined_deg'][1]:.1f} | "
                          f"{r['true_refined_to_final_deg'][1]:.1f} | {e['final']:.0f} / {e['true']:.0f} / "
                          f"{e['true_refined']:.0f} | {h['final']:.2f} / {h['true']:.2f} / {h['true_refined']:.2f} | "
                          f"{mirror} |")
    from carvi_torch.io.outputs import write_record

    out = Path(args.out) if args.out else _record("misses")
    write_record(out, record, args.key)
    print(f"wrote {out}" + (f", key {args.key}" if args.key else ""))
    return 0


# =========================================================================== per-object shapes


def _own_shapes(S, G, X):
    """Two per-object shapes in the SfM frame, or ``None`` when fewer than 4 keypoints are shared: the object's true
    keypoints ``X (K, 3)`` (CAD frame) at the mean shape's size and centre (the mean shape's point where the object has
    none), and the mean shape ``S (K, 3)`` (SfM frame) stretched along the CAD frame's three axes by least squares onto
    ``X``, at its own size. ``G``: the class's fitted rotation (``R_sfm G ~ R_true``: a CAD point ``x`` is ``G x``)."""
    import torch

    Sc = S @ G
    both = torch.isfinite(Sc).all(1) & torch.isfinite(X).all(1)
    if int(both.sum()) < 4:
        return None
    cS, cX = Sc[both].mean(0), X[both].mean(0)
    A, B = Sc[both] - cS, X[both] - cX
    own = (X - cX) * (A.norm() / B.norm()) + cS
    axes = (A * B).sum(0) / (A * A).sum(0).clamp(min=1e-12)
    stretched = (Sc - cS) * axes
    stretched = stretched * (A.norm() / stretched[both].norm()) + cS
    return torch.where(torch.isfinite(own), own, Sc) @ G.T, stretched @ G.T, axes / axes.norm() * 3 ** 0.5


def _class_own_shapes(coll, gt: dict, cfg, seed: int) -> dict | None:
    """Per original with a camera and a true one: the final camera's error, and the errors of that camera refined
    again under the object's own shape and under the mean shape stretched onto it (:func:`_own_shapes`; degrees,
    after the class's fitted rotation), with the three stretch factors (unit RMS)."""
    import torch

    from carvi_torch.cameras import geodesic_errors
    from carvi_torch.evaluation.viewpoint_metrics import viewpoint_report
    from carvi_torch.viewpoints import estimate_viewpoints, ground_truth_cameras
    from carvi_torch.viewpoints.refine import refine_with_shape

    gtc, _why = ground_truth_cameras(gt, coll)
    if gtc is None:
        return None
    n, vp = len(coll), estimate_viewpoints(coll, cfg, seed=seed)
    ok = (vp.has_camera[:n].cpu() & torch.isfinite(gtc.R.cpu()).flatten(1).all(1))
    if int(ok.sum()) < 3:
        return None
    Rt = gtc.R.cpu()
    G = torch.tensor(viewpoint_report(vp.cameras.R[:n].cpu(), Rt, valid=ok)["alignment"], dtype=Rt.dtype)
    S, names = vp.shape.cpu().to(Rt.dtype), coll.meta.keypoint_names
    out: dict = {k: [] for k in ("annotation_ids", "final", "own_shape", "stretched", "axes")}
    for i in ok.nonzero().squeeze(1).tolist():
        kp = gt["models"][gt["annotations"][str(coll.annotation_ids[i])]["model"]]["keypoints"]
        shapes = _own_shapes(S, G, torch.tensor([kp.get(k, [float("nan")] * 3) for k in names], dtype=S.dtype))
        if shapes is None:
            continue
        row = torch.tensor([i], device=vp.cameras.R.device)
        cam, err = vp.cameras[row], (lambda c: float(geodesic_errors(c.R.cpu().to(Rt), Rt[i:i + 1], G)[0]))
        out["annotation_ids"].append(coll.annotation_ids[i])
        out["final"].append(err(cam))
        for key, shape in zip(("own_shape", "stretched"), shapes[:2]):
            out[key].append(err(refine_with_shape(shape.to(cam.R), cam, vp.both[row], vp.distances[row], cfg).cameras))
        out["axes"].append([round(float(a), 3) for a in shapes[2]])
    return out


def own_shapes(args) -> int:
    """Whether a class's misses are its shape's: per class of each rendered set (``--data``), each view's final camera
    refined again under its object's own keypoints and under the mean shape stretched per axis onto them; per CAD
    model the medians. One mean shape per class (``sfm_groups=1``)."""
    import numpy as np
    import torch

    from carvi_torch.config import ViewpointConfig
    from carvi_torch.io.coco import load_coco
    from carvi_torch.io.outputs import write_record

    torch.set_num_threads(1)
    cfg = ViewpointConfig(sfm_groups=1)
    wanted = set(args.classes.split(",")) if args.classes else None
    record = {"command": _command(), "viewpoints": {"sfm_groups": 1}, "sets": {},
              "note": "median geodesic error (degrees, after the class's fitted rotation) of the final cameras, and of "
                      "the same cameras refined again under each object's own keypoints (own_shape) and under the "
                      "mean shape stretched along the CAD axes onto them (stretched); per class and per CAD model"}
    print("| set | class | views | final | own shape | stretched (per axis) |\n|---|---|---|---|---|---|")
    for ann in map(Path, args.data):
        gt, model = _rendered_set(ann)
        per_set = record["sets"][ann.parent.name] = {}
        for cls, coll in sorted(load_coco(ann).collections.items()):
            rows = None if wanted and cls not in wanted else _class_own_shapes(coll, gt, cfg, args.seed)
            if rows is None:
                continue
            med = {k: round(float(np.median(rows[k])), 2) for k in ("final", "own_shape", "stretched")}
            per_model: dict = {}
            for a, *e in zip(rows["annotation_ids"], rows["final"], rows["own_shape"], rows["stretched"]):
                per_model.setdefault(model[a], []).append(e)
            per_set[cls] = {"n": len(rows["final"]), **med, "models": {
                m: [round(float(v), 2) for v in np.median(np.array(e), axis=0)] for m, e in sorted(per_model.items())}}
            print(f"| {ann.parent.name} | {cls} | {len(rows['final'])} | {med['final']:.1f} | {med['own_shape']:.1f} | "
                  f"{med['stretched']:.1f} |")
    out = Path(args.out) if args.out else _record("own_shapes")
    write_record(out, record, args.key)
    print(f"wrote {out}" + (f", key {args.key}" if args.key else ""))
    return 0


# =========================================================================== metric step


def step(args) -> int:
    """Evaluate the same reconstructions at two sampling steps; per-object differences and times."""
    bench = Path(args.bench)
    data = _data_dir(bench)
    steps = [float(v) for v in args.steps.split(",")]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    recon = [f"--recon={m}={bench / d}" for m, d in (("Full", "run_full"),)]
    times, res = {}, {}
    for st in steps:
        out = bench / "step" / f"s{st:g}"
        argv = [sys.executable, "-m", "carvi_torch.evaluate", "--data", str(data / "annotations.json"), "--split",
                "test", "--quiet", "--jobs", "1", "--step-percent", str(st), "--classes", args.classes,
                "--out", str(out), "--baselines", *recon]
        print("  " + " ".join(shlex.quote(a) for a in argv), flush=True)
        c0 = cpu_seconds(children=True)
        subprocess.run(argv, env=env, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
        times[f"{st:g}"] = round(cpu_seconds(children=True) - c0, 1)
        res[f"{st:g}"] = json.loads((out / "results.json").read_text())
    a, b = (res[f"{st:g}"] for st in steps)
    diffs = {}
    for m in a["methods"]:
        d = [b["objects"][k][m]["error_percent"] - r[m]["error_percent"] for k, r in a["objects"].items()
             if isinstance(r.get(m), dict) and r[m].get("error_percent") is not None
             and b["objects"][k][m].get("error_percent") is not None]
        d = np.array(d)
        diffs[m] = {"n": int(len(d)), "mean_difference_pp": float(d.mean()),
                    "mean_abs_difference_pp": float(np.abs(d).mean()),
                    "max_abs_difference_pp": float(np.abs(d).max()),
                    "class_mean_difference_pp": {c: b["classes"][c][m]["mean"] - a["classes"][c][m]["mean"]
                                                 for c in a["classes"] if a["classes"][c][m]["mean"] is not None}}
    out = {"command": _command(), "classes": args.classes.split(","), "steps_percent": steps,
           "cpu_seconds": times, "difference": diffs,
           "note": f"errors at step {steps[1]:g}% minus errors at step {steps[0]:g}% (percentage points)"}
    from carvi_torch.io.outputs import write_json

    write_json(_record("metric_step"), out)
    print(json.dumps({k: out[k] for k in ("cpu_seconds", "difference")}, indent=1))
    return 0


# =========================================================================== frames


def _arrow(ax, p, q, color, text, dx=0.0, dy=0.0):
    from matplotlib.patches import FancyArrowPatch

    ax.add_patch(FancyArrowPatch(p, q, arrowstyle="-|>", mutation_scale=14, lw=2, color=color))
    ax.text(q[0] + dx, q[1] + dy, text, color=color, fontsize=11, ha="center", va="center")


def _save_figure(fig, out: str | Path, dpi: int) -> None:
    """Lay out ``fig``, write it to ``out`` (its folder made), close it and say so."""
    import matplotlib.pyplot as plt

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    print(f"wrote {out}")


def frames(args) -> int:
    """docs/figures/frames.png: the image, camera and voxel-grid frames of carvi_torch (docs/conventions.md)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 5.5))
    _draw_pixel_frame(axes[0])
    _draw_camera_frame(axes[1])
    _draw_voxel_frame(fig, axes[2])
    _save_figure(fig, args.out, 110)
    return 0


def _draw_pixel_frame(ax) -> None:
    """(a) of frames.png: image and canvas pixels, their centres and the mask."""
    from matplotlib.patches import Rectangle

    ax.set_title("(a) image and canvas pixels")
    for i in range(5):
        for j in range(6):
            ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=0.5, color="0.6"))
            ax.plot(j, i, ".", color="0.4", ms=3)
    ax.add_patch(Rectangle((1.5, 0.5), 3, 3, color="tab:orange", alpha=0.35))
    _arrow(ax, (0, 0), (6.2, 0), "tab:red", "x", 0.3, 0)
    _arrow(ax, (0, 0), (0, 5.2), "tab:green", "y", 0, 0.3)
    ax.plot(0, 0, "o", color="k", ms=5)
    ax.text(0.1, -0.8, "origin = centre of pixel [0, 0]", fontsize=9)
    ax.text(2.5, 4.9, "pixel [i, j] has its centre at (x=j, y=i)", fontsize=9, ha="center")
    ax.text(3.0, 2.0, "mask", ha="center", fontsize=9)
    ax.text(2.5, 5.5, "canvas = a * image + b  (per instance)", fontsize=9, ha="center")
    ax.set_xlim(-1.2, 6.8)
    ax.set_ylim(6.0, -1.3)
    ax.set_aspect("equal")
    ax.axis("off")


def _draw_camera_frame(ax) -> None:
    """(b) of frames.png: the scaled orthographic camera, its image plane and depth axis."""
    ax.set_title("(b) scaled orthographic camera")
    ax.plot([-2.5, 2.5], [2.2, 2.2], color="k", lw=3)
    ax.text(2.6, 2.2, "image plane", fontsize=9, va="center")
    obj = np.array([[-0.8, -0.6], [0.9, -0.4], [0.6, 0.7], [-0.7, 0.5], [-0.8, -0.6]])
    ax.fill(obj[:, 0], obj[:, 1] - 0.5, color="tab:blue", alpha=0.3)
    for x in (-0.8, 0.9):
        ax.plot([x, x], [2.2, -1.6], ls=":", color="0.5")
    _arrow(ax, (-2.2, 2.2), (-1.0, 2.2), "tab:red", "x (u)", 0, 0.25)
    _arrow(ax, (-2.2, 2.2), (-2.2, -0.8), "tab:purple", "z = depth\n(into scene, R[2])", 0.1, -0.45)
    ax.text(0.0, -1.9, "uv = s * X R[:2]^T + t     z = s * X . R[2]", ha="center", fontsize=10)
    ax.text(0.0, -2.4, "R rows: image x, image y (down), view direction", ha="center", fontsize=9)
    ax.text(0.0, 2.7, "y (down) points out of the page", ha="center", fontsize=9, color="tab:green")
    ax.set_xlim(-3, 3.4)
    ax.set_ylim(-2.8, 3.0)
    ax.set_aspect("equal")
    ax.axis("off")


def _draw_voxel_frame(fig, flat_ax) -> None:
    """(c) of frames.png: the voxel grid in the reference camera frame, on a 3-D axes in place of ``flat_ax``."""
    ax = fig.add_subplot(1, 3, 3, projection="3d")
    flat_ax.axis("off")
    ax.set_title("(c) voxel grid (D, H, W), reference camera frame", pad=4)
    n = 4
    for d in range(n):
        for h in range(n):
            ax.plot([0, n - 1], [d, d], [h, h], color="0.8", lw=0.6)
            ax.plot([d, d], [0, n - 1], [h, h], color="0.8", lw=0.6)
    pts = np.array([[w, d, h] for d in range(n) for h in range(n) for w in range(n)])
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=6, color="0.4")
    ax.quiver(0, 0, 0, n, 0, 0, color="tab:red")
    ax.quiver(0, 0, 0, 0, n, 0, color="tab:purple")
    ax.quiver(0, 0, 0, 0, 0, n, color="tab:green")
    ax.text(n, -0.6, 0, "x: index w", color="tab:red")
    ax.text(0.3, n, 1.2, "z (depth): index d", color="tab:purple")
    ax.text(-0.5, 0, n + 0.5, "y (down): index h", color="tab:green")
    ax.text2D(0.02, 0.02, "(x, y, z, 1) = voxel_to_camera @ (d, h, w, 1)\n"
              "a column (h, w) is the ray of one reference pixel", transform=ax.transAxes, fontsize=9)
    ax.set_zlim(n, 0)  # y down
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()


def canonical(args) -> int:
    """docs/figures/canonical_frame.png: the canonical object frame (the shipped aeroplane template) and
    PASCAL3D+'s azimuth and elevation of one camera, drawn with the package's own functions."""
    import math

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from carvi_torch.cameras import rotation_from_azimuth_elevation_roll
    from carvi_torch.viewpoints.frame import load_templates

    pts = load_templates()["classes"]["aeroplane"]["keypoints"]
    az, el = 40.0, 25.0
    R = rotation_from_azimuth_elevation_roll(torch.tensor(math.radians(az), dtype=torch.float64),
                                             torch.tensor(math.radians(el), dtype=torch.float64),
                                             torch.tensor(0.0, dtype=torch.float64)).numpy()
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.4))
    _draw_camera_angles(axes[:2], pts, R, az, el)
    _draw_camera_view(axes[2], pts, R)
    fig.suptitle("The canonical frame of the PASCAL3D+ classes (shipped aeroplane template): +z up, front towards "
                 "-y.   R = diag(1, -1, -1) Rz(roll) Rx(elevation - 90) Rz(-azimuth)")
    _save_figure(fig, args.out, 100)
    return 0


def _draw_camera_angles(axes, pts: dict, R: np.ndarray, az: float, el: float) -> None:
    """(a), (b) of canonical_frame.png: keypoints ``pts`` (name -> xyz) and the camera of rotation ``R (3, 3)``
    seen from above (its azimuth ``az``) and from the side in its vertical plane (its elevation ``el``), degrees."""
    import math

    P = np.array(list(pts.values()))
    cam = -R[2]  # unit vector from the object towards the camera
    views = (("(a) from above: x right, y up the page", 0, 1, "x", "y"),
             ("(b) from the side, in the camera's vertical plane", None, 2, "horizontal", "z (up)"))
    for ax, (title, i, j, xl, yl) in zip(axes, views):
        h = np.array([cam[0], cam[1], 0.0]) / math.hypot(cam[0], cam[1])
        X = P[:, i] if i is not None else P @ h
        Y = P[:, j]
        ax.scatter(X, Y, color="tab:blue", s=20, zorder=3)
        for (name, p), x, y in zip(pts.items(), X, Y):
            ax.annotate(name, (x, y), fontsize=7, color="0.3", xytext=(3, 3), textcoords="offset points")
        c = (cam[i], cam[j]) if i is not None else (float(cam @ h), cam[2])
        ax.plot([0, 0.5 * c[0]], [0, 0.5 * c[1]], color="tab:orange", lw=1.5)
        ax.plot(0.5 * c[0], 0.5 * c[1], "s", color="tab:orange", ms=9)
        ax.text(0.5 * c[0], 0.5 * c[1] + 0.03, "camera", color="tab:orange", ha="center")
        if i is not None:  # azimuth: from the front (-y), counter-clockwise seen from above
            t = np.radians(np.linspace(0, az, 30))
            ax.plot(0.25 * np.sin(t), -0.25 * np.cos(t), color="tab:orange")
            ax.text(0.04, -0.19, f"azimuth {az:.0f}", color="tab:orange")
            ax.annotate("", (0, -0.42), (0, 0), arrowprops=dict(arrowstyle="-|>", ls="--"))
            ax.text(0.01, -0.46, "front = -y", fontsize=9)
        else:
            t = np.radians(np.linspace(0, el, 20))
            ax.plot(0.3 * np.cos(t), 0.3 * np.sin(t), color="tab:orange")
            ax.text(0.32, 0.05, f"elevation {el:.0f}", color="tab:orange")
            ax.axhline(0, color="0.7", lw=0.8)
        ax.set_title(title)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_xlim(-0.55, 0.55)
        ax.set_ylim(-0.55, 0.55)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)


def _draw_camera_view(ax, pts: dict, R: np.ndarray) -> None:
    """(c) of canonical_frame.png: what the camera of rotation ``R (3, 3)`` sees of the keypoints ``pts``
    (``uv = X R[:2]^T``, image y down, roll 0)."""
    P = np.array(list(pts.values()))
    uv = P @ R[:2].T
    ax.scatter(uv[:, 0], uv[:, 1], color="tab:blue", s=20)
    for (name, _), (u, v) in zip(pts.items(), uv):
        ax.annotate(name, (u, v), fontsize=7, color="0.3", xytext=(3, 3), textcoords="offset points")
    ax.set_ylim(0.5, -0.5)
    ax.set_xlim(-0.5, 0.5)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_title("(c) what it sees (image y down), roll 0")


# =========================================================================== main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="study", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--bench", default=str(ROOT / "outputs" / "benchmark"), help="benchmark working directory")
    common.add_argument("--jobs", type=int, default=2, help="processes at once")
    common.add_argument("--seed", type=int, default=0)
    p = sub.add_parser("frames", help="the figure of the image, camera and voxel-grid frames (docs/conventions.md)")
    p.add_argument("--out", default=str(FIGURES / "frames.png"))
    p = sub.add_parser("canonical", help="the canonical object frame and its angles (docs/conventions.md)")
    p.add_argument("--out", default=str(FIGURES / "canonical_frame.png"))
    p = sub.add_parser("ranking", parents=[common], help="(a) top/random/best proposal, (b) pool size")
    p.add_argument("--step-percent", type=float, default=2.0, help="metric step, %% of the GT bbox diagonal")
    p.add_argument("--views-per-model", type=int, default=5, help="test views per model to study (subset)")
    p.add_argument("--classes", help="comma-separated subset")
    p.add_argument("--fresh", action="store_true", help="recompute the per-proposal errors even if cached")
    p.add_argument("--figures", default=str(FIGURES),
                   help="folder of ranking.png and pool_size.png (default docs/figures)")
    p.add_argument("--record", default="ranking", help="the record's name: outputs/studies/studies_<NAME>.json")
    p.add_argument("--out", help="instead, write the record under a key of this records file (e.g. "
                                 "docs/data/benchmark_synthetic.json), its other keys kept")
    p.add_argument("--key", help="the key of --out (default: the --record name)")
    p = sub.add_parser("threshold", parents=[common], help="(c) error against the clustering threshold")
    p.add_argument("--classes", default="aeroplane,car,chair,sofa")
    p.add_argument("--thresholds", default="15,20,25,30,35,40,45")
    p.add_argument("--step-percent", type=float, default=1.0)
    p = sub.add_parser("viewpoints", parents=[common], help="(d) viewpoint error per class, SfM vs refined")
    p.add_argument("--bench-json", default=str(BENCHMARK_JSON), help="the synthetic benchmark's JSON record")
    p = sub.add_parser("clusters", parents=[common], help="shape clusters (K-medoids) per class")
    p.add_argument("--k", type=int, default=5)
    p.add_argument("--points", type=int, default=1024, help="surface samples per reconstruction")
    p = sub.add_parser("step", parents=[common], help="metric sampling step: 0.5%% vs 1%% on a subset")
    p.add_argument("--classes", default="bicycle,car,chair,sofa")
    p.add_argument("--steps", default="0.5,1.0")
    rendered = argparse.ArgumentParser(add_help=False)  # the studies of rendered sets with their true cameras
    rendered.add_argument("--data", nargs="+", required=True, metavar="ANNOTATIONS",
                          help="annotations.json of rendered sets, each with its gt.json (tools/viewpoints_cad.py's "
                               "renders)")
    rendered.add_argument("--classes", help="comma-separated subset")
    rendered.add_argument("--seed", type=int, default=0, help="the pipeline's seed (the mixture's starts)")
    rendered.add_argument("--out", help="the JSON record (default outputs/studies/studies_<study>.json, dashes as "
                                        "underscores: studies_misses.json, studies_own_shapes.json)")
    rendered.add_argument("--key", help="write the record under this key of --out's JSON object, its other keys kept")
    p = sub.add_parser("misses", parents=[rendered], help="where the viewpoint misses come from: final cameras "
                                                          "against the true ones refined (docs/viewpoints.md)")
    p.add_argument("--threshold", type=float, default=10.0, help="print the models whose final median error "
                                                                 "(degrees) exceeds this")
    sub.add_parser("own-shapes", parents=[rendered], help="whether the misses are the shapes': the final cameras "
                   "refined again under each object's own keypoints and a per-axis stretch of the mean shape")
    args = ap.parse_args(argv)
    if args.study == "ranking" and args.key and not args.out:
        ap.error("ranking: --key names a key of --out's records file; give --out too")
    return {"misses": misses, "own-shapes": own_shapes, "frames": frames, "canonical": canonical, "ranking": ranking,
            "threshold": threshold,
            "viewpoints": viewpoints, "clusters": clusters, "step": step}[args.study](args)


if __name__ == "__main__":
    sys.exit(main())
