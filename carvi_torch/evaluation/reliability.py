"""How well the per-object ``quality`` (cameras.json) predicts the true errors: Spearman's rho.

For every method of an evaluation (:func:`carvi_torch.evaluate.evaluate`), the objects' quality and
each of its signals (``quality_signals``) are ranked against the true viewpoint error (geodesic,
degrees, after the class's global alignment) and the true shape error (symmetric RMS, % of the
ground-truth diagonal), pooled over classes and per class. A useful quality has a negative rho
(higher quality, lower error).

Example:
    >>> spearman([1, 2, 3, 4], [4, 3, 2, 1])["rho"]
    -1.0
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import stats

from ..io.outputs import read_json

__all__ = ["spearman", "quality_vs_error", "format_quality_table"]

#: Signals whose Spearman rho is reported beside quality's (numeric ones; higher = better for none of them
#: in particular: the sign says).
SIGNALS = ("keypoint_residual", "visible_keypoints", "refinement_deg", "silhouette_inside", "mirror_deg",
           "reconstruction_iou")


def spearman(x, y) -> dict:
    """Spearman's rho and p-value of paired samples (non-finite pairs dropped; ``None`` under 3 pairs)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return {"rho": None, "p": None, "n": int(ok.sum())}
    r = stats.spearmanr(x[ok], y[ok])
    return {"rho": round(float(r.statistic), 4), "p": float(r.pvalue), "n": int(ok.sum())}


def _per_object(res: dict, method: str, recon: Path, cameras: dict) -> dict:
    """``{aid: {"class", "quality", signals..., "viewpoint_deg", "shape_percent"}}`` of one method (an entry of
    ``cameras.json`` that is not an object, or whose quality is not a number, left out; a file that cannot be
    read as one, all of its class: evaluate says why). ``cameras``: class -> its ``cameras.json`` content as
    already read (``None``: no file); a class it lacks is read from ``recon``."""
    rows: dict = {}
    for cls, per in res.get("viewpoints", {}).items():
        cams = _entries(cameras[cls]) if cls in cameras else _entries(_read(recon / cls / "cameras.json"))
        rep = per.get(method, {}).get("refined") or {}
        geo = dict(zip(map(str, rep.get("annotation_ids", [])), rep.get("per_instance_geodesic", [])))
        for aid, entry in cams.items():
            q = entry.get("quality") if isinstance(entry, dict) else None
            if isinstance(q, bool) or not isinstance(q, (int, float)):
                continue
            obj = res.get("objects", {}).get(aid, {}).get(method)
            shape = obj.get("error_percent") if isinstance(obj, dict) else None
            sig = entry.get("quality_signals") if isinstance(entry.get("quality_signals"), dict) else {}
            rows[aid] = {"class": cls, "quality": q, **{k: sig.get(k) for k in SIGNALS},
                         "viewpoint_deg": geo.get(aid), "shape_percent": shape}
    return rows


def _read(path: Path):
    """The content of a ``cameras.json`` (``None`` without a file, or one that cannot be read as JSON)."""
    try:
        return read_json(path) if path.is_file() else None
    except (OSError, ValueError):
        return None


def _entries(content) -> dict:
    """The ``cameras`` of a ``cameras.json``'s ``content`` (``{}`` for ``None``, or one that is not a JSON object
    with them).

    Example:
        >>> _entries({"cameras": {"3": {"quality": 0.5}}}), _entries(None), _entries({"cameras": []})
        ({'3': {'quality': 0.5}}, {}, {})
    """
    cams = content.get("cameras") if isinstance(content, dict) else None
    return cams if isinstance(cams, dict) else {}


def _nan(v) -> float:
    """``v`` as a float, NaN for ``None``, a non-finite value or anything that is not a number."""
    try:
        v = float(v)
    except (TypeError, ValueError, OverflowError):
        return float("nan")
    return v if math.isfinite(v) else float("nan")


def quality_vs_error(res: dict, cameras: dict | None = None) -> dict:
    """Per method: Spearman rho of quality (and of each signal) against the viewpoint and shape errors,
    pooled (``all``) and per class, and the median errors of the objects above / below the median quality.

    ``res``: an evaluation's results (``recons``, ``viewpoints``, ``objects``); ``cameras``: method -> class -> its
    ``cameras.json`` content as the evaluation read it (``None``: no file), so that no file is read twice; a method
    or class it lacks (all of them without it, e.g. for results merged from ``results.json`` files) is read from
    the method's folder in ``recons``."""
    out = {}
    for method, rdir in res.get("recons", {}).items():
        rows = _per_object(res, method, Path(rdir), (cameras or {}).get(method, {}))
        if not rows:
            continue
        entry = {}
        for scope in ["all"] + sorted({r["class"] for r in rows.values()}):
            sel = [r for r in rows.values() if scope == "all" or r["class"] == scope]
            e = {}
            for err in ("viewpoint_deg", "shape_percent"):
                y = [_nan(r[err]) for r in sel]
                e[err] = {k: spearman([_nan(r[k]) for r in sel], y) for k in ("quality",) + SIGNALS}
            q = np.array([_nan(r["quality"]) for r in sel])
            hi = q >= np.nanmedian(q)
            for err in ("viewpoint_deg", "shape_percent"):
                y = np.array([_nan(r[err]) for r in sel])
                e[err]["median_error_top_half"] = _median(y[hi])
                e[err]["median_error_bottom_half"] = _median(y[~hi])
            entry[scope] = e
        out[method] = entry
    return out


def _median(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return round(float(np.median(v)), 3) if len(v) else None


def format_quality_table(q: dict) -> str:
    """Markdown: per method and class, rho of quality vs viewpoint and shape error (n objects)."""
    lines = ["| method | class | n | rho(quality, viewpoint error) | rho(quality, shape error) | "
             "viewpoint median, top / bottom half (deg) | shape median, top / bottom half (%) |",
             "|---|---|---|---|---|---|---|"]
    for method, per in q.items():
        for scope, e in per.items():
            v, s = e["viewpoint_deg"], e["shape_percent"]

            def f(x):
                return "n/a" if x is None else f"{x:.2f}"

            lines.append(f"| {method} | {scope} | {v['quality']['n']} | {f(v['quality']['rho'])} | "
                         f"{f(s['quality']['rho'])} | {f(v['median_error_top_half'])} / "
                         f"{f(v['median_error_bottom_half'])} | {f(s['median_error_top_half'])} / "
                         f"{f(s['median_error_bottom_half'])} |")
    return "\n".join(lines)
