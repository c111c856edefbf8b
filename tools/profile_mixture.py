"""Where the mixture of shapes' time goes: CPU seconds per part of the fit, per class.

Runs ``reconstruct stage=cameras`` in this process with timers (the process's CPU clock) wrapped around
the parts of :func:`carvi_torch.viewpoints.mixture.fit_mixture_of_shapes`: every group's SfM started cold
(the first EM round) and warm (later rounds), each split into its factorisation and its bundle polish
(:mod:`carvi_torch.viewpoints.sfm`) with the outer steps and polish rounds they ran; the keypoint-only
camera fits (:func:`~carvi_torch.viewpoints.mixture.keypoint_fit`); the hull agreements; the k-means
starts; and the whole fit and viewpoint stage of every class. The wrappers only time: the cameras are
the run's own. Default data: the many-class benchmark's 584 CAD renders (``tools/benchmark.py
--many-classes``, rendered there on first use).

    python tools/profile_mixture.py [--data annotations.json] [--out PATH] [key=value ...]   # default sfm_groups=3

Prints a table per class and in total and writes the numbers to ``--out`` (JSON, default
``outputs/profile_mixture.json``).
"""
from __future__ import annotations

import argparse
import collections
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PARTS = ["cold:group_sfm", "cold:factorize", "cold:polish", "warm:group_sfm", "warm:factorize", "warm:polish",
         "keypoint_fit", "hull_agreements", "kmeans", "mixture_total", "viewpoints_total"]


class Clock:
    """CPU seconds and calls per ``(class, part)``; the part's prefix says which kind of group SfM runs."""

    def __init__(self):
        self.seconds = collections.defaultdict(lambda: collections.defaultdict(float))
        self.counts = collections.defaultdict(lambda: collections.defaultdict(int))
        self.cls, self.kind = None, "single"

    def wrap(self, name: str, fn, prefixed: bool = True):
        def timed(*a, **k):
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                key = f"{self.kind}:{name}" if prefixed else name
                self.seconds[self.cls][key] += time.process_time() - t0
                self.counts[self.cls][key] += 1
        return timed

    def add(self, name: str, n: int) -> None:
        self.counts[self.cls][f"{self.kind}:{name}"] += n


def instrument(clock: Clock) -> None:
    """Wrap the fit's parts (module attributes, so every caller goes through the wrappers)."""
    import carvi_torch.pipeline as pipeline
    import carvi_torch.viewpoints.mixture as mixture
    import carvi_torch.viewpoints.sfm as sfm

    factorize, polish, group_sfm = sfm._factorize, sfm.bundle_polish, mixture._group_sfm
    fit, viewpoints = mixture.fit_mixture_of_shapes, pipeline.estimate_viewpoints

    def counted_factorize(*a, **k):
        out = factorize(*a, **k)
        clock.add("outer_steps", out[4])
        return out

    def counted_polish(*a, **k):
        out = polish(*a, **k)
        clock.add("polish_rounds", len(out[3]))
        return out

    def kind_group_sfm(both, labels, g, n, sfm_fn, full_shape, init=None):
        before, clock.kind = clock.kind, "cold" if init is None else "warm"
        try:
            return clock.wrap("group_sfm", group_sfm)(both, labels, g, n, sfm_fn, full_shape, init)
        finally:
            clock.kind = before

    def mixture_fit(*a, **k):
        clock.kind = "mixture"
        try:
            return clock.wrap("mixture_total", fit, prefixed=False)(*a, **k)
        finally:
            clock.kind = "single"

    def class_viewpoints(coll, *a, **k):
        clock.cls = coll.meta.key
        return clock.wrap("viewpoints_total", viewpoints, prefixed=False)(coll, *a, **k)

    sfm._factorize = clock.wrap("factorize", counted_factorize)
    sfm.bundle_polish = clock.wrap("polish", counted_polish)
    mixture._group_sfm = kind_group_sfm
    for name in ("keypoint_fit", "hull_agreements", "kmeans_labels"):
        setattr(mixture, name, clock.wrap(name.replace("_labels", ""), getattr(mixture, name), prefixed=False))
    mixture.fit_mixture_of_shapes = mixture_fit
    pipeline.estimate_viewpoints = class_viewpoints


def table(clock: Clock) -> tuple[list[str], dict]:
    """Markdown rows (seconds, and calls / outer steps / polish rounds of the group SfMs) and the JSON record."""
    rec = {c: {"seconds": {k: round(v, 3) for k, v in sorted(clock.seconds[c].items())},
               "counts": dict(sorted(clock.counts[c].items()))} for c in sorted(clock.seconds)}
    total = collections.defaultdict(float)
    for c in rec.values():
        for k, v in c["seconds"].items():
            total[k] += v
    lines = ["| class | " + " | ".join(PARTS) + " |", "|---|" + "---:|" * len(PARTS)]
    for c, r in list(rec.items()) + [("**all**", {"seconds": total, "counts": {}})]:
        lines.append(f"| {c} | " + " | ".join(f"{r['seconds'].get(p, 0.0):.2f}" for p in PARTS) + " |")
    steps = collections.Counter()
    for r in rec.values():
        steps.update(r["counts"])
    for kind in ("cold", "warm"):
        calls = steps[f"{kind}:group_sfm"]
        if calls:
            lines.append(f"{kind} group SfMs: {calls}, {steps[f'{kind}:outer_steps'] / calls:.1f} outer steps and "
                         f"{steps[f'{kind}:polish_rounds'] / calls:.1f} polish rounds each")
    return lines, {"classes": rec, "total_seconds": {k: round(v, 3) for k, v in sorted(total.items())}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="COCO annotations (default: the many-class benchmark's renders)")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "profile_mixture.json"))
    ap.add_argument("overrides", nargs="*", help="reconstruct overrides (default sfm_groups=3)")
    args = ap.parse_args()
    data = args.data
    if data is None:
        sys.path.insert(0, str(ROOT / "tools"))
        from benchmark import ensure_many_classes

        data = str(ensure_many_classes(ROOT / "outputs" / "bench" / "data", 0))
    clock = Clock()
    instrument(clock)
    from carvi_torch import reconstruct

    with tempfile.TemporaryDirectory() as tmp:
        rc = reconstruct.main(["--data", data, "--out", tmp, "stage=cameras", "progress=false",
                               *(args.overrides or ["sfm_groups=3"])])
    if rc:
        return rc
    lines, rec = table(clock)
    print("\n".join(lines))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"data": data, "overrides": args.overrides or ["sfm_groups=3"], **rec},
                                         indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
