"""Draw docs/figures/frames.png: the image, camera and voxel-grid frames of carvi_torch.

    python tools/figure_frames.py [--out docs/figures/frames.png]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import FancyArrowPatch, Rectangle  # noqa: E402


def arrow(ax, p, q, color, text, dx=0.0, dy=0.0):
    ax.add_patch(FancyArrowPatch(p, q, arrowstyle="-|>", mutation_scale=14, lw=2, color=color))
    ax.text(q[0] + dx, q[1] + dy, text, color=color, fontsize=11, ha="center", va="center")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "figures" / "frames.png"))
    args = ap.parse_args(argv)

    fig, axes = plt.subplots(1, 3, figsize=(16, 5.5))

    # (a) image / canvas pixels
    ax = axes[0]
    ax.set_title("(a) image and canvas pixels")
    for i in range(5):
        for j in range(6):
            ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=0.5, color="0.6"))
            ax.plot(j, i, ".", color="0.4", ms=3)
    ax.add_patch(Rectangle((1.5, 0.5), 3, 3, color="tab:orange", alpha=0.35))
    arrow(ax, (0, 0), (6.2, 0), "tab:red", "x", 0.3, 0)
    arrow(ax, (0, 0), (0, 5.2), "tab:green", "y", 0, 0.3)
    ax.plot(0, 0, "o", color="k", ms=5)
    ax.text(0.1, -0.8, "origin = centre of pixel [0, 0]", fontsize=9)
    ax.text(2.5, 4.9, "pixel [i, j] has its centre at (x=j, y=i)", fontsize=9, ha="center")
    ax.text(3.0, 2.0, "mask", ha="center", fontsize=9)
    ax.text(2.5, 5.5, "canvas = a * image + b  (per instance)", fontsize=9, ha="center")
    ax.set_xlim(-1.2, 6.8)
    ax.set_ylim(6.0, -1.3)
    ax.set_aspect("equal")
    ax.axis("off")

    # (b) scaled orthographic camera
    ax = axes[1]
    ax.set_title("(b) scaled orthographic camera")
    ax.plot([-2.5, 2.5], [2.2, 2.2], color="k", lw=3)
    ax.text(2.6, 2.2, "image plane", fontsize=9, va="center")
    obj = np.array([[-0.8, -0.6], [0.9, -0.4], [0.6, 0.7], [-0.7, 0.5], [-0.8, -0.6]])
    ax.fill(obj[:, 0], obj[:, 1] - 0.5, color="tab:blue", alpha=0.3)
    for x in (-0.8, 0.9):
        ax.plot([x, x], [2.2, -1.6], ls=":", color="0.5")
    arrow(ax, (-2.2, 2.2), (-1.0, 2.2), "tab:red", "x (u)", 0, 0.25)
    arrow(ax, (-2.2, 2.2), (-2.2, -0.8), "tab:purple", "z = depth\n(into scene, R[2])", 0.1, -0.45)
    ax.text(0.0, -1.9, "uv = s * X R[:2]^T + t     z = s * X . R[2]", ha="center", fontsize=10)
    ax.text(0.0, -2.4, "R rows: image x, image y (down), view direction", ha="center", fontsize=9)
    ax.text(0.0, 2.7, "y (down) points out of the page", ha="center", fontsize=9, color="tab:green")
    ax.set_xlim(-3, 3.4)
    ax.set_ylim(-2.8, 3.0)
    ax.set_aspect("equal")
    ax.axis("off")

    # (c) voxel grid in the reference camera frame
    ax = fig.add_subplot(1, 3, 3, projection="3d")
    axes[2].axis("off")
    ax.set_title("(c) voxel grid (D, H, W), reference camera frame", pad=4)
    n = 4
    for d in range(n):
        for h in range(n):
            ax.plot([0, n - 1], [d, d], [h, h], color="0.8", lw=0.6)
            ax.plot([d, d], [0, n - 1], [h, h], color="0.8", lw=0.6)
    pts = np.array([[w, d, h] for d in range(n) for h in range(n) for w in range(n)])
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=6, color="0.4")
    ax.quiver(0, 0, 0, n, 0, 0, color="tab:red")
    ax.quiver(0, 0, 0, 0, n, 0, color="tab:purple")
    ax.quiver(0, 0, 0, 0, 0, n, color="tab:green")
    ax.text(n, -0.6, 0, "x: index w", color="tab:red")
    ax.text(0.3, n, 1.2, "z (depth): index d", color="tab:purple")
    ax.text(-0.5, 0, n + 0.5, "y (down): index h", color="tab:green")
    ax.text2D(0.02, 0.02, "(x, y, z, 1) = voxel_to_camera @ (d, h, w, 1)\n"
              "a column (h, w) is the ray of one reference pixel", transform=ax.transAxes, fontsize=9)
    ax.set_zlim(n, 0)  # y down
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
