"""Which refined cameras are worse than their SfM cameras, and what tells them apart without ground truth.

On the renders of ``tools/viewpoints_cad.py`` (run it first: ``--views 8 --seed 0,1,2``), every class is
estimated with ``refine_keep=refined`` (the refined cameras whatever they score); every object's SfM
and refined cameras are compared with the truth (median geodesic error after one fitted rotation per
class and camera set, as ``evaluate`` does), and scored by what the pipeline can see:

* ``keypoint_growth``: the rise of the keypoint RMS error over the mask's box diagonal;
* ``hull_gain``: the rise of the IoU of the mask and the projected mean shape's convex hull;
* ``silhouette_gain``: the fall of the mean distance (over the box diagonal) from the projected mean-shape
  points to the mask;
* ``energy_drop``: the refinement's own relative energy drop;
* ``turn``: degrees between the two cameras;
* ``tilt_change``: the rise of the image tilt of the class's up (``viewpoints.choice.image_tilt``).

It prints, per band of the true error change (refined minus SfM), how many objects the tilt test
(``refine_max_tilt_deg``) and the suspect test (``refine_keep``) flag, and each score's AUC between the
objects refinement made worse and those it made better by more than 2 degrees; and, as a bound on any
per-object choice, the classes whose median would be no worse than SfM at every seed if each object
kept its better camera by the truth (the class aligned again after the choice).

    python tools/refine_choice_study.py [--work outputs/viewpoints_cad] [--views 8] [--seed 0,1,2]
                                         [--cameras photo|level] [--out PATH]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default=str(ROOT / "outputs" / "viewpoints_cad"))
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--seed", default="0,1,2")
    ap.add_argument("--cameras", default="photo")
    ap.add_argument("--out", default=None, help="JSON of the counts (default: beside the renders)")
    args = ap.parse_args(argv)
    from carvi_torch.io.coco import load_coco

    torch.set_num_threads(1)
    rows: dict = {}
    per_class: dict = {}
    for seed in [int(s) for s in args.seed.split(",")]:
        renders = Path(args.work) / (f"renders_v{args.views}_s{seed}" + ("" if args.cameras == "photo"
                                                                         else f"_{args.cameras}"))
        if not (renders / "annotations.json").is_file():
            print(f"error: {renders} has no renders (run tools/viewpoints_cad.py first)", file=sys.stderr)
            return 2
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
    out.write_text(json.dumps({"command": " ".join(["python", "tools/refine_choice_study.py", *(argv or sys.argv[1:])]),
                               "bands": bands, "auc_worse_vs_better": auc, "best_per_object_not_worse": best_ok,
                               "per_class": per_class}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
