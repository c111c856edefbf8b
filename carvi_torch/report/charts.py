"""The per-class figure: viewpoint distribution, keypoint residuals, silhouette agreement, quality.

One PNG per class, drawn by matplotlib from the class's cards (:class:`carvi_torch.report.cards.Card`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.outputs import write_within

__all__ = ["class_figure"]


def _values(cards, name: str) -> np.ndarray:
    return np.array([getattr(c, name) for c in cards if getattr(c, name) is not None], dtype=np.float64)


def _hist(ax, values: np.ndarray, title: str, xlabel: str, bins=20, rng=None) -> None:
    if len(values):
        ax.hist(values, bins=bins, range=rng, color="#5577aa")
        ax.axvline(float(np.median(values)), color="#cc4444", lw=1, label=f"median {np.median(values):.3g}")
        ax.legend(fontsize=7, frameon=False)
    else:
        ax.text(0.5, 0.5, "none", ha="center", va="center", transform=ax.transAxes, color="gray")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.tick_params(labelsize=7)


def class_figure(cards: list, out: Path, rel: str) -> Path:
    """Draw the class's panels into ``out/rel`` (PNG; :func:`carvi_torch.io.outputs.write_within`: never through
    a symbolic link): azimuth (a polar histogram) with elevation, the SfM and refined keypoint residuals, the
    silhouette IoU, and the quality when the run scored it. Returns the file's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    az, el = _values(cards, "az"), _values(cards, "el")
    quality = _values(cards, "quality")
    n = 5 if len(quality) else 4
    fig = plt.figure(figsize=(2.1 * n, 2.1), dpi=72)
    ax = fig.add_subplot(1, n, 1, projection="polar")
    ax.set_theta_zero_location("N")
    if len(az):
        counts, edges = np.histogram(np.radians(az) % (2 * np.pi), bins=24, range=(0, 2 * np.pi))
        ax.bar(edges[:-1], counts, width=2 * np.pi / 24, align="edge", color="#5577aa", edgecolor="white")
    ax.set_title("azimuth (deg)", fontsize=9)
    ax.tick_params(labelsize=7)
    _hist(fig.add_subplot(1, n, 2), el, "elevation", "degrees", bins=18, rng=(-90, 90))
    ax = fig.add_subplot(1, n, 3)
    rs, rr = _values(cards, "residual_sfm"), _values(cards, "residual")
    top = float(max([1.0, *rs, *rr]))
    _hist(ax, rs, "keypoint residual (SfM)", "pixels", rng=(0, top))
    if len(rr):
        ax.hist(rr, bins=20, range=(0, top), histtype="step", color="#dd8800", label="refined")
        ax.legend(fontsize=7, frameon=False)
    _hist(fig.add_subplot(1, n, 4), _values(cards, "iou"), "silhouette IoU", "mask vs reconstruction", rng=(0, 1))
    if len(quality):
        _hist(fig.add_subplot(1, n, 5), quality, "quality", "higher is better")
    fig.tight_layout()
    try:
        return write_within(out, rel, lambda f: fig.savefig(f, format="png"), sync=False)
    finally:
        plt.close(fig)
