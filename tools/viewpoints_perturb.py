"""How stable are the CAD-render viewpoint medians under rounding-sized keypoint changes?

Reruns ``tools/viewpoints_cad.py`` on copies of its renders whose visible keypoints are moved by
Gaussian noise of ``--eps`` pixels (far below what a render or an annotator resolves), one copy
per seed, and prints the median geodesic error (SfM -> refined) of each run. A median that moves
by degrees under 0.001-pixel changes is luck, not a measurement.

    python tools/viewpoints_perturb.py --classes tvmonitor,bus [key=value ...]
        [--eps 0,0.001,0.001,0.001,0.01,0.01] [--out docs/results/viewpoints_perturb.json]

Needs the renders of ``tools/viewpoints_cad.py`` (run it once first; ``--renders``).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def perturbed_copy(src: Path, dst: Path, eps: float, seed: int) -> None:
    """``src``'s renders (annotations, gt.json, meshes linked) with visible keypoints moved by N(0, eps) pixels."""
    dst.mkdir(parents=True, exist_ok=True)
    data = json.loads((src / "annotations.json").read_text())
    g = np.random.default_rng(seed)
    for a in data["annotations"]:
        kp = np.asarray(a["keypoints"], dtype=np.float64).reshape(-1, 3)
        kp[:, :2] += np.where(kp[:, 2:] > 0, g.normal(0.0, eps, kp[:, :2].shape), 0.0)
        a["keypoints"] = kp.reshape(-1).tolist()
    (dst / "annotations.json").write_text(json.dumps(data))
    shutil.copy(src / "gt.json", dst / "gt.json")
    if not (dst / "meshes").exists():
        (dst / "meshes").symlink_to((src / "meshes").resolve())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--classes", default="tvmonitor", help="comma-separated classes")
    ap.add_argument("--eps", default="0,0.001,0.001,0.001,0.01,0.01",
                    help="noise (pixels) of each run; run i uses seed i")
    ap.add_argument("--renders", default=str(ROOT / "outputs" / "viewpoints_cad" / "renders_v30_s0"))
    ap.add_argument("--work", default=str(ROOT / "outputs" / "viewpoints_perturb"))
    ap.add_argument("--out", default=None, help="JSON path (optional)")
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="extra reconstruct overrides")
    args = ap.parse_args(argv)
    src = Path(args.renders)
    if not (src / "annotations.json").is_file():
        print(f"error: {src} has no renders (run tools/viewpoints_cad.py first)", file=sys.stderr)
        return 2
    classes = [c for c in args.classes.split(",") if c]
    eps = [float(e) for e in args.eps.split(",")]
    tag = "".join("_" + "".join(ch if ch.isalnum() else "-" for ch in o) for o in args.overrides)
    rows = []
    t0 = time.perf_counter()
    for seed, e in enumerate(eps):
        work = Path(args.work) / f"seed{seed}_eps{e:g}{tag}"
        perturbed_copy(src, work / src.name, e, seed)
        out = work / "viewpoints.json"
        cmd = [sys.executable, str(ROOT / "tools" / "viewpoints_cad.py"), "--cad", str(ROOT), "--work", str(work),
               "--views", src.name.split("_")[1].lstrip("v"), "--seed", src.name.split("_s")[-1], "--out", str(out),
               "classes=" + ",".join(classes), *args.overrides]
        subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        for r in json.loads(out.read_text())["rows"]:
            rows.append({"class": r["class"], "seed": seed, "eps_px": e, "sfm_geodesic": r["sfm_geodesic"],
                         "refined_geodesic": r["refined_geodesic"], "refined_acc30": r["refined_acc30"]})
            print(f"{r['class']:<12} seed {seed} eps {e:<6g} SfM {r['sfm_geodesic']:5.1f} -> refined "
                  f"{r['refined_geodesic']:5.1f}  acc@30 {r['refined_acc30']:.2f}", flush=True)
    summary = {}
    for c in classes:
        ref = [r["refined_geodesic"] for r in rows if r["class"] == c]
        summary[c] = {"refined_min": min(ref), "refined_max": max(ref)}
        print(f"{c}: refined median from {min(ref):.1f} to {max(ref):.1f} over {len(ref)} runs")
    if args.out:
        Path(args.out).write_text(json.dumps({
            "command": "python tools/viewpoints_perturb.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "rows": rows, "summary": summary, "seconds": round(time.perf_counter() - t0, 1)}, indent=1))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
