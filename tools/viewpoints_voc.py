"""Viewpoints of the real PASCAL VOC aeroplanes against PASCAL3D+ only: the quick check (about 15 s).

The viewpoint steps of ``tools/voc_study.py`` (which also reconstructs every shape, estimates
cameras of unseen images and compares shapes with the CAD models, about 8 minutes), run with
``stage=cameras``: convert the Berkeley keypoint files, ``python -m carvi_torch.reconstruct
stage=cameras``, then the SfM and refined cameras against ``viewpoints_dev.json`` after one
global rotation (:func:`carvi_torch.evaluation.viewpoint_metrics.viewpoint_report`).

    python tools/viewpoints_voc.py [--data ../shared/data] [--work outputs/viewpoints_voc]
                                   [--out docs/results/viewpoints_voc.json] [key=value ...]

``key=value`` are reconstruct overrides, e.g. ``silhouette_robust=0`` for the paper's squared
silhouette penalty.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

import voc_study  # noqa: E402

from carvi_torch.io.outputs import write_json  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT / ".." / "shared" / "data"), help="the shared data folder")
    ap.add_argument("--work", default=str(ROOT / "outputs" / "viewpoints_voc"), help="annotations and cameras go here")
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "viewpoints_voc.json"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="extra reconstruct overrides")
    args = ap.parse_args(argv)
    data, work = Path(args.data).resolve(), Path(args.work).resolve()
    src = data / "pascal_voc_aeroplane"
    if not (src / "keypoints").is_dir() or not (src / "viewpoints_dev.json").is_file():
        print(f"error: {src} has no keypoints/ and viewpoints_dev.json (the PASCAL VOC aeroplanes)", file=sys.stderr)
        return 2
    work.mkdir(parents=True, exist_ok=True)
    conv = voc_study.step_convert(data, work)
    recon = voc_study.step_reconstruct(Path(conv["annotations"]), work / "cameras",
                                       ["stage=cameras", "overwrite=true", *args.overrides], args.device)
    gt = json.loads((src / "viewpoints_dev.json").read_text())
    vp = voc_study.step_viewpoints(work / "cameras", gt)
    summary = {stage: {"n": vp[stage]["report"]["n"],
                       **{f"{a}_median": vp[stage]["report"][a]["median"] for a in ("geodesic", "azimuth", "elevation")},
                       "acc_at_30": vp[stage]["report"]["geodesic"]["acc_at_30"],
                       "mirrored": vp[stage]["report"]["mirrored"]} for stage in ("sfm", "refined")}
    cmd = " ".join(shlex.quote(a) for a in ["python", "tools/viewpoints_voc.py",
                                            *(argv if argv is not None else sys.argv[1:])])
    write_json(args.out, {"command": cmd, "objects": conv["converted"], **summary,
                          "acceptance": vp["acceptance"], "cameras_seconds": recon["total_seconds"]})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
