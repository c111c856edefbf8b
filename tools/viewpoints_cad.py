"""Viewpoint accuracy on renders of the PASCAL3D+ CAD models: SfM alone vs silhouette refinement.

All models of a class are pooled (a class = many different objects, as in PASCAL VOC), each
rendered from ``--views`` photo-like cameras; ``reconstruct stage=cameras`` estimates every
camera; errors are measured as written (absolute: the class's canonical frame against the CAD
frame, +z up, front -y) and after one global rotation aligning the two
(``carvi_torch.evaluation.viewpoint_metrics``); the up error is the angle between the written
+z and the CAD +z under that rotation (with ``viewpoints.frame=symmetry+up`` it measures the
automatic frame, which uses no template). SfM -> refined compares the same views (those with
an SfM camera, ``evaluate``'s ``refined_with_sfm``); every view's refined median, the
unseen-image cameras included, has a column of its own. The cameras of a run go to
``<work>/cameras[_<overrides>][_v<views>][_renders-s<seed>][_<cameras>][_sides-as-given]``
(rerunning the same settings resumes there). The CAD models' left/right names are made consistent
within each class (``--sides class``, the default: motorbike01's handles are renamed; ``--sides
as-given`` keeps them); renders on disk made with other settings, models or names than the run's
stop it with the reason. With several seeds (``--seed 0,1,2``) every seed is rendered and
reconstructed in turn and a last table gives, per class and seed, the SfM -> refined medians, their
means, whether refinement is no worse than SfM at every seed, and whether it is worse beyond the 95%
interval of the change that another draw of the CAD models gives at some seed (``evaluate``'s
``change_from_sfm``: a bootstrap over whole models, the views of one model sharing its shape; each
seed's table shows the change and its interval too) (the small-class benchmark: ``--views 8``, 32-80
views per class).
``--cameras level`` draws the renders' cameras from a level camera held above the ground (elevation
mostly 0-30 degrees, up to 50; roll sd 2) instead of the renderer's default photo-like distribution.

    python tools/viewpoints_cad.py [--views 30] [--seed 0[,1,2]] [--cameras photo|level] [--quiet]
                                   [--work outputs/viewpoints_cad] [--out PATH [--key KEY]] [key=value ...]
    python tools/viewpoints_cad.py --views 8 --seed 0,1,2 --choice-study [--out PATH]
    python tools/viewpoints_cad.py --views 8 --seed 2 --render-only [--work DIR]
    python tools/viewpoints_cad.py --compare RUN_A RUN_B [RUN_B ...] [--labels cpu,cuda] [--out PATH [--key KEY]]

``--choice-study`` runs no table: every class of every seed is estimated with ``refine_keep=refined``,
every object's SfM and refined cameras are compared with the truth and scored by what the pipeline
can see (keypoint growth, hull gain, silhouette gain, the refinement's energy drop, the turn, the
change of the image tilt of the class's up); it prints how many objects the tilt and suspect tests
flag per band of the true error change, each score's AUC between the objects refinement made worse
and those it made better by over 2 degrees, and the classes a per-object choice by the truth would
keep within their SfM medians at every seed (docs/viewpoints.md, *What separates a worse refined
camera*).

``key=value`` are reconstruct overrides (``sfm_groups=1``, ``viewpoints.frame=symmetry+up``). The
JSON record goes to ``--out`` (under ``--key`` when given, the file's other keys kept; the records of
docs/viewpoints.md are keys of ``docs/data/viewpoints.json``), by default beside the run's cameras
(``<work>/cameras...json``).

``--render-only`` renders the seeds (cached in ``--work``) and stops, so that several runs can then
share the renders at the same time. ``--compare RUN_A RUN_B [RUN_B ...]`` reconstructs nothing: it compares
two runs of the same renders object by object (several RUN_B folders: one run split across processes;
``carvi_torch.evaluation.viewpoint_metrics.compare_camera_runs``: per class the median and largest angle
between the refined cameras, ``camera_choice`` differences, each run's SfM start, shapes kept and seconds; a
class one run has not finished is listed, not an error), prints a line per class, writes the record to
``--out`` (default ``RUN_B/agreement.json``) and exits 1 when a class's median angle exceeds 0.5 degrees or
no class was compared (``tools/gpu_session.sh`` compares the CPU with CUDA so).

Needs ../shared/data/pascal3d_cad (the PASCAL3D+ CAD models, Xiang et al. 2014).
"""
from __future__ import annotations

import argparse
import functools
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def _per_model(annotations: Path, viewpoints: dict) -> dict:
    """Median geodesic error per CAD model: ``{class: {model: {"n", "sfm", "refined"}}}`` (degrees);
    where some views have no SfM camera also ``"refined_with_sfm"``: the model's views that have
    one, under the alignment of those views (the class rows' SfM -> refined comparison)."""
    from statistics import median

    model = {a["id"]: Path(a.get("source") or str(a.get("object_id"))).stem
             for a in json.loads(Path(annotations).read_text())["annotations"]}
    out = {}
    for cls, per in sorted(viewpoints.items()):
        rows = {}
        for stage in ("sfm", "refined", "refined_with_sfm"):
            rep = per.get("estimated", {}).get(stage)
            if not rep:
                continue
            errs: dict = {}
            for aid, e in zip(rep["annotation_ids"], rep["per_instance_geodesic"]):
                errs.setdefault(model[aid], []).append(e)
            for m, es in errs.items():
                rows.setdefault(m, {"n": len(es)})[stage] = round(median(es), 2)
        out[cls] = dict(sorted(rows.items()))
    return out


def _up_error(alignment: list) -> float:
    """Degrees between the written +z and the CAD +z: ``R_est G ~ R_gt`` puts the CAD +z at ``G e_z``."""
    import math

    return round(math.degrees(math.acos(max(-1.0, min(1.0, alignment[2][2])))), 2)


#: Camera distributions of the renders (``render_dataset``'s ``camera_options``): ``photo`` the
#: renderer's default (elevation N(12, 12) degrees in -20..75, roll sd 3); ``level`` a level camera
#: held above the ground (elevation N(15, 12) in 0..50, roll sd 2): mostly 0-30 degrees, some up to 50.
CAMERAS = {"photo": {}, "level": {"elevation_deg": (15.0, 12.0), "elevation_range_deg": (0.0, 50.0),
                                  "roll_sd_deg": 2.0}}


def _rows(res: dict, recon: Path) -> list:
    """One row per class of an evaluation of the run in ``recon`` (medians in degrees); with a mixture of
    shapes (``sfm_groups > 1``) also the class's ``sfm_groups`` of ``summary.json`` (groups kept, misfit,
    every candidate split with its residual cut, frame agreement and hull gain)."""
    rows = []
    summary = json.loads((recon / "summary.json").read_text()).get("classes", {})
    for cls, per in sorted(res["viewpoints"].items()):
        rep = per.get("estimated", {})
        sfm, ref = rep.get("sfm", {}), rep.get("refined", {})
        if not ref:
            continue
        same = rep.get("refined_with_sfm", ref)  # the refinement's own before/after: the SfM objects
        cj = json.loads((recon / cls / "cameras.json").read_text())
        choice = [c.get("camera_choice") for c in cj["cameras"].values()]
        rows.append({
            "class": cls, "n": ref["geodesic"]["n"], "n_sfm": sfm.get("geodesic", {}).get("n", 0),
            "sfm_geodesic": sfm.get("geodesic", {}).get("median"),
            "refined_geodesic_sfm_objects": same["geodesic"]["median"],
            "refined_geodesic": ref["geodesic"]["median"], "change_from_sfm": same.get("change_from_sfm"),
            "sfm_azimuth": sfm.get("azimuth", {}).get("median"), "refined_azimuth": same["azimuth"]["median"],
            "sfm_elevation": sfm.get("elevation", {}).get("median"), "refined_elevation": same["elevation"]["median"],
            "sfm_up_axis": sfm.get("up_axis", {}).get("median"), "refined_up_axis": same["up_axis"]["median"],
            "sfm_acc30": sfm.get("geodesic", {}).get("acc_at_30"), "refined_acc30": ref["geodesic"]["acc_at_30"],
            "mirrored": bool(ref.get("mirrored")), "frame": cj.get("frame"), "kept_sfm": choice.count("sfm"),
            "absolute_geodesic": ref["absolute"]["geodesic"]["median"],
            "absolute_azimuth": ref["absolute"]["azimuth"]["median"],
            "absolute_elevation": ref["absolute"]["elevation"]["median"],
            "up_error_deg": _up_error(ref["alignment"]),
        })
        if "sfm_groups" in summary.get(cls, {}):  # the mixture's decision (sfm_groups > 1): misfit, candidates
            rows[-1]["sfm_groups"] = summary[cls]["sfm_groups"]
    return rows


def _table(rows: list) -> str:
    from carvi_torch.evaluate import format_change

    f = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    lines = ["| class | views (with an SfM camera) | median geodesic SfM -> refined (change [95% over models]) | "
             "median azimuth SfM -> refined | median elevation SfM -> refined | "
             "median up axis (ignores azimuth) SfM -> refined | every view: refined median, acc@30 | frame mirrored | "
             "frame (up error) | absolute: geodesic, azimuth, elevation |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        worse = r["sfm_geodesic"] is not None and r["refined_geodesic_sfm_objects"] > r["sfm_geodesic"]
        change = f" ({format_change(r['change_from_sfm'])})" if r.get("change_from_sfm") else \
            (" (worse)" if worse else "")
        views = f"{r['n']}" + ("" if r["n_sfm"] == r["n"] else f" ({r['n_sfm']})")
        lines.append(f"| {r['class']} | {views} | {f(r['sfm_geodesic'])} -> {f(r['refined_geodesic_sfm_objects'])}"
                     f"{change} | {f(r['sfm_azimuth'])} -> {f(r['refined_azimuth'])} | "
                     f"{f(r['sfm_elevation'])} -> {f(r['refined_elevation'])} | "
                     f"{f(r.get('sfm_up_axis'))} -> {f(r.get('refined_up_axis'))} | {f(r['refined_geodesic'])}, "
                     f"{r['refined_acc30']:.2f} | {r['mirrored']} | {r['frame']} ({f(r['up_error_deg'])}) | "
                     f"{f(r['absolute_geodesic'])}, {f(r['absolute_azimuth'])}, {f(r['absolute_elevation'])} |")
    return "\n".join(lines)


@functools.lru_cache(maxsize=2)
def _models(cad: str, sides: str) -> tuple:
    """The CAD models of ``--cad`` with ``--sides``'s names, read once per run of the tool (every seed uses them)."""
    from carvi_torch.synthetic import load_models

    return tuple(load_models(Path(cad), sides=sides, strict=True))


def _renders(args, seed: int) -> Path:
    """The renders of one seed (rendered on first use, or again over a folder without ``annotations.json`` or
    ``gt.json``): ``<work>/renders_v<views>_s<seed>[_<cameras>][_sides-as-given]``.

    Raises:
        SystemExit: the folder holds other renders than these arguments make (other views, seed,
            cameras, models or left/right names, e.g. made before
            :func:`~carvi_torch.synthetic.meshes.harmonize_sides`:
            :func:`~carvi_torch.synthetic.render.render_mismatch` gives the reason).
    """
    from carvi_torch.synthetic.render import read_render_info, render_dataset, render_mismatch

    dist = "" if args.cameras == "photo" else f"_{args.cameras}"
    sides = "" if args.sides == "class" else "_sides-as-given"
    renders = Path(args.work) / f"renders_v{args.views}_s{seed}{dist}{sides}"
    models = _models(str(args.cad), args.sides)
    settings = {"views": args.views, "seed": seed, "camera_options": CAMERAS[args.cameras]}
    if (renders / "annotations.json").is_file() and (renders / "gt.json").is_file():  # else incomplete: made again
        reason = render_mismatch(read_render_info(renders), models, **settings)
        if reason is not None:
            raise SystemExit(f"error: {renders} holds other renders than these arguments make ({reason}); "
                             "remove it, or use another --work")
        return renders
    render_dataset(list(models), renders, progress=not args.quiet, **settings)
    return renders


def recon_dir(work: Path, overrides: list, views: int = 30, seed: int = 0, cameras: str = "photo",
              sides: str = "class") -> Path:
    """The folder of one run's cameras: one per render seed and set of overrides, so that runs with different
    settings never mix their cameras (every character of an override but letters and digits becomes ``-``).

    >>> recon_dir(Path("w"), ["device=cpu", "classes=[sofa,train]"], views=8, seed=2).name
    'cameras_device-cpu_classes--sofa-train-_v8_renders-s2'
    """
    dist = "" if cameras == "photo" else f"_{cameras}"
    return work / ("cameras" + "".join("_" + "".join(ch if ch.isalnum() else "-" for ch in o) for o in overrides)
                   + (f"_v{views}" if views != 30 else "") + (f"_renders-s{seed}" if seed else "") + dist
                   + ("" if sides == "class" else "_sides-as-given"))


def _run(args, seed: int, overrides: list) -> dict:
    """Render (once) and reconstruct the cameras of one seed with ``overrides``; its rows and timings."""
    from carvi_torch.evaluate import evaluate

    t0 = time.perf_counter()
    renders = _renders(args, seed)
    t_render = time.perf_counter() - t0
    recon = recon_dir(Path(args.work), overrides, args.views, seed, args.cameras, args.sides)
    cmd = [sys.executable, "-m", "carvi_torch.reconstruct", "--data", str(renders / "annotations.json"),
           "--out", str(recon), "stage=cameras", "progress=false", f"seed={seed}", *overrides]
    t1 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    t_cams = time.perf_counter() - t1
    res = evaluate(renders / "annotations.json", {"estimated": recon}, shapes=False, progress=False)
    return {"seed": seed, "recon": recon, "renders": renders, "rows": _rows(res, recon),
            "per_model": _per_model(renders / "annotations.json", res["viewpoints"]),
            "render_seconds": round(t_render, 1), "cameras_seconds": round(t_cams, 1)}


def _seed_rotations(run: dict) -> dict:
    """Per class of one seed's run: ``(sfm, final, truth, model, seed)`` of every view with all three cameras."""
    ann = json.loads((run["renders"] / "annotations.json").read_text())["annotations"]
    model = {str(a["id"]): Path(a.get("source") or str(a.get("object_id") or f"annotation{a['id']}")).stem
             for a in ann}
    gt_all = json.loads((run["renders"] / "gt.json").read_text())
    gt = gt_all.get("annotations", gt_all)
    out: dict = {}
    for row in run["rows"]:
        cams = json.loads((run["recon"] / row["class"] / "cameras.json").read_text())["cameras"]
        out[row["class"]] = [(c["sfm"]["R"], c["refined"]["R"], gt[aid]["R"], model[aid], run["seed"])
                             for aid, c in cams.items() if c.get("sfm") and c.get("refined") and aid in gt]
    return out


def _change_over_seeds(runs: list) -> dict:
    """Per class: refinement's change of the median over every seed at once (``median_change`` with the seeds as
    its runs: each seed aligned on its own, the change the mean of the seeds', a drawn CAD model counting in
    every seed); ``None`` where fewer than 2 models have cameras."""
    from carvi_torch.evaluation.viewpoint_metrics import median_change

    views: dict = {}
    for run in runs:
        for cls, rows in _seed_rotations(run).items():
            views.setdefault(cls, []).extend(rows)
    out = {}
    for cls, rows in views.items():
        R = [torch.tensor([r[i] for r in rows], dtype=torch.float64).reshape(-1, 3, 3) for i in range(3)]
        ok = torch.stack([torch.isfinite(x).flatten(1).all(1) for x in R]).all(0)
        kept = [r for r, k in zip(rows, ok.tolist()) if k]
        if len({r[3] for r in kept}) < 2:
            out[cls] = None
            continue
        res = median_change(*(x[ok] for x in R), [r[3] for r in kept], runs=[r[4] for r in kept])
        out[cls] = {k: round(v, 3) if isinstance(v, float) else v for k, v in res.items()}
    return out


def _seeds_table(runs: list, refined: list | None = None) -> tuple[str, dict]:
    """Per class and seed: the SfM and final (kept) medians (degrees, the views with an SfM camera), with
    ``refined`` (the runs with ``refine_keep=refined``) the refined ones between them; the means over the
    seeds; whether the final median is no worse than the SfM one at every seed; whether it is worse beyond
    the 95% interval of the change that another draw of the CAD models gives (``evaluate``'s
    ``change_from_sfm``, which resamples the views of whole models) at some seed; and that change over every
    seed at once with its interval (:func:`_change_over_seeds`)."""
    from carvi_torch.evaluate import format_change

    f = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    what = "SfM / refined / final" if refined else "SfM -> refined"
    over = _change_over_seeds(runs)
    lines = ["| class | " + " | ".join(f"seed {r['seed']}: {what}" for r in runs) + f" | mean {what} | "
             "final <= SfM at every seed | worse beyond the 95% interval | every seed: final - SfM [95%] |",
             "|---" * (len(runs) + 5) + "|"]
    out = {}
    for cls in [r["class"] for r in runs[0]["rows"]]:
        rows = [next(x for x in run["rows"] if x["class"] == cls) for run in runs]
        cols = {"sfm": [r["sfm_geodesic"] for r in rows], "final": [r["refined_geodesic_sfm_objects"] for r in rows]}
        if refined:
            cols["refined"] = [next(x for x in run["rows"] if x["class"] == cls)["refined_geodesic_sfm_objects"]
                               for run in refined]
        ok = all(s is None or r <= s for s, r in zip(cols["sfm"], cols["final"]))
        changes = [r.get("change_from_sfm") for r in rows]
        beyond = [run["seed"] for run, c in zip(runs, changes) if c and c["low"] > 0]
        mean = {k: sum(v for v in vs if v is not None) / max(1, sum(v is not None for v in vs))
                for k, vs in cols.items()}
        order = ["sfm", "refined", "final"] if refined else ["sfm", "final"]
        sep = " / " if refined else " -> "
        out[cls] = {**cols, **{f"mean_{k}": round(v, 2) for k, v in mean.items()}, "final_not_worse": ok,
                    "change_from_sfm": changes, "worse_beyond_interval_at_seeds": beyond,
                    "change_over_seeds": over.get(cls),
                    "kept_sfm": [r.get("kept_sfm") for r in rows]}
        lines.append(f"| {cls} | " + " | ".join(sep.join(f(cols[k][i]) for k in order) for i in range(len(runs)))
                     + f" | {sep.join(f(mean[k]) for k in order)} | {'yes' if ok else 'no'} | "
                     + (f"seed {', '.join(map(str, beyond))}" if beyond else "no")
                     + f" | {format_change(over.get(cls))} |")
    return "\n".join(lines), out


BANDS = [("worse by over 10", 10, np.inf), ("worse by 2-10", 2, 10), ("within 2", -2, 2),
         ("better by 2-10", -10, -2), ("better by over 10", -np.inf, -10)]


def _aligned_errors(R: torch.Tensor, Rg: torch.Tensor) -> np.ndarray:
    from carvi_torch.cameras import align_rotations, geodesic_errors

    return geodesic_errors(R, Rg, align_rotations(R, Rg)).numpy()


def _class_rows(coll, gt: dict, seed: int) -> dict:
    """Per original with an SfM camera and a true one: scores and the true error change (degrees)."""
    from carvi_torch.cameras import geodesic_angle
    from carvi_torch.config import ViewpointConfig
    from carvi_torch.sdf import distance_to_mask
    from carvi_torch.viewpoints import camera_fit, estimate_viewpoints, ground_truth_cameras
    from carvi_torch.viewpoints.choice import (box_diagonal, class_up, hull_agreement, image_tilt, keypoint_rms,
                                               tilted)
    from carvi_torch.viewpoints.refine import choose_per_group

    cfg = ViewpointConfig(refine_keep="refined")
    vp = estimate_viewpoints(coll, cfg, seed=seed)
    n, both = len(coll), vp.both
    gtc, _why = ground_truth_cameras(gt, coll)
    if gtc is None:
        return {}
    ok = (vp.sfm_valid[:n].cpu() & torch.isfinite(gtc.R).flatten(1).all(1)).numpy()
    if ok.sum() < 3:
        return {}
    Rg = gtc.R.double()[ok]
    err = {k: _aligned_errors(c.R[:n].double().cpu()[ok], Rg) for k, c in (("sfm", vp.sfm_cameras),
                                                                           ("refined", vp.cameras))}
    S = camera_fit.supported_shape(vp.shape, both.visible, cfg.refine_min_support)
    sfm, ref = vp.sfm_cameras[:n], vp.cameras[:n]
    kp, vis, masks = both.keypoints[:n], both.visible[:n], both.masks[:n]
    diag = box_diagonal(masks).numpy()
    dist = camera_fit._finite_maps(distance_to_mask(masks))
    sil = [camera_fit.sample_distance(dist, c.project(S[torch.isfinite(S).all(-1)])).mean(-1).double().numpy()
           for c in (sfm, ref)]
    choice = choose_per_group(vp.groups, vp.sfm_cameras, vp.cameras, both, cfg)
    energy = [camera_fit.refinement_energy(c.s[:, None, None] * c.R[:, :2], c.t, S, kp, vis, dist,
                                           silhouette_robust=cfg.silhouette_robust).double().numpy()
              for c in (sfm, ref)]
    up = class_up(vp.sfm_cameras.R[vp.sfm_valid])
    tilt = [image_tilt(c.R, up)[0].numpy() if up is not None else np.zeros(n) for c in (sfm, ref)]
    flagged = tilted(vp.sfm_cameras.R, vp.cameras.R, vp.sfm_valid, cfg.refine_max_tilt_deg)[:n].numpy()
    scores = {
        "keypoint_growth": ((keypoint_rms(S, ref, kp, vis) - keypoint_rms(S, sfm, kp, vis)).double().numpy() / diag),
        "hull_gain": (hull_agreement(S, ref, masks) - hull_agreement(S, sfm, masks)).numpy(),
        "silhouette_gain": (sil[0] - sil[1]) / diag,
        "energy_drop": (energy[0] - energy[1]) / np.maximum(energy[0], 1e-9),
        "turn": np.rad2deg(geodesic_angle(sfm.R.double(), ref.R.double()).cpu().numpy()),
        "tilt_change": tilt[1] - tilt[0],
    }
    # the best any per-object choice can do: each object's better camera, by the truth, then aligned again
    best = np.where((err["refined"] > err["sfm"])[:, None, None], sfm.R.double().cpu().numpy()[ok],
                    ref.R.double().cpu().numpy()[ok])
    medians = {"sfm": float(np.median(err["sfm"])), "refined": float(np.median(err["refined"])),
               "best_per_object": float(np.median(_aligned_errors(torch.from_numpy(best), Rg)))}
    return {"change": err["refined"] - err["sfm"], "tilted": flagged[ok], "suspect": choice.suspect[:n].numpy()[ok],
            **{k: v[ok] for k, v in scores.items()}, "medians": medians}


def _auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """P(score of a worse object > score of a better one), ties half."""
    if not len(pos) or not len(neg):
        return float("nan")
    return float((pos[:, None] > neg[None]).mean() + 0.5 * (pos[:, None] == neg[None]).mean())


def _choice_study(args) -> int:
    """``--choice-study``: which refined cameras are worse than their SfM cameras, and what tells them apart
    without ground truth (every class of every seed estimated with ``refine_keep=refined``; scores, bands of
    the true error change, AUCs and the bound of a per-object choice by the truth, printed and written to
    ``--out``, default ``<work>/refine_choice_v<views>_<cameras>.json``)."""
    from carvi_torch.io.coco import load_coco

    torch.set_num_threads(1)
    rows: dict = {}
    per_class: dict = {}
    for seed in args.seed:
        renders = _renders(args, seed)
        gt = json.loads((renders / "gt.json").read_text())
        for cls, coll in sorted(load_coco(renders / "annotations.json").collections.items()):
            r = _class_rows(coll, gt, seed)
            medians = r.pop("medians", None)
            for k, v in r.items():
                rows.setdefault(k, []).append(v)
            if r:
                per_class.setdefault(cls, []).append({"seed": seed, "worse_over_10": int((r["change"] > 10).sum()),
                                                      "tilted": int(r["tilted"].sum()),
                                                      "tilted_worse": int((r["tilted"] & (r["change"] > 0)).sum()),
                                                      "medians": medians})
    x = {k: np.concatenate(v) for k, v in rows.items()}
    ch = x["change"]
    bands = []
    print("| true change, refined - SfM (degrees) | objects | tilted | suspect |\n|---|---:|---:|---:|")
    for name, lo, hi in BANDS:
        m = (ch > lo) & (ch <= hi)
        bands.append({"band": name, "objects": int(m.sum()), "tilted": int((m & x["tilted"]).sum()),
                      "suspect": int((m & x["suspect"]).sum())})
        print(f"| {name} | {bands[-1]['objects']} | {bands[-1]['tilted']} | {bands[-1]['suspect']} |")
    worse, better = ch > 2, ch < -2
    auc = {k: round(_auc(x[k][worse], x[k][better]), 3) for k in x if k not in ("change", "tilted", "suspect")}
    print("AUC, worse by over 2 against better by over 2 degrees:", auc)
    best_ok = [c for c, v in per_class.items()
               if all(r["medians"]["best_per_object"] <= r["medians"]["sfm"] for r in v)]
    print(f"each object's better camera by the truth: median no worse than SfM at every seed in {len(best_ok)} of "
          f"{len(per_class)} classes ({', '.join(best_ok)})")
    out = Path(args.out) if args.out else Path(args.work) / f"refine_choice_v{args.views}_{args.cameras}.json"
    out.write_text(json.dumps({"command": " ".join(["python", "tools/viewpoints_cad.py", *sys.argv[1:]]),
                               "bands": bands, "auc_worse_vs_better": auc, "best_per_object_not_worse": best_ok,
                               "per_class": per_class}, indent=1))
    print(f"wrote {out}")
    return 0


def _compare(args) -> int:
    """``--compare RUN_A RUN_B``: the two runs' cameras object by object; prints, writes, exit 0 when they agree."""
    from carvi_torch.evaluation.viewpoint_metrics import RUN_TURNED_DEG, compare_camera_runs
    from carvi_torch.io.outputs import write_record

    labels = tuple(args.labels.split(","))
    rec = compare_camera_runs(args.compare[0], args.compare[1:], labels=labels)
    a, b = labels
    for cls, why in rec["not_compared"].items():
        print(f"{cls:12s} {why}")
    for cls, r in rec["classes"].items():
        sec = r["viewpoint_seconds"]
        print(f"{cls:12s} median {r['median_deg']:.3f} deg, max {r['max_deg']:.2f} deg, {len(r['turned'])} of "
              f"{r['compared']} over {RUN_TURNED_DEG:g} deg, camera_choice differs in "
              f"{r['camera_choice_differs']}, SfM start {a}/{b} {r['sfm_start'][0]}/{r['sfm_start'][1]}, shape "
              f"groups {r['shape_groups'][0]}/{r['shape_groups'][1]}, SfM + refinement {sec[a]:.1f} s {a}, "
              f"{sec[b]:.1f} s {b}")
    sec, threads = rec["viewpoint_seconds"], rec["torch_threads"]
    print(f"{len(rec['classes'])} classes compared; SfM + refinement {sec[a]:.1f} s {a} ({threads[a]} torch threads), "
          f"{sec[b]:.1f} s {b} ({threads[b]} torch threads)")
    worst = rec["largest_median_deg"]
    print("no class compared" if worst is None else
          f"largest class median {worst:.3f} deg: {'within' if rec['agree'] else 'OUTSIDE'} the "
          f"{rec['tolerance_deg']} degree tolerance")
    rec["runs"] = {a: [str(Path(args.compare[0]).resolve())], b: [str(Path(r).resolve()) for r in args.compare[1:]]}
    out = Path(args.out) if args.out else Path(args.compare[1]) / "agreement.json"
    write_record(out, rec, args.key)
    print(f"wrote {out}" + (f", key {args.key}" if args.key else ""))
    return 0 if rec["agree"] else 1


def _seeds(text: str) -> list:
    """``"0,1,2"`` -> ``[0, 1, 2]`` (the ``--seed`` argument)."""
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds must be integers separated by commas, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    """The command line (the module docstring is its help)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=30, help="renders per CAD model (default 30)")
    ap.add_argument("--seed", type=_seeds, default=[0], help="render seed, or several comma-separated (0,1,2: a table "
                                                             "per class and seed of the SfM and refined medians)")
    ap.add_argument("--cameras", choices=sorted(CAMERAS), default="photo", help="camera distribution of the renders")
    ap.add_argument("--refined-too", action="store_true", help="also run every seed with refine_keep=refined (the "
                                                               "refined cameras whatever they score) for the table")
    ap.add_argument("--choice-study", action="store_true",
                    help="instead of the tables: which refined cameras are worse than SfM's and what separates them")
    ap.add_argument("--quiet", action="store_true", help="no render progress bar")
    ap.add_argument("--cad", default=str(ROOT / ".." / "shared" / "data" / "pascal3d_cad"))
    ap.add_argument("--sides", choices=("class", "as-given"), default="class",
                    help="the CAD models' left/right keypoint names: 'class' renames a pair one model names from the "
                         "other side than the rest of its class (motorbike01's handles), 'as-given' keeps them")
    ap.add_argument("--work", default=str(ROOT / "outputs" / "viewpoints_cad"), help="renders and cameras go here")
    ap.add_argument("--out", default=None, help="JSON record (default: beside the cameras in --work)")
    ap.add_argument("--key", default=None, help="write the record under this key of --out's JSON object, its other "
                                                "keys kept (e.g. --out docs/data/viewpoints.json --key "
                                                "viewpoints_cad8)")
    ap.add_argument("--render-only", action="store_true", help="render the seeds (cached in --work) and stop")
    ap.add_argument("--compare", nargs="+", metavar="RUN", default=None,
                    help="instead: compare two runs' cameras object by object, RUN_A then RUN_B (several folders: "
                         "one run split across processes); exit 1 when a class's median angle exceeds 0.5 degrees")
    ap.add_argument("--labels", default="cpu,cuda", help="--compare: the two runs' names, comma-separated")
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="extra reconstruct overrides")
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if args.compare:
        if len(args.compare) < 2:
            ap.error("--compare needs RUN_A and RUN_B")
        if len(args.labels.split(",")) != 2 or len(set(args.labels.split(","))) != 2:
            ap.error(f"--labels needs two different names separated by a comma, got {args.labels!r}")
        return _compare(args)
    if not Path(args.cad).is_dir():
        print(f"error: {args.cad} not found (the PASCAL3D+ CAD models in ../shared/data)", file=sys.stderr)
        return 2
    if args.choice_study:
        return _choice_study(args)
    if args.render_only:
        for seed in args.seed:
            print(_renders(args, seed))
        return 0
    return _tables(args, argv)


def _tables(args, argv) -> int:
    """The default run: every seed's cameras (and with ``--refined-too`` the refined ones), their tables printed
    and recorded (``--out``, default beside the first seed's cameras)."""
    runs = [_run(args, seed, args.overrides) for seed in args.seed]
    refined = [_run(args, seed, [*args.overrides, "refine_keep=refined"]) for seed in args.seed] \
        if args.refined_too else None
    out, key = (Path(args.out), args.key) if args.out else (runs[0]["recon"].with_suffix(".json"), args.key)
    record = {"command": " ".join(shlex.quote(a) for a in ["python", "tools/viewpoints_cad.py",
                                                           *(argv if argv is not None else sys.argv[1:])]),
              "views": args.views, "cameras": args.cameras}
    for run in runs:
        rec = _seed_report(run)
        if len(runs) == 1:
            record.update(rec)
        else:
            record.setdefault("seeds", []).append(rec)
    if len(runs) > 1 or refined:
        table, per_class = _seeds_table(runs, refined)
        print(table)
        record.update({"seeds_table": table, "per_class": per_class})
        if refined:
            record["refined_runs"] = [{"seed": r["seed"], "rows": r["rows"]} for r in refined]
    from carvi_torch.io.outputs import write_record

    write_record(out, record, key)
    print(f"wrote {out}" + (f", key {key}" if key else ""))
    return 0


def _seed_report(run: dict) -> dict:
    """Print one seed's table and what refinement did; its part of the record."""
    rows = run["rows"]
    table = _table(rows)
    print(f"seed {run['seed']}\n{table}")
    print("(SfM -> refined: the views with an SfM camera, before and after refinement; views without one take "
          "their camera from the unseen-image path and count in the 'every view' column only)")
    improved = sum(1 for r in rows
                   if r["sfm_geodesic"] is not None and r["refined_geodesic_sfm_objects"] < r["sfm_geodesic"])
    up_ok = sum(1 for r in rows if r["up_error_deg"] <= 10.0)
    print(f"refinement lowers the median geodesic error in {improved} of {len(rows)} classes")
    print(f"the written up axis lies within 10 degrees of the CAD +z in {up_ok} of {len(rows)} classes")
    print(f"render {run['render_seconds']:.1f} s, SfM + refinement of all classes {run['cameras_seconds']:.1f} s")
    return {"seed": run["seed"], "rows": rows, "table": table, "refinement_lowers": improved,
            "up_within_10deg": up_ok, "per_model": run["per_model"], "render_seconds": run["render_seconds"],
            "cameras_seconds": run["cameras_seconds"]}


if __name__ == "__main__":
    sys.exit(main())
