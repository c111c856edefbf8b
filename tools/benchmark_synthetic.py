"""The paper's synthetic benchmark (its Table 1) on the PASCAL3D+ CAD models, with one command.

Steps (each skipped when its output exists, unless ``--fresh``; renders only when made with the same
settings, models (names and content) and left/right names,
:func:`carvi_torch.synthetic.render.render_mismatch`; a finished
reconstruction only when its ``config.yaml`` names these renders and the method's and ``--set`` settings,
else it is made again over its folder):

1. **Render** every model of ``--models`` (73 PASCAL3D+ CAD models, 12 classes) from
   ``--pool + --test-views`` cameras drawn like photographs
   (:func:`carvi_torch.synthetic.render_dataset`): the first ``--test-views`` renders of each
   model are ``split=test``, the others ``split=pool``.
2. **Reconstruct** every test render with ``python -m carvi_torch.reconstruct
   references=test`` (surrogates come from other models only: renders of one model share an
   ``object_id``), once per method: ``Full``; ``-CRef`` (``viewpoints.refine=false``); ``-SImp``
   (``carve.imprint=false``); ``oracle`` (``study.cameras=gt``). ``Full`` also saves every
   proposal and its score (``study.save_proposals=true study.keep_all_scores=true``, off by
   default) for ``tools/studies.py``. ``--jobs`` runs that many at once, each with ``torch``
   threads = cores / jobs.
3. **Evaluate** with ``python -m carvi_torch.evaluate --baselines --split test`` (adds Puffball
   and SFMc): the symmetric RMS error in percent of the ground-truth bounding-box diagonal,
   surfaces sampled every ``--step-percent`` of that diagonal. With ``--jobs 2`` the classes
   are split in two evaluate processes and their results merged.
4. **Write** ``benchmark_synthetic.json`` into ``--results`` (default ``docs/data/``, the record
   docs/results.md cites: everything, with the command line, the machine, wall and CPU times per
   step), and ``table1.md`` (per class + mean, the paper's numbers beside ours) and
   ``viewpoints.md`` into ``--out``. With ``--classes`` the names end in ``_<classes>``. With
   ``--key`` the record goes under that key of the JSON file, its other keys kept (a run
   without ``--key`` writes the file's top level and keeps the keyed records too).

``--seed 0,1`` runs steps 1-3 once per seed (into ``--out/seed<S>``) and ``table1.md`` then
gives, per class and method, every seed's mean error, missing objects, and the mean over the
seeds. The small-class shape benchmark of docs/results.md renders 8 views per model and
reconstructs and evaluates the first 2 of each (``--pool 6 --test-views 2``, records ``shapes_cad8*``):
every render still takes part in SfM and may serve as another model's surrogate, as in the 30-view
benchmark.

Same seed, same numbers: the renders depend only on ``(seed, model name)``, the
reconstructions on ``seed``.

Command line (``--help`` lists every option); the numbers of docs/results.md:

    python tools/benchmark_synthetic.py [--out outputs/benchmark] [--results docs/data] [--key KEY] [--jobs 2]
                                        [--pool 20] [--test-views 5] [--seed 0[,1]]
                                        [--methods Full,-CRef,-SImp,oracle] [--classes C1,C2]
                                        [--set KEY=VALUE ...] [--no-baselines] [--fresh]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

from carvi_torch.runtime import cpu_seconds

ROOT = Path(__file__).resolve().parents[1]

#: The paper's Table 1 (symmetric RMS, % of the GT bbox diagonal) for the 12 PASCAL3D+ classes and its mean
#: over its 20 classes.
PAPER = {
    "aeroplane": {"Full": 3.58, "-CRef": 4.94, "-SImp": 3.95, "Puffball": 9.64, "SFMc": 5.79},
    "bicycle": {"Full": 4.30, "-CRef": 3.26, "-SImp": 4.75, "Puffball": 10.51, "SFMc": 6.56},
    "boat": {"Full": 5.91, "-CRef": 6.78, "-SImp": 6.05, "Puffball": 8.81, "SFMc": 6.52},
    "bottle": {"Full": 8.09, "-CRef": 10.77, "-SImp": 8.53, "Puffball": 6.25, "SFMc": 12.13},
    "bus": {"Full": 6.45, "-CRef": 6.10, "-SImp": 6.49, "Puffball": 11.02, "SFMc": 7.34},
    "car": {"Full": 3.04, "-CRef": 6.33, "-SImp": 3.10, "Puffball": 11.07, "SFMc": 3.22},
    "chair": {"Full": 5.36, "-CRef": 5.73, "-SImp": 6.06, "Puffball": 8.13, "SFMc": 7.37},
    "diningtable": {"Full": 8.97, "-CRef": 12.57, "-SImp": 14.30, "Puffball": 8.67, "SFMc": 9.52},
    "motorbike": {"Full": 4.12, "-CRef": 4.24, "-SImp": 4.16, "Puffball": 9.24, "SFMc": 5.32},
    "sofa": {"Full": 6.11, "-CRef": 6.24, "-SImp": 6.31, "Puffball": 8.06, "SFMc": 5.75},
    "train": {"Full": 15.73, "-CRef": 20.55, "-SImp": 16.19, "Puffball": 17.01, "SFMc": 17.47},
    "tvmonitor": {"Full": 9.73, "-CRef": 10.45, "-SImp": 10.28, "Puffball": 9.67, "SFMc": 10.08},
}
PAPER_MEAN_20 = {"Full": 6.96, "-CRef": 8.01, "-SImp": 7.53, "Puffball": 9.57, "SFMc": 9.40}

#: Methods: name -> reconstruct overrides.
METHODS = {
    "Full": ["study.save_proposals=true", "study.keep_all_scores=true"],  # for tools/studies.py
    "-CRef": ["viewpoints.refine=false"],
    "-SImp": ["carve.imprint=false"],
    "oracle": ["study.cameras=gt"],
}
PYTHON = sys.executable


# --------------------------------------------------------------------------- helpers


def _env(threads: int) -> dict:
    env = dict(os.environ)
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[k] = str(threads)
    return env


def run_parallel(commands: list[tuple[str, list[str], Path]], jobs: int, threads: int) -> dict[str, dict]:
    """Run ``(name, argv, log)`` commands, ``jobs`` at a time; wall and CPU seconds per command."""
    pending = list(commands)
    running: dict[str, tuple[subprocess.Popen, float, object]] = {}
    done: dict[str, dict] = {}
    while pending or running:
        while pending and len(running) < jobs:
            name, argv, log = pending.pop(0)
            log.parent.mkdir(parents=True, exist_ok=True)
            fh = open(log, "w")
            print(f"  start {name}: {' '.join(shlex.quote(a) for a in argv)}", flush=True)
            running[name] = (subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, env=_env(threads),
                                              cwd=ROOT), time.perf_counter(), fh)
        time.sleep(0.5)
        for name in list(running):
            proc, t0, fh = running[name]
            if proc.poll() is None:
                continue
            fh.close()
            wall = time.perf_counter() - t0
            done[name] = {"wall_s": round(wall, 1), "returncode": proc.returncode}
            del running[name]
            print(f"  done  {name} in {wall:.0f} s (exit {proc.returncode})", flush=True)
            if proc.returncode != 0:
                for other, _, ofh in running.values():  # stop the others before giving up
                    other.terminate()
                    other.wait()
                    ofh.close()
                raise RuntimeError(f"{name} failed (exit {proc.returncode}); see {log_of(commands, name)}")
    return done


def log_of(commands, name):
    return next(str(c[2]) for c in commands if c[0] == name)


# --------------------------------------------------------------------------- steps


def _render_settings(pool: int, test_views: int, seed: int) -> dict:
    """``render_dataset``'s arguments that change the renders (the cache check and the render use them)."""
    return {"views": pool + test_views, "test_views": test_views, "seed": seed}


def render(models: list, data_dir: Path, pool: int, test_views: int, seed: int) -> dict:
    """Render the dataset (step 1) from the loaded ``models``; returns ``render_dataset``'s summary."""
    import torch

    from carvi_torch.synthetic import render_dataset

    torch.manual_seed(seed)
    return render_dataset(models, data_dir, progress=False, **_render_settings(pool, test_views, seed))


def _render_mismatch(data_dir: Path, models: list, pool: int, test_views: int, seed: int) -> str | None:
    """Why ``data_dir`` does not hold the renders step 1 would make of ``models`` (other settings, models or
    left/right names: :func:`~carvi_torch.synthetic.render.render_mismatch`; no ``gt.json``), or ``None``.
    Such renders are made again, and their reconstructions redone."""
    from carvi_torch.synthetic.render import read_render_info, render_mismatch

    if not (data_dir / "gt.json").is_file():
        return "no gt.json"
    return render_mismatch(read_render_info(data_dir), models, **_render_settings(pool, test_views, seed))


def merge_evaluations(parts: list[dict]) -> dict:
    """Merge ``evaluate`` results computed on disjoint class subsets: the per-object and per-class fields joined,
    the means over classes and the quality study computed again (a joint evaluation's result, but ``seconds``)."""
    from carvi_torch.evaluate import mean_over_classes
    from carvi_torch.evaluation import reliability

    out = dict(parts[0])
    for key in ("objects", "classes", "viewpoints", "compared", "viewpoint_coverage"):  # keyed by object or class
        out[key] = {k: v for p in parts for k, v in (p.get(key) or {}).items()}
    for key in ("camera_problems",):  # per method, then per class
        out[key] = {}
        for p in parts:
            for m, per in (p.get(key) or {}).items():
                out[key].setdefault(m, {}).update(per)
    out["unfinished"] = sorted({m for p in parts for m in p.get("unfinished") or ()})
    out["classes"] = dict(sorted(out["classes"].items()))
    out["mean_over_classes"] = mean_over_classes(out["classes"], out["methods"], "mean")
    out["mean_over_classes_compared"] = mean_over_classes(out["classes"], out["methods"], "compared_mean")
    out["quality"] = reliability.quality_vs_error(out)
    out["seconds"] = [p["seconds"] for p in parts]
    return out



def _covered(res: dict, m: str) -> int:
    """The classes for which method ``m`` has a mean."""
    return sum(1 for c in res["classes"].values() if c[m]["mean"] is not None)

def table1(res: dict) -> str:
    """Markdown: our per-class means (bold = best of our methods) with the paper's in brackets."""
    methods = [m for m in ("Full", "-CRef", "-SImp", "Puffball", "SFMc", "oracle") if m in res["methods"]]
    head = "| class (objects) | " + " | ".join(methods) + " |"
    lines = [head, "|---" * (len(methods) + 1) + "|"]
    compared = [m for m in methods if m != "oracle"]
    for cls, row in res["classes"].items():
        vals = {m: row[m]["mean"] for m in methods}
        finite = [vals[m] for m in compared if vals[m] is not None]
        best = min(finite) if finite else None
        cells = []
        for m in methods:
            v = vals[m]
            txt = "-" if v is None else f"{v:.2f}"
            if v is not None and v == best:
                txt = f"**{txt}**"
            paper = PAPER.get(cls, {}).get(m)
            if paper is not None:
                txt += f" ({paper:.2f})"
            miss = row[m]["missing"]
            if miss:
                txt += f" [{miss} missing]"
            cells.append(txt)
        n = max(row[m]["count"] + row[m]["missing"] for m in methods)
        lines.append(f"| {cls} ({n}) | " + " | ".join(cells) + " |")
    means = res["mean_over_classes"]
    common = common_classes(res, methods)
    cmean = {m: sum(res["classes"][c][m]["mean"] for c in common) / len(common) if common else None for m in methods}
    paper_c = {m: sum(PAPER[c][m] for c in common if c in PAPER) / max(1, sum(c in PAPER for c in common))
               for m in compared}
    lines.append(f"| **mean, the {len(common)} classes every method covers** | " + " | ".join(
        ("-" if cmean[m] is None else f"**{cmean[m]:.2f}**") + (f" ({paper_c[m]:.2f})" if m in paper_c else "")
        for m in methods) + " |")
    lines.append("| mean, every class the method covers | " + " | ".join(
        ("-" if means[m] is None else f"{means[m]:.2f}") + f" ({_covered(res, m)})" for m in methods) + " |")
    lines.append("| paper, mean of its 20 classes | " + " | ".join(
        f"{PAPER_MEAN_20[m]:.2f}" if m in PAPER_MEAN_20 else "-" for m in methods) + " |")
    return "\n".join(lines)


def common_classes(res: dict, methods) -> list[str]:
    """Classes where every method in ``methods`` has a mean error (the fair set for a mean)."""
    return [c for c, row in res["classes"].items() if all(row[m]["mean"] is not None for m in methods)]


def acceptance(res: dict) -> dict:
    """The acceptance checks of the benchmark (Full vs baselines and ablations).

    Means are compared over the classes every compared method covers (a class a method has no
    reconstruction for would otherwise drop out of its mean only); a class without a Full result
    counts as a loss in the per-class count.
    """
    means = res["mean_over_classes"]
    cls = res["classes"]
    compared = [m for m in ("Full", "-CRef", "-SImp", "Puffball", "SFMc") if m in means]
    common = common_classes(res, compared)
    cmean = {m: float(sum(cls[c][m]["mean"] for c in common) / len(common)) if common else None for m in compared}

    def beats(c, b):
        return cls[c]["Full"]["mean"] is not None and cls[c][b]["mean"] is not None and \
            cls[c]["Full"]["mean"] < cls[c][b]["mean"]

    baselines = [b for b in ("Puffball", "SFMc") if b in means]
    checks = {
        "classes": len(cls),
        "classes_with_full": sum(1 for c in cls.values() if c["Full"]["mean"] is not None),
        "common_classes": common,
        "mean_over_common_classes": cmean,
        "full_mean_over_its_classes": means.get("Full"),
        "full_mean_at_most_7": means.get("Full") is not None and means["Full"] <= 7.0,
        "full_beats_baselines_on_common_mean": bool(common) and all(cmean["Full"] < cmean[b] for b in baselines),
        "classes_full_beats_puffball": sum(beats(c, "Puffball") for c in cls) if "Puffball" in means else None,
        "classes_full_beats_sfmc": sum(beats(c, "SFMc") for c in cls) if "SFMc" in means else None,
        "classes_full_beats_both": sum(all(beats(c, b) for b in baselines) for c in cls),
    }
    checks["full_beats_both_in_8_of_12"] = checks["classes_full_beats_both"] >= 8
    for abl in ("-CRef", "-SImp"):
        if abl in cmean and common:
            checks[f"{abl}_worse_than_full_on_common_mean"] = cmean[abl] > cmean["Full"]
    return checks


# --------------------------------------------------------------------------- several seeds


def seeds_table(per_seed: dict) -> str:
    """Markdown: per class, each method's mean error at every seed and over the seeds, with missing objects.

    ``per_seed``: ``{seed: evaluate results}`` (:func:`merge_evaluations`). A class's seed mean is the
    mean of its per-seed means; the last row is the mean over the classes (per seed, and of those).
    """
    seeds = list(per_seed)
    first = per_seed[seeds[0]]
    methods = [m for m in ("Full", "-CRef", "-SImp", "Puffball", "SFMc", "oracle") if m in first["methods"]]
    cols = [f"{m} s{s}" for m in methods for s in seeds] + [f"{m} mean" for m in methods]
    lines = ["| class (objects per seed) | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for cls in first["classes"]:
        cells, means = [], []
        for m in methods:
            vals = []
            for s in seeds:
                row = per_seed[s]["classes"].get(cls, {}).get(m, {})
                v, miss = row.get("mean"), row.get("missing", 0)
                vals.append(v)
                cells.append(("-" if v is None else f"{v:.2f}") + (f" [{miss} missing]" if miss else ""))
            ok = [v for v in vals if v is not None]
            means.append(f"{sum(ok) / len(ok):.2f}" if len(ok) == len(vals) else "-")
        row0 = first["classes"][cls][methods[0]]
        lines.append(f"| {cls} ({row0['count'] + row0['missing']}) | " + " | ".join(cells + means) + " |")
    cells, means = [], []
    for m in methods:
        vals = [per_seed[s]["mean_over_classes"].get(m) for s in seeds]
        cells += ["-" if v is None else f"**{v:.2f}**" for v in vals]
        means.append(f"**{sum(vals) / len(vals):.2f}**" if all(v is not None for v in vals) else "-")
    lines.append(f"| **mean, {len(first['classes'])} classes** | " + " | ".join(cells + means) + " |")
    return "\n".join(lines)


def seeds_record(per_seed: dict, reports: dict, command: str) -> dict:
    """The JSON record of a several-seed run: per seed the single-seed record, and the summary table
    (per class and method: every seed's mean and missing count, the mean over the seeds)."""
    seeds = list(per_seed)
    first = per_seed[seeds[0]]
    table, missing = {}, {}
    for cls in first["classes"]:
        for m in first["methods"]:
            rows = [per_seed[s]["classes"].get(cls, {}).get(m, {}) for s in seeds]
            vals = [r.get("mean") for r in rows]
            table.setdefault(cls, {})[m] = {**{str(s): v for s, v in zip(seeds, vals)},
                                            "mean": (sum(vals) / len(vals) if all(v is not None for v in vals)
                                                     else None)}
            missing.setdefault(cls, {})[m] = {str(s): r.get("missing", 0) for s, r in zip(seeds, rows)}
    means = {m: {str(s): per_seed[s]["mean_over_classes"].get(m) for s in seeds} for m in first["methods"]}
    for m, v in means.items():
        vals = list(v.values())
        v["mean"] = sum(vals) / len(vals) if all(x is not None for x in vals) else None
    return {"command": command, "seeds": seeds, "table": table, "missing": missing, "mean_over_classes": means,
            "per_seed": {str(s): reports[s] for s in seeds}}


def write_results(path: Path, record: dict, key: str | None) -> None:
    """``record`` into ``path``: under ``key`` (the file's other keys kept), or as the file's top level,
    the keyed records already there kept."""
    from carvi_torch.io.outputs import read_json, write_json, write_record

    if key is not None:
        write_record(path, record, key=key)
        return
    old = read_json(path) if path.is_file() else {}
    kept = {k: v for k, v in old.items() if k not in record} if isinstance(old, dict) else {}
    write_json(path, {**record, **kept})


# --------------------------------------------------------------------------- main


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=str(ROOT.parent / "shared" / "data" / "pascal3d_cad"),
                    help="directory of CAD models with 3-D keypoints (default ../shared/data/pascal3d_cad)")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "benchmark"), help="working directory (data, runs)")
    ap.add_argument("--results", default=str(ROOT / "docs" / "data"),
                    help="where benchmark_synthetic.json goes (default docs/data; table1.md and viewpoints.md go "
                         "to --out)")
    ap.add_argument("--key", default=None,
                    help="write the record under this key of benchmark_synthetic.json, its other keys kept "
                         "(default: the file's top level, Table 1's record)")
    ap.add_argument("--pool", type=int, default=20, help="pool (surrogate) renders per model (default 20)")
    ap.add_argument("--test-views", type=int, default=5, help="test renders per model (default 5)")
    ap.add_argument("--seed", default="0",
                    help="seed, or comma-separated seeds (each rendered and reconstructed in --out/seed<S>)")
    ap.add_argument("--step-percent", type=float, default=1.0,
                    help="metric sampling step, %% of the GT bbox diagonal (paper 0.5; default 1.0, "
                         "see docs/results.md)")
    ap.add_argument("--methods", default=",".join(METHODS),
                    help=f"comma-separated subset of {list(METHODS)} (case-insensitive; Full among them)")
    ap.add_argument("--classes", help="comma-separated classes (default: all)")
    ap.add_argument("--sides", choices=("class", "as-given"), default="class",
                    help="the models' left/right keypoint names: 'class' renames a pair one model names from the "
                         "other side than the rest of its class (motorbike01's handles), 'as-given' keeps them "
                         "(its data folders end in _sides-as-given)")
    ap.add_argument("--jobs", type=int, default=2, help="processes at once (default 2)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="extra reconstruct override for every method (repeatable)")
    ap.add_argument("--fresh", action="store_true", help="recompute every step (default: reuse finished outputs)")
    ap.add_argument("--no-baselines", action="store_true", help="skip Puffball and SFMc")
    return ap


def parse_methods(text: str) -> list[str]:
    """``--methods``: names of :data:`METHODS`, case-insensitive, in :data:`METHODS` order.

    Example:
        >>> parse_methods("oracle,full")
        ['Full', 'oracle']
    """
    by_lower = {m.lower(): m for m in METHODS}
    asked = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in asked if m.lower() not in by_lower]
    if unknown or "full" not in {m.lower() for m in asked}:
        raise ValueError(f"--methods must include Full and come from {list(METHODS)}; got {asked}")
    names = {by_lower[m.lower()] for m in asked}
    return [m for m in METHODS if m in names]


def _reconstructions(args, seed: int, ann: Path, runs: dict, classes, fresh: bool) -> list:
    """The ``reconstruct`` commands of step 2, ``(method, argv, log)``: every method's run that is not reused
    (:func:`_run_mismatch`; all of them over renders made now)."""
    cmds = []
    for m, run in runs.items():
        settings = ["references=test", f"seed={seed}", *METHODS[m], *args.set]
        redo = "renders made now" if fresh else _run_mismatch(run, ann, settings)
        if redo is None:
            print(f"reconstruct {m}: reusing {run}", flush=True)
            continue
        argv = [PYTHON, "-m", "carvi_torch.reconstruct", "--data", str(ann), "--out", str(run),
                "progress=false", "preview=false", "report=false",
                *([] if redo in RESUMED else ["overwrite=true"]), *settings]
        if classes:
            argv.append("classes=" + ",".join(classes))
        print(f"reconstruct {m} ({redo})", flush=True)
        cmds.append((m, argv, run / "log.txt"))
    return cmds


class ModelsError(Exception):
    """``--models`` holds no models to render (one ``error:`` line, exit 2)."""


def run_seed(args, seed: int, out: Path, methods: list[str], classes, command: str) -> tuple[dict, dict]:
    """Render, reconstruct and evaluate at one seed into ``out``; returns the evaluation and the record."""
    t_start, cpu0 = time.perf_counter(), cpu_seconds() + cpu_seconds(children=True)
    from carvi_torch.synthetic import load_models

    sides = "" if args.sides == "class" else "_sides-as-given"
    data = out / f"data_pool{args.pool}_test{args.test_views}_seed{seed}{sides}"
    try:
        models = load_models(Path(args.models), sides=args.sides, strict=True)  # once: the cache check, the render
    except (FileNotFoundError, ValueError) as e:  # no such folder, no models in it, a broken model
        raise ModelsError(f"--models {e}" if str(args.models) in str(e) else f"--models {args.models}: {e}") from None
    ncpu = os.cpu_count() or 1
    jobs = max(1, args.jobs)
    threads = max(1, ncpu // jobs)
    timings: dict = {}

    # 1. data
    fresh = _render_data(args, models, data, seed, timings)
    ann = data / "annotations.json"

    # 2. reconstructions
    runs = {m: out / f"run_{m.lstrip('-').lower()}" for m in methods}
    cmds = _reconstructions(args, seed, ann, runs, classes, fresh)
    t0, c0 = time.perf_counter(), cpu_seconds(children=True)
    timings["reconstruct"] = run_parallel(cmds, jobs, threads) if cmds else {}
    timings["reconstruct_total"] = {"wall_s": round(time.perf_counter() - t0, 1),
                                    "cpu_s": round(cpu_seconds(children=True) - c0, 1)}

    # 3. evaluation
    t0, c0 = time.perf_counter(), cpu_seconds(children=True)
    evals = out / "eval"
    ecmds = _evaluations(args, ann, runs, classes, evals, jobs)
    timings["evaluate"] = run_parallel(ecmds, jobs, threads)
    timings["evaluate_total"] = {"wall_s": round(time.perf_counter() - t0, 1),
                                 "cpu_s": round(cpu_seconds(children=True) - c0, 1)}
    res = merge_evaluations([json.loads((evals / f"part{i}" / "results.json").read_text())
                             for i in range(len(ecmds))])

    summaries = {m: json.loads((runs[m] / "summary.json").read_text()) for m in methods}
    report = {
        "command": command,
        "machine": {"platform": platform.platform(), "cpus": ncpu, "python": platform.python_version(),
                    "load_average_at_end": list(os.getloadavg())},
        "settings": {"pool": args.pool, "test_views": args.test_views, "seed": seed, "sides": args.sides,
                     "step_percent": args.step_percent, "jobs": jobs, "threads_per_job": threads,
                     "methods": {m: METHODS[m] + args.set for m in methods}},
        "timings": timings, "total_wall_s": round(time.perf_counter() - t_start, 1),
        "total_cpu_s": round(cpu_seconds() + cpu_seconds(children=True) - cpu0, 1),
        "acceptance": acceptance(res),
        "table": {c: {m: r[m]["mean"] for m in res["methods"]} for c, r in res["classes"].items()},
        "mean_over_classes": res["mean_over_classes"],
        "paper": PAPER, "paper_mean_20": PAPER_MEAN_20,
        "reconstruct_seconds": {m: {c: v.get("seconds") for c, v in s["classes"].items()}
                                for m, s in summaries.items()},
        "clusters": {c: v.get("clusters") for c, v in summaries["Full"]["classes"].items()},
        "evaluation": res,
    }
    return res, report


def _render_data(args, models: list, data: Path, seed: int, timings: dict) -> bool:
    """Render the pool and test views into ``data`` unless renders of these settings are there (``--fresh``:
    always); their timing goes to ``timings["render"]``. Whether it rendered."""
    t0, c0 = time.perf_counter(), cpu_seconds()
    stale = "--fresh" if args.fresh else _render_mismatch(data, models, args.pool, args.test_views, seed)
    if stale is not None:
        print(f"render {args.pool}+{args.test_views} views per model into {data} ({stale})", flush=True)
        info = render(models, data, args.pool, args.test_views, seed)
        print(f"  {info['images']} renders of {info['models']} models in {info['seconds']:.0f} s", flush=True)
        timings["render"] = {"wall_s": round(time.perf_counter() - t0, 1), "cpu_s": round(cpu_seconds() - c0, 1)}
    else:
        print(f"render: reusing {data}", flush=True)
        timings["render"] = {"reused": True}
    return stale is not None


def _evaluations(args, ann: Path, runs: dict, classes, evals: Path, jobs: int) -> list:
    """``(name, argv, log)`` of the evaluation commands: the classes (those asked) dealt round-robin over ``jobs``
    processes, each scoring every method's run (``runs``: method -> folder) into ``evals/part<i>`` in its own process
    (``--jobs 1``: the classes are what runs side by side)."""
    names = sorted(c["name"] for c in json.loads(ann.read_text())["categories"])
    names = [c for c in names if not classes or c in classes]
    halves = [names[i::jobs] for i in range(jobs)] if jobs > 1 else [names]
    halves = [h for h in halves if h]
    ecmds = []
    for i, part in enumerate(halves):
        argv = [PYTHON, "-m", "carvi_torch.evaluate", "--data", str(ann), "--split", "test", "--quiet", "--jobs", "1",
                "--step-percent", str(args.step_percent), "--classes", ",".join(part), "--out", str(evals / f"part{i}")]
        if not args.no_baselines:
            argv.append("--baselines")
        for m in runs:
            argv.append(f"--recon={m}={runs[m]}")  # "=" form: names such as -CRef start with a dash
        ecmds.append((f"evaluate[{i}]", argv, evals / f"part{i}.log"))
    return ecmds


def main(argv=None) -> int:
    ap = _parser()
    cli = sys.argv[1:] if argv is None else list(argv)
    args = ap.parse_args(argv)
    try:
        methods = parse_methods(args.methods)
        seeds = [int(s) for s in str(args.seed).split(",") if s.strip()]
    except ValueError as e:
        ap.error(str(e))
    if not seeds or len(set(seeds)) != len(seeds):
        ap.error(f"--seed must name distinct integer seeds, got {args.seed!r}")
    if not Path(args.models).is_dir():
        print(f"error: --models {args.models} not found (the PASCAL3D+ CAD models in ../shared/data)",
              file=sys.stderr)
        return 2
    out = Path(args.out)
    classes = args.classes.split(",") if args.classes else None
    command = "python tools/benchmark_synthetic.py " + " ".join(shlex.quote(a) for a in cli)

    from carvi_torch.evaluate import format_viewpoint_table
    from carvi_torch.io.outputs import write_bytes

    results = Path(args.results)
    tag = "" if not classes else "_" + "_".join(classes)
    target = results / f"benchmark_synthetic{tag}.json"
    per_seed, reports = {}, {}
    for seed in seeds:
        sout = out if len(seeds) == 1 else out / f"seed{seed}"
        try:
            per_seed[seed], reports[seed] = run_seed(args, seed, sout, methods, classes, command)
        except ModelsError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        write_bytes(sout / f"viewpoints{tag}.md", (format_viewpoint_table(per_seed[seed]) + "\n").encode())
    if len(seeds) == 1:
        res, record = per_seed[seeds[0]], reports[seeds[0]]
        table = table1(res)
        head = "the paper's Table 1 in brackets."
    else:
        record = seeds_record(per_seed, reports, command)
        table = seeds_table(per_seed)
        head = f"seeds {', '.join(map(str, seeds))} and their mean."
    write_results(target, record, args.key)
    write_bytes(out / f"table1{tag}.md", (
        f"Symmetric RMS error, % of the ground-truth bounding-box diagonal (surface step {args.step_percent}% "
        f"of it); {head}\n\n{table}\n\nCommand: `{command}`\n").encode())
    print()
    print(table)
    print()
    for seed in seeds:
        for k, v in reports[seed]["acceptance"].items():
            print(f"  seed {seed} {k}: {v}")
    print(f"wrote {target}" + (f" (key {args.key})" if args.key else "") + f", {out / f'table1{tag}.md'}")
    return 0


def _finished(run: Path) -> bool:
    try:
        s = json.loads((run / "summary.json").read_text())
    except (OSError, ValueError):
        return False
    return "total_seconds" in s


#: :func:`_run_mismatch`'s reasons for which the run is resumed (nothing there, or the same run cut short),
#: not made again over its folder (``overwrite=true``).
RESUMED = ("not run yet", "unfinished")


def _run_mismatch(run: Path, ann: Path, settings: list[str]) -> str | None:
    """Why the run in ``run`` is not a finished ``reconstruct --data ann settings``, or ``None`` (it is reused).

    A run whose ``config.yaml`` names other data (renders of another ``--pool``, ``--test-views`` or
    ``--sides``) or differs in a setting that changes the reconstructions (other ``--set``s, another method)
    is made again over its folder; one of these data and settings cut short is resumed (:data:`RESUMED`)."""
    from carvi_torch.config import NEUTRAL_SETTINGS, ConfigError, flatten_settings, load_config, read_yaml

    if not (run / "config.yaml").exists():
        return "not run yet" if not (run / "summary.json").exists() else "no config.yaml"
    try:
        saved = flatten_settings(read_yaml(run / "config.yaml"))
    except ConfigError as e:
        return f"unreadable config.yaml: {e}"
    data = saved.get("data")
    if not isinstance(data, str) or Path(data).resolve() != ann.resolve():
        return f"made from {data}, not {ann}"
    try:
        wanted = load_config(None, settings).flat()
    except ConfigError as e:  # reconstruct says so in its log
        return f"settings not valid: {e}"
    changed = [k for k, v in wanted.items() if k not in NEUTRAL_SETTINGS and saved.get(k) != v]
    if changed:
        return f"made with {changed[0]}={saved.get(changed[0])}, not {wanted[changed[0]]}"
    return None if _finished(run) else "unfinished"


if __name__ == "__main__":
    sys.exit(main())
