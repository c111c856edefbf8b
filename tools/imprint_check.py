"""Imprinting on renders of the PASCAL3D+ CAD models: does every foreground pixel keep a voxel?

For each class, each render is a reference carved with two random surrogate renders of *other*
CAD models (and the mirrored copies of all three), with the true cameras, at the default 60^3
grid, once with imprinting and once without. It counts, per proposal, the reference foreground
columns (the reference mask at grid resolution) that have no interior voxel.

    python tools/imprint_check.py [--renders outputs/viewpoints_cad/renders_v30_s0] [--proposals 4]

Writes docs/results/imprint_check.json and prints a table.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--renders", default=str(ROOT / "outputs" / "viewpoints_cad" / "renders_v30_s0"),
                    help="render directory of tools/viewpoints_cad.py (annotations.json + gt.json)")
    ap.add_argument("--proposals", type=int, default=4, help="random triplets per reference")
    ap.add_argument("--resolution", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "imprint_check.json"))
    args = ap.parse_args(argv)
    from carvi_torch.cameras import ScaledOrthographic
    from carvi_torch.carve import carve_proposals
    from carvi_torch.io.coco import load_coco
    from carvi_torch.io.outputs import read_json, write_json
    from carvi_torch.sdf import signed_distance

    renders = Path(args.renders)
    if not (renders / "annotations.json").is_file():
        print(f"error: no renders in {renders}; run tools/viewpoints_cad.py first", file=sys.stderr)
        return 2
    gt = read_json(renders / "gt.json")["annotations"]
    loaded = load_coco(renders / "annotations.json")
    g = torch.Generator().manual_seed(args.seed)
    P = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))  # CAD frames are symmetric about x = 0
    rows = []
    for name, coll in sorted(loaded.collections.items()):
        n = len(coll)
        both = coll.with_mirrors()
        cam_img = ScaledOrthographic.from_list([gt[str(a)] for a in coll.annotation_ids.tolist()])
        w = coll.image_size[:, 0].float()
        cams = ScaledOrthographic.cat([cam_img.compose_similarity(coll.canvas_from_image),
                                       cam_img.mirror(w, P).compose_similarity(both.canvas_from_image[n:])])
        sdf = signed_distance(both.masks)
        # two random surrogates of other models per proposal
        same = coll.object_ids[:, None] == coll.object_ids[None, :]
        weights = (~same).float().repeat_interleave(args.proposals, dim=0)  # (n*P, n)
        sur = torch.multinomial(weights, 2, replacement=False, generator=g)  # (n*P, 2)
        ref = torch.arange(n).repeat_interleave(args.proposals)
        views = torch.cat([sur, (ref + n)[:, None], sur + n], dim=1)
        res = {}
        for imprint in (True, False):
            grids = carve_proposals(sdf, cams, ref, views, resolution=args.resolution, imprint=imprint)
            covered = grids.occupancy.any(dim=1)  # (B, H, W): columns with an interior voxel
            fg = grids.reference_columns
            missing = (fg & ~covered).flatten(1).sum(1).float()
            res[imprint] = {"proposals_with_uncovered_columns": float((missing > 0).float().mean()),
                            "uncovered_fraction": float(missing.sum() / fg.flatten(1).sum(1).sum().clamp(min=1))}
        rows.append({"class": name, "references": n, "proposals": int(len(ref)),
                     "imprint": res[True], "no_imprint": res[False]})
        print(f"{name:12s} proposals {len(ref):5d}  with imprinting: {100 * res[True]['uncovered_fraction']:.3f}% "
              f"of foreground columns empty ({100 * res[True]['proposals_with_uncovered_columns']:.1f}% of proposals)"
              f"  without: {100 * res[False]['uncovered_fraction']:.2f}% "
              f"({100 * res[False]['proposals_with_uncovered_columns']:.1f}% of proposals)")
    write_json(args.out, {"command": "python tools/imprint_check.py " + " ".join(shlex.quote(a) for a in
                                                                             (argv or sys.argv[1:])),
                          "rows": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
