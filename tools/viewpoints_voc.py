"""Viewpoints of the real PASCAL VOC aeroplanes against PASCAL3D+: SfM and refined, one table.

The three steps a user runs, then the comparison:

    python -m carvi_torch.datasets voc --keypoints DATA/pascal_voc_aeroplane/keypoints --out WORK/annotations.json
    python -m carvi_torch.reconstruct --data WORK/annotations.json --out WORK/cameras stage=cameras
    (cameras.json vs DATA/pascal_voc_aeroplane/viewpoints_dev.json, carvi_torch.viewpoint_metrics)

Errors are measured after one global rotation aligning the SfM class frame with the CAD frame,
on the objects that have a PASCAL3D+ viewpoint (165 of 330) and an SfM camera; the refined
cameras are scored on the same objects. Berkeley keypoint names use ``left_convention="object"``
(the converter's default).

    python tools/viewpoints_voc.py [--data ../shared/data] [--work outputs/viewpoints_voc]
                                   [--out docs/results/viewpoints_voc.json] [key=value ...]
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
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT / ".." / "shared" / "data"), help="the shared data folder")
    ap.add_argument("--work", default=str(ROOT / "outputs" / "viewpoints_voc"), help="annotations and cameras go here")
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "viewpoints_voc.json"))
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="extra reconstruct overrides")
    args = ap.parse_args(argv)
    src = Path(args.data) / "pascal_voc_aeroplane"
    if not (src / "keypoints").is_dir() or not (src / "viewpoints_dev.json").is_file():
        print(f"error: {src} has no keypoints/ and viewpoints_dev.json (the PASCAL VOC aeroplanes)", file=sys.stderr)
        return 2
    import torch

    from carvi_torch.io.outputs import read_json, write_json
    from carvi_torch.viewpoint_metrics import viewpoint_report

    work = Path(args.work)
    ann = work / "annotations.json"
    py = sys.executable
    subprocess.run([py, "-m", "carvi_torch.datasets", "voc", "--keypoints", str(src / "keypoints"), "--out", str(ann)],
                   check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    t0 = time.perf_counter()
    subprocess.run([py, "-m", "carvi_torch.reconstruct", "--data", str(ann), "--out", str(work / "cameras"),
                    "stage=cameras", "progress=false", "overwrite=true", *args.overrides],
                   check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - t0
    cams = read_json(work / "cameras" / "aeroplane" / "cameras.json")["cameras"]
    gt = json.loads((src / "viewpoints_dev.json").read_text())
    rows = []
    by_source = {Path(c["source"]).stem: c for c in cams.values()}
    keys = sorted(k for k in gt if k in by_source and by_source[k].get("sfm") is not None)
    R_gt = torch.tensor([gt[k]["R"] for k in keys], dtype=torch.float64)
    out = {}
    for stage in ("sfm", "refined"):
        R = torch.tensor([by_source[k][stage]["R"] for k in keys], dtype=torch.float64)
        rep = viewpoint_report(R, R_gt)
        out[stage] = {"n": rep["n"], "geodesic_median": rep["geodesic"]["median"],
                      "acc_at_30": rep["geodesic"]["acc_at_30"], "azimuth_median": rep["azimuth"]["median"],
                      "elevation_median": rep["elevation"]["median"], "mirrored": rep["mirrored"]}
        rows.append(f"| {stage} | {rep['n']} | {rep['geodesic']['median']:.1f} | {rep['geodesic']['acc_at_30']:.2f} | "
                    f"{rep['azimuth']['median']:.1f} | {rep['elevation']['median']:.1f} | {rep['mirrored']} |")
    table = "\n".join(["| stage | n | median geodesic | acc@30 | median azimuth | median elevation | mirrored |",
                       "|---|---|---|---|---|---|---|", *rows])
    print(table)
    print(f"objects converted: {len(cams)}; with a PASCAL3D+ viewpoint and an SfM camera: {len(keys)}; "
          f"reconstruct stage=cameras {seconds:.1f} s")
    cmd = " ".join(shlex.quote(a) for a in ["python", "tools/viewpoints_voc.py",
                                            *(argv if argv is not None else sys.argv[1:])])
    write_json(args.out, {"command": cmd, "objects": len(cams), "scored": len(keys), **out, "table": table,
                          "cameras_seconds": round(seconds, 1)})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
