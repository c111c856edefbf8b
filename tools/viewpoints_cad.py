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
``<work>/cameras[_<overrides>][_v<views>][_renders-s<seed>]`` (rerunning the same settings resumes there).

    python tools/viewpoints_cad.py [--views 30] [--seed 0] [--work outputs/viewpoints_cad]
                                   [--out PATH] [key=value ...]

``key=value`` are reconstruct overrides (``sfm_groups=3``, ``viewpoints.frame=symmetry+up``). The
JSON record goes to ``--out``; by default, for the default settings (no override, seed 0), to
``docs/data/viewpoints_cad.json`` (docs/viewpoints.md), else beside the run's cameras
(``<work>/cameras...json``).

Needs ../shared/data/pascal3d_cad (the PASCAL3D+ CAD models, Xiang et al. 2014).
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=30, help="renders per CAD model (default 30)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cad", default=str(ROOT / ".." / "shared" / "data" / "pascal3d_cad"))
    ap.add_argument("--work", default=str(ROOT / "outputs" / "viewpoints_cad"), help="renders and cameras go here")
    ap.add_argument("--out", default=None, help="JSON record (default: docs/data/viewpoints_cad.json for the "
                                                "default settings, else beside the cameras in --work)")
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="extra reconstruct overrides")
    args = ap.parse_args(argv)
    cad = Path(args.cad)
    if not cad.is_dir():
        print(f"error: {cad} not found (the PASCAL3D+ CAD models in ../shared/data)", file=sys.stderr)
        return 2
    from carvi_torch.synthetic import load_models
    from carvi_torch.synthetic.render import render_dataset

    work = Path(args.work)
    renders = work / f"renders_v{args.views}_s{args.seed}"
    t0 = time.perf_counter()
    if not (renders / "annotations.json").is_file():
        render_dataset(load_models(cad), renders, views=args.views, seed=args.seed, progress=True)
    t_render = time.perf_counter() - t0
    # one folder per render seed and set of overrides, so runs with different settings never mix their cameras
    recon = work / ("cameras" + "".join("_" + "".join(ch if ch.isalnum() else "-" for ch in o) for o in args.overrides)
                    + (f"_v{args.views}" if args.views != 30 else "") + (f"_renders-s{args.seed}" if args.seed else ""))
    cmd = [sys.executable, "-m", "carvi_torch.reconstruct", "--data", str(renders / "annotations.json"),
           "--out", str(recon), "stage=cameras", "progress=false", f"seed={args.seed}", *args.overrides]
    out = Path(args.out) if args.out else (ROOT / "docs" / "data" / "viewpoints_cad.json"
                                           if not args.overrides and not args.seed else recon.with_suffix(".json"))
    t1 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    t_cams = time.perf_counter() - t1
    from carvi_torch.evaluate import evaluate

    res = evaluate(renders / "annotations.json", {"estimated": recon}, shapes=False, progress=False)
    rows = []
    for cls, per in sorted(res["viewpoints"].items()):
        rep = per.get("estimated", {})
        sfm, ref = rep.get("sfm", {}), rep.get("refined", {})
        if not ref:
            continue
        same = rep.get("refined_with_sfm", ref)  # the refinement's own before/after: the SfM objects
        rows.append({
            "class": cls, "n": ref["geodesic"]["n"], "n_sfm": sfm.get("geodesic", {}).get("n", 0),
            "sfm_geodesic": sfm.get("geodesic", {}).get("median"),
            "refined_geodesic_sfm_objects": same["geodesic"]["median"],
            "refined_geodesic": ref["geodesic"]["median"],
            "sfm_azimuth": sfm.get("azimuth", {}).get("median"), "refined_azimuth": same["azimuth"]["median"],
            "sfm_elevation": sfm.get("elevation", {}).get("median"), "refined_elevation": same["elevation"]["median"],
            "sfm_acc30": sfm.get("geodesic", {}).get("acc_at_30"), "refined_acc30": ref["geodesic"]["acc_at_30"],
            "mirrored": bool(ref.get("mirrored")),
            "frame": json.loads((recon / cls / "cameras.json").read_text()).get("frame"),
            "absolute_geodesic": ref["absolute"]["geodesic"]["median"],
            "absolute_azimuth": ref["absolute"]["azimuth"]["median"],
            "absolute_elevation": ref["absolute"]["elevation"]["median"],
            "up_error_deg": _up_error(ref["alignment"]),
        })
    per_model = _per_model(renders / "annotations.json", res["viewpoints"])
    f = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    lines = ["| class | views (with an SfM camera) | median geodesic SfM -> refined | median azimuth SfM -> refined | "
             "median elevation SfM -> refined | every view: refined median, acc@30 | frame mirrored | "
             "frame (up error) | absolute: geodesic, azimuth, elevation |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        worse = r["sfm_geodesic"] is not None and r["refined_geodesic_sfm_objects"] > r["sfm_geodesic"]
        views = f"{r['n']}" + ("" if r["n_sfm"] == r["n"] else f" ({r['n_sfm']})")
        lines.append(f"| {r['class']} | {views} | {f(r['sfm_geodesic'])} -> {f(r['refined_geodesic_sfm_objects'])}"
                     f"{' (worse)' if worse else ''} | {f(r['sfm_azimuth'])} -> {f(r['refined_azimuth'])} | "
                     f"{f(r['sfm_elevation'])} -> {f(r['refined_elevation'])} | {f(r['refined_geodesic'])}, "
                     f"{r['refined_acc30']:.2f} | {r['mirrored']} | {r['frame']} ({f(r['up_error_deg'])}) | "
                     f"{f(r['absolute_geodesic'])}, {f(r['absolute_azimuth'])}, {f(r['absolute_elevation'])} |")
    table = "\n".join(lines)
    print(table)
    print("(SfM -> refined: the views with an SfM camera, before and after refinement; views without one take "
          "their camera from the unseen-image path and count in the 'every view' column only)")
    improved = sum(1 for r in rows
                   if r["sfm_geodesic"] is not None and r["refined_geodesic_sfm_objects"] < r["sfm_geodesic"])
    print(f"refinement lowers the median geodesic error in {improved} of {len(rows)} classes")
    up_ok = sum(1 for r in rows if r["up_error_deg"] <= 10.0)
    print(f"the written up axis lies within 10 degrees of the CAD +z in {up_ok} of {len(rows)} classes")
    print(f"render {t_render:.1f} s, SfM + refinement of all classes {t_cams:.1f} s")
    from carvi_torch.io.outputs import write_json

    write_json(out, {"command": " ".join(shlex.quote(a) for a in ["python", "tools/viewpoints_cad.py",
                                                                      *(argv if argv is not None else sys.argv[1:])]),
                          "views": args.views, "seed": args.seed, "rows": rows, "table": table,
                          "refinement_lowers": improved, "up_within_10deg": up_ok,
                          "per_model": per_model,
                          "render_seconds": round(t_render, 1), "cameras_seconds": round(t_cams, 1)})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
