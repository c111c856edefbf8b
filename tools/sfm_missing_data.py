"""Missing-data SfM accuracy: one rigid shape, random cameras, missing entries, with and without noise.

    python tools/sfm_missing_data.py [--instances 200] [--keypoints 12] [--missing 0.4] [--seeds 5]

For each seed: a random rigid shape (K keypoints), N random scaled orthographic cameras,
``missing`` of every instance's keypoints hidden at random (no depth cue, so the frame can come
back mirrored: the better of the two is scored), optionally Gaussian noise of 1% of each
instance's projected extent. Errors are geodesic, after the one global rotation
(``viewpoint_metrics.align_rotations``). Prints a table, writes docs/results/sfm_missing_data.json.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from carvi_torch.cameras import ScaledOrthographic, random_rotations  # noqa: E402
from carvi_torch.sfm import rigid_sfm  # noqa: E402
from carvi_torch.viewpoint_metrics import align_rotations, geodesic_errors  # noqa: E402

F = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))


def one(seed, n, k, missing, noise):
    g = torch.Generator().manual_seed(seed)
    S = torch.randn(k, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64)
    R = random_rotations(n, g, dtype=torch.float64)
    cams = ScaledOrthographic(R, 40 + 10 * torch.rand(n, generator=g, dtype=torch.float64),
                              64 + 5 * torch.randn(n, 2, generator=g, dtype=torch.float64))
    kp = cams.project(S - S.mean(0))
    extent = (kp.amax(1) - kp.amin(1)).amax(-1)
    kp = kp + noise * extent[:, None, None] * torch.randn(kp.shape, generator=g, dtype=torch.float64)
    vis = torch.rand(n, k, generator=g).argsort(1).argsort(1) >= round(missing * k)
    res = rigid_sfm(kp.float(), vis)
    best = None
    for Rest in (res.cameras.R.double(), F @ res.cameras.R.double() @ F):
        G = align_rotations(Rest, R)
        e = geodesic_errors(Rest, R, G).numpy()
        if best is None or np.median(e) < np.median(best):
            best = e
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--instances", type=int, default=200)
    ap.add_argument("--keypoints", type=int, default=12)
    ap.add_argument("--missing", type=float, default=0.4)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "sfm_missing_data.json"))
    args = ap.parse_args(argv)
    rows = []
    for noise in (0.0, 0.01):
        errs = np.concatenate([one(s, args.instances, args.keypoints, args.missing, noise) for s in range(args.seeds)])
        rows.append({"noise": noise, "cameras": int(errs.size), "median_deg": float(np.median(errs)),
                     "max_deg": float(errs.max()), "p95_deg": float(np.percentile(errs, 95))})
        print(f"noise {noise:4.2f}: {errs.size} cameras, median {np.median(errs):.4f} deg, "
              f"95th pct {np.percentile(errs, 95):.4f}, max {errs.max():.4f}")
    from carvi_torch.io.outputs import write_json

    write_json(args.out, {"command": "python tools/sfm_missing_data.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])), "instances": args.instances,
        "keypoints": args.keypoints, "missing": args.missing, "seeds": args.seeds, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
