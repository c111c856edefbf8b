"""Study: a mixture of rigid SfM shapes per class, on the CAD renders (every candidate split, scored).

One rigid mean shape per class cannot fit classes whose members differ in proportions (sofa:
a long low couch, an armchair and ordinary sofas; docs/viewpoints.md); the camera then absorbs
the shape difference. This study splits a class into ``k`` groups, each with its own rigid SfM,
by hard EM (k-subspaces), without any ground truth:

1. ``k = 1``: the pipeline's rigid SfM on originals + mirrored copies (reproduces
   ``tools/viewpoints_cad.py``).
2. Initial groups for ``k > 1``, two candidates: ``lifted`` = k-means (``scipy.cluster.vq.kmeans2``,
   k-means++ starts, best of 10) of every object's single-model reprojection residuals lifted into
   the object frame (``R[:2]^T r / s``; object and mirrored copy side by side, unit norm);
   ``residual`` = quantiles of every object's single-model keypoint residual.
3. Alternate (at most 6 rounds): rigid SfM per group (objects with their mirrored copies); a
   keypoint-only camera of every object under every group's mean shape
   (:func:`carvi_torch.refine.estimate_camera`, ``silhouette_weight=0``); move every object to the
   group with the lowest squared pixel residual (object + mirrored copy). Groups below
   ``--min-group`` objects take the objects that cost least to move. As in the pipeline, the
   keypoint fits start from the one-shape fit and then from the last round, and the groups'
   SfM from their last shape (the warm starts of :func:`carvi_torch.sfm_mixture.hard_em`).
4. One class frame: every group's mean shape is rotated onto group 0's (a proper rotation fitted
   on their shared keypoints, centred and scaled: ``scipy.spatial.transform.Rotation.align_vectors``)
   and its cameras with it.
5. The silhouette refinement of the pipeline, per group, with that group's rotated mean shape.
6. Of the two initialisations the one with the lower total residual is kept.

The ground truth (``gt.json`` of the renders) is read only to score: median geodesic error
after one global rotation (:func:`carvi_torch.viewpoint_metrics.viewpoint_report`, as
``evaluate`` does), per CAD model, and which models each group holds. The table also applies
an unsupervised selection rule (``--rule``): ``k = 2`` when it lowers the total squared residual
by more than that fraction against ``k = 1``, ``k = 3`` when it lowers it by more than that
against ``k = 2``.

    python tools/viewpoints_cad.py                       # renders the CAD models (cached)
    python tools/sfm_mixture_study.py [--classes sofa] [--k 1 2 3] [--out docs/results/sfm_mixture.json]

About 5 to 50 s per class on one core (5 minutes for the 12 CAD classes).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from carvi_torch import pipeline  # noqa: E402
from carvi_torch.config import load_config  # noqa: E402
from carvi_torch.io import coco  # noqa: E402
from carvi_torch.io.outputs import write_json  # noqa: E402
from carvi_torch.sdf import distance_to_mask  # noqa: E402
from carvi_torch.sfm_mixture import (MixtureResult, SplitFailed, frame_agreement, group_rotations,  # noqa: E402
                                     group_rows, hard_em, keypoint_fit, kmeans_labels, lifted_residuals,
                                     top_up)
from carvi_torch.viewpoint_metrics import summarize, viewpoint_report  # noqa: E402

RENDERS = ROOT / "outputs" / "viewpoints_cad" / "renders_v30_s0" / "annotations.json"


def group_sfm(both, idx: torch.Tensor, n: int, cfg):
    """Rigid SfM of objects ``idx`` and their mirrored copies; returns (rows of ``both``, SfMResult)."""
    rows = group_rows(idx, n)
    return rows, pipeline.class_sfm(both[rows], cfg)


def fit_mixture(both, n, dist, cfg, labels, k, min_size, full_shape, warm, rounds=6):
    """Hard EM from ``labels (n,)`` with the pipeline's SfM and warm starts
    (:func:`carvi_torch.sfm_mixture.hard_em`)."""
    return hard_em(both, n, dist, lambda sub, init_shape=None: pipeline.class_sfm(sub, cfg, init_shape), labels, k,
                   min_size, rounds, full_shape=full_shape, warm=warm)


def class_cameras(both, n, dist, cfg, groups, Q, single):
    """SfM and refined cameras (2n) in group 0's frame, as the pipeline computes them for a kept split
    (:func:`carvi_torch.pipeline.group_sfm_cameras`, ``refine_groups``, ``unseen_per_group``);
    ``single`` is the one-shape SfM of the whole class (every row); returns (sfm cams, sfm valid, refined cams)."""
    mix = MixtureResult(len(groups), torch.zeros(n, dtype=torch.long), groups, Q, 0.0, single)
    sfm_cams, valid = pipeline.group_sfm_cameras(mix)
    cams = pipeline.refine_groups(mix, sfm_cams, both, dist, cfg)[0] if cfg.refine else sfm_cams
    # objects without an SfM camera: the unseen-image path, as the pipeline
    return sfm_cams, valid, pipeline.unseen_per_group(mix, cams, ~valid, both, dist, cfg)


def score(coll, cams, ok, gt_R, models):
    """Median geodesic error (degrees) after one global rotation, overall and per CAD model
    (:func:`carvi_torch.viewpoint_metrics.summarize`: an even count's median is the mean of
    the two middle values, as everywhere in the project)."""
    img = cams[: len(coll)].compose_similarity(coll.canvas_from_image.inverse())
    rep = viewpoint_report(img.R.double(), gt_R, valid=ok[: len(coll)])
    err = torch.tensor(rep["per_instance_geodesic"], dtype=torch.float64)
    per_model = {}
    for m in sorted(set(models)):
        med = summarize(err[[i for i, x in enumerate(models) if x == m]])["median"]
        per_model[m] = None if med != med else round(med, 1)  # NaN: no finite error
    return round(rep["geodesic"]["median"], 2), per_model


def study_class(coll, gt, cfg, ks, min_size, seed):
    n = len(coll)
    both = coll.with_mirrors()
    dist = distance_to_mask(both.masks)
    aids = coll.annotation_ids.tolist()
    models = [gt[str(a)].get("model", "?") for a in aids]
    gt_R = torch.tensor([gt[str(a)]["R"] for a in aids], dtype=torch.float64)
    seen = both.visible & torch.isfinite(both.keypoints).all(-1)
    nvis_obj = (seen[:n].sum(-1) + seen[n:].sum(-1)).clamp(min=1)  # (n,)
    nvis = float(nvis_obj.sum())
    rows1, res1 = group_sfm(both, torch.arange(n), n, cfg)
    cost1, cams1 = keypoint_fit(res1.shape, both, dist, n)
    R1 = cams1.R[:n]
    lifted = lifted_residuals(res1, both.keypoints[rows1], both.visible[rows1])
    lifted = torch.cat([lifted[:n], lifted[n:]], 1)
    lifted = lifted / lifted.norm(dim=1, keepdim=True).clamp(min=1e-9)
    out = {}
    for k in ks:
        if k == 1:
            cands = [("single", torch.zeros(n, dtype=torch.long), [(rows1, res1)], cost1[:, None], [R1], [])]
        else:
            cands = []
            inits = {"lifted": kmeans_labels(lifted, k, seed),
                     "residual": ((cost1 / nvis_obj).argsort(stable=True).argsort(stable=True) * k // n).clamp(max=k - 1)}
            for name, lab0 in inits.items():
                lab0 = top_up(lab0, torch.zeros(n, k), k, min_size)
                try:
                    cands.append((name, *fit_mixture(both, n, dist, cfg, lab0, k, min_size, res1.shape,
                                                     (res1.shape, cams1))))
                except SplitFailed as e:
                    print(f"  k={k} {name}: not usable: {e}", flush=True)
        rows = []
        for name, lab, groups, cost, rotations, hist in cands:
            sse = float(cost.gather(1, lab[:, None]).sum())
            try:
                Q = group_rotations(groups)
            except ValueError as e:
                print(f"  k={k} {name}: no class frame: {e}", flush=True)
                continue
            sfm_cams, sfm_ok, ref_cams = class_cameras(both, n, dist, cfg, groups, Q, res1)
            sfm_med, sfm_pm = score(coll, sfm_cams, sfm_ok, gt_R, models)
            ref_med, ref_pm = score(coll, ref_cams, torch.ones(2 * n, dtype=torch.bool), gt_R, models)
            agree = frame_agreement(rotations, Q, valid=res1.valid[:n])
            rows.append({"init": name, "sse_px2": sse, "rms_px": (sse / nvis) ** 0.5, "frame_agreement_deg": agree,
                         "sfm": sfm_med,
                         "refined": ref_med, "sfm_per_model": sfm_pm, "refined_per_model": ref_pm,
                         "groups": {g: {m: [models[i] for i in (lab == g).nonzero().squeeze(1).tolist()].count(m)
                                        for m in sorted(set(models))} for g in range(k)},
                         "history": hist})
            print(f"  k={k} {name}: rms {rows[-1]['rms_px']:.3f} px, frames agree within {agree:.1f} deg, "
                  f"SfM {sfm_med:.1f}, refined {ref_med:.1f} deg, "
                  f"sizes {torch.bincount(lab, minlength=k).tolist()}", flush=True)
        chosen = min(rows, key=lambda r: r["sse_px2"])["init"] if rows else None  # unsupervised: the lower residual
        out[str(k)] = {"chosen": chosen, "candidates": rows}
    return out


def pick(entry: dict, rule: float, agreement: float | None = None) -> tuple[int, dict]:
    """The rule's choice of ``k`` for one class and the candidate it uses per ``k``.

    Per ``k`` the candidate is the lower-residual initialisation; with ``agreement`` (degrees),
    only among those whose groups' frames agree within it (:func:`frame_agreement`). One more
    group is taken while it has such a candidate and cuts the residual by more than ``rule``.
    """
    ch = {}
    for k, v in entry.items():
        if agreement is not None and int(k) > 1 and any("frame_agreement_deg" not in c for c in v["candidates"]):
            raise ValueError("--agreement needs a JSON written by a study that measured frame_agreement_deg")
        ok = [c for c in v["candidates"]
              if agreement is None or int(k) == 1 or c["frame_agreement_deg"] <= agreement]
        if ok:
            ch[int(k)] = min(ok, key=lambda c: c["sse_px2"])
    k = 1
    while k + 1 in ch and 1 - ch[k + 1]["sse_px2"] / max(ch[k]["sse_px2"], 1e-12) > rule:
        k += 1
    return k, ch


def _cut(sse: float, previous: float) -> str:
    """The residual cut of one more group, as a percentage (or 'residual up')."""
    cut = 1 - sse / max(previous, 1e-12)
    return f"{cut:.0%}" if cut >= 0 else "residual up"


def table(results: dict, rule: float, agreement: float | None = None) -> str:
    ks = sorted({int(k) for e in results.values() for k in e})
    head = ["class"] + [f"k={k}: SfM -> refined (residual cut vs k={k - 1})" if k > 1 else "k=1: SfM -> refined"
                        for k in ks]
    head += [f"rule (> {rule:.0%} per step{'' if agreement is None else f', frames within {agreement:g} deg'}) picks",
             "picked: SfM -> refined"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cls in sorted(results):
        k_pick, ch = pick(results[cls], rule, agreement)
        cells = [cls]
        for k in ks:
            c = ch.get(k)
            if c is None:
                cells.append("")
                continue
            cut = "" if k == 1 or k - 1 not in ch else f" ({_cut(c['sse_px2'], ch[k - 1]['sse_px2'])})"
            agree = "" if k == 1 or "frame_agreement_deg" not in c else f" [{c['frame_agreement_deg']:.0f} deg]"
            cells.append(f"{c['sfm']:.1f} -> {c['refined']:.1f}{cut}{agree}")
        cells += [str(k_pick), f"{ch[k_pick]['sfm']:.1f} -> {ch[k_pick]['refined']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def figure(results: dict, path: Path) -> None:
    """Scatter of every split (class, k > 1, initialisation): frame agreement vs refined error over k=1's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for k, marker in ((2, "o"), (3, "s")):
        pts = [(c["frame_agreement_deg"], c["refined"] / e["1"]["candidates"][0]["refined"], cls)
               for cls, e in results.items()
               for c in e.get(str(k), {}).get("candidates", []) if "frame_agreement_deg" in c]
        if pts:
            ax.scatter([p[0] for p in pts], [p[1] for p in pts], marker=marker, alpha=0.75, label=f"k={k}")
            for x, y, cls in pts:
                if y > 1.1 or x > 60:
                    ax.annotate(cls, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("groups' frames agree within (deg, no ground truth)")
    ax.set_ylabel("refined median geodesic error / one shape's")
    ax.set_yscale("log")
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_yticks([0.5, 1, 2, 4, 8])
    ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_title("Mixture of rigid shapes on the CAD renders: every split")
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--data", default=str(RENDERS), help="annotations.json of the renders (gt.json beside it)")
    ap.add_argument("--classes", nargs="*", default=None, help="default: every class of the renders")
    ap.add_argument("--k", nargs="*", type=int, default=[1, 2, 3], help="group counts to fit")
    ap.add_argument("--min-group", type=int, default=15, help="fewest objects per group")
    ap.add_argument("--rule", type=float, default=0.3, help="residual cut that accepts one more group")
    ap.add_argument("--agreement", type=float, default=None, metavar="DEG",
                    help="also require the groups' frames to agree within DEG degrees (table only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "sfm_mixture.json"))
    ap.add_argument("--figure", metavar="PNG", default=None,
                    help="also plot frame agreement against the refined error of every split")
    ap.add_argument("--table", metavar="JSON", default=None,
                    help="print the table of an earlier run's JSON (with --rule) and stop")
    args = ap.parse_args(argv)
    if args.table:
        loaded_json = json.loads(Path(args.table).read_text())["classes"]
        print(table(loaded_json, args.rule, args.agreement))
        if args.figure:
            figure(loaded_json, Path(args.figure))
        return 0
    data = Path(args.data)
    if not data.is_file() or not (data.parent / "gt.json").is_file():
        raise SystemExit(f"no renders at {data} (with gt.json beside it): run python tools/viewpoints_cad.py first")
    if not args.k or min(args.k) < 1 or 1 not in args.k:
        raise SystemExit("--k must include 1 (the baseline) and hold positive counts")
    torch.set_num_threads(1)
    cfg = load_config(None, [])
    gt = json.loads((data.parent / "gt.json").read_text())
    gt = gt.get("annotations", gt)
    loaded = coco.load_coco(data, canvas_size=cfg.canvas_size, margin=cfg.canvas_margin, classes=args.classes)
    results, seconds = {}, {}
    for name in sorted(loaded.collections):
        t0 = time.perf_counter()
        print(f"{name}:", flush=True)
        results[name] = study_class(loaded.collections[name], gt, cfg, sorted(set(args.k)), args.min_group, args.seed)
        seconds[name] = round(time.perf_counter() - t0, 1)
    text = table(results, args.rule, args.agreement)
    print(text)
    if args.figure:
        figure(results, Path(args.figure))
    write_json(Path(args.out), {"command": "python tools/sfm_mixture_study.py " + " ".join(argv or sys.argv[1:]),
                                "data": str(data), "rule": args.rule, "agreement_deg": args.agreement, "min_group": args.min_group, "seed": args.seed,
                                "seconds": seconds, "table": text, "classes": results})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
