"""Benchmark: rigid SfM + silhouette refinement for one synthetic class.

A random bilaterally symmetric rigid shape with ``--k`` keypoints (default 12) is
deformed a little per instance and seen by ``--n`` random scaled orthographic
cameras in a square canvas; keypoints get 1% noise, the farthest 30% are hidden
(self-occlusion) and 5% more drop out at random; masks are the filled convex
hulls of the instance's projected keypoints. Every instance also gets its
left-right mirrored copy (x' = W - 1 - x, left/right labels swapped), as the
pipeline does, so the class holds ``2 n`` instances.

Timed stages: exact distance maps, rigid SfM, silhouette refinement, with the pipeline's settings
(``ViewpointConfig``: the polish, its rounds, the tolerance, the compiled factorisation, the mixture's
groups; ``--set`` changes them, e.g. ``--set viewpoints.sfm_polish=alternate``). Prints a
table (seconds, instances per second, peak memory) and the viewpoint errors
against the true cameras, and writes everything to ``--out`` as JSON.

With ``--groups 3`` it also times the fit of a mixture of rigid shapes
(:func:`carvi_torch.viewpoints.mixture.fit_mixture_of_shapes`, the pipeline's ``sfm_groups``
settings) on the same class. The class is one rigid shape, so the fit tries two
groups (two initialisations, as every k = 2), finds no residual cut worth a split and stops: a
lower bound on what the option costs on a class that does split; ``--shapes 3`` makes one
(every third instance stretched longer and lower, every third shorter and taller), so the fit
also tries three groups (three initialisations). The fit runs each ``k``'s initialisations on ``--group-threads``
Python threads (the pipeline's ``sfm_group_threads``); ``--one-thread-too`` also times it on one
and checks that the result is the same (below ``sfm_mixture.THREADS_MIN_OBJECTS`` objects the fit
stays on one thread; ``--threads-min-objects 0`` lifts that, to measure what threads do to a
small class), ``--cold-too`` also times it without its warm starts,
both in the same run. Then every group's cameras are refined with its own mean shape, as the
pipeline does (:func:`carvi_torch.viewpoints.refine.refine_groups`; ``--max-iters`` steps); "stage
with mixture" is the one-shape SfM, the fit and that refinement.

    python tools/bench_viewpoints.py [--n 2000] [--device cpu] [--groups 1] [--shapes 1] [--cold-too]
                                     [--group-threads 2] [--one-thread-too] [--threads-min-objects N]
                                     [--out PATH] [--key KEY]

``--profile-mixture DATA`` runs none of that: it profiles the pipeline's mixture fit on a COCO file
(``reconstruct stage=cameras`` in this process, ``--profile-set`` its overrides, default none: the defaults)
with timers on the process's CPU clock around the fit's parts: every group's SfM started cold (the first EM
round) and warm (later rounds), each split into its factorisation
(:mod:`carvi_torch.viewpoints.factorization`) and bundle polish (:mod:`carvi_torch.viewpoints.sfm`) with the
outer steps and polish rounds they ran, the keypoint-only camera fits, the hull agreements, the k-means
starts, the whole fit and viewpoint stage per class (the timers only time: the cameras are the run's own). It
prints a table per class and writes the numbers to ``--out`` (default ``outputs/profile_mixture.json``; with
``--key``, under that key of ``--out``, default ``docs/data/viewpoints.json``); docs/viewpoints.md's *Cost*
profiles the many-class benchmark's renders:

    python tools/bench_viewpoints.py --profile-mixture outputs/bench/data/cad_v8_s0/annotations.json \\
        --key mixture_profile_cad8

``--cameras-cpu DATA`` runs none of that either: it times ``reconstruct --data DATA stage=cameras`` as child
processes, one per variant (``--variants``, each a space-separated list of overrides; default ``sfm_groups=1``
against the default ``sfm_groups``), ``--rounds`` times (default 2), the variants interleaved (their order reversed
every other round), and records each run's CPU seconds (user + system of the child and of the processes it waited
for), wall seconds, the 1-minute load average before and after, the groups each class kept and the classes the
mixture was fitted for (``summary.json``) and a digest of every ``cameras.json`` (the same settings give the same
cameras in every round); the ratios of every variant's CPU seconds to the first's, per round and of the least of
each (docs/viewpoints.md, *Cost*):

    python tools/bench_viewpoints.py --cameras-cpu outputs/bench/data/cad_v8_s0/annotations.json --key cameras_cpu_cad8

``--kernels DATA`` times two of the mixture's inner operations class by class on a COCO file, on one thread, best
of ``--rounds``: the joint bundle adjustment (from the class's factorisation, 100 damped solves at most) in the
compiled kernel against the torch operators, per damped solve and with the two results' largest camera angle; and
the hull agreements of every row under its SfM camera, batched against the per-row reference, with whether they
are equal (docs/viewpoints.md, the compiled kernels and *Keeping SfM cameras*):

    python tools/bench_viewpoints.py --kernels outputs/bench/data/cad_v8_s0/annotations.json --key kernels_cad8
    python tools/bench_viewpoints.py --kernels outputs/bench/data/car1000_s0/annotations.json --key kernels_car1000

The JSON record goes to ``--out`` (under ``--key`` when given); by default under the key
``viewpoints_speed[_groups<G>][_shapes<S>][_n<N>][_<device>]`` (``cameras_cpu`` for ``--cameras-cpu``) of
``outputs/viewpoints.json``, so that a plain run leaves the committed records alone; ``--key`` without ``--out``
writes that key of ``docs/data/viewpoints.json``, the records of docs/viewpoints.md (it cites the default run's
and ``--shapes 3 --groups 3``'s, each under its default key).
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import hashlib
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import ConvexHull
from skimage.draw import polygon2mask

from carvi_torch.cameras import FLIP_X, ScaledOrthographic, random_rotations
from carvi_torch.config import Config
from carvi_torch.evaluation.viewpoint_metrics import viewpoint_report
from carvi_torch.io.outputs import record_target, write_record
from carvi_torch.runtime import cpu_seconds, peak_rss_mb
from carvi_torch.sdf import distance_to_mask
from carvi_torch.viewpoints import mixture as sfm_mixture
from carvi_torch.viewpoints.camera_fit import refine_cameras, supported_shape
from carvi_torch.viewpoints.mixture import fit_mixture_of_shapes
from carvi_torch.viewpoints.refine import group_sfm_cameras, refine_groups
from carvi_torch.viewpoints.sfm import SfMOptions, rigid_sfm

ROOT = Path(__file__).resolve().parents[1]


#: Proportions of the ``--shapes`` variants of the base shape (x: width, y: length, z: height).
STRETCHES = ((1.0, 1.0, 1.0), (1.0, 1.6, 0.6), (1.2, 0.6, 1.5))


def make_class(n: int, k: int, canvas: int, seed: int, shapes: int = 1):
    """Synthetic class (originals then mirrored copies) with its true cameras; CPU tensors.

    ``shapes > 1``: instance ``i`` is a variant ``i % shapes`` of the base shape, stretched by
    :data:`STRETCHES` (a class of different proportions, for the mixture fit to split); the base
    shape and every random draw are those of ``shapes = 1``."""
    g = torch.Generator().manual_seed(seed)
    n_pairs = (k - 2) // 2
    half = torch.randn(n_pairs, 3, generator=g) * torch.tensor([0.5, 1.0, 0.6])
    half[:, 0] = half[:, 0].abs() + 0.2  # left side: x > 0
    mid = torch.randn(k - 2 * n_pairs, 3, generator=g) * torch.tensor([0.0, 1.0, 0.6])
    S = torch.cat([half, half * torch.tensor([-1.0, 1.0, 1.0]), mid])
    S = S - S.mean(0)
    pairs = [(i, i + n_pairs) for i in range(n_pairs)]
    if not 1 <= shapes <= len(STRETCHES):
        raise ValueError(f"shapes must be 1 to {len(STRETCHES)}, got {shapes}")
    variants = torch.stack([S * torch.tensor(st) for st in STRETCHES[:shapes]])
    base = variants[torch.arange(n) % shapes]  # (n, k, 3)
    Sn = base + 0.05 * torch.randn(n, k, 3, generator=g)  # instances differ from their shape a little
    R = random_rotations(n, g)
    radius = variants.norm(dim=-1).max()  # shapes = 1: the base shape's
    s = (0.35 * canvas / radius) * (0.9 + 0.2 * torch.rand(n, generator=g))
    t = canvas / 2.0 + 0.03 * canvas * torch.randn(n, 2, generator=g)
    cams = ScaledOrthographic(R, s, t)
    kp = cams.project(Sn)
    extent = (kp.amax(1) - kp.amin(1)).amax(-1)
    kp_noisy = kp + 0.01 * extent[:, None, None] * torch.randn(kp.shape, generator=g)
    z = cams.depth(Sn)
    rank = (-z).argsort(1).argsort(1)  # 0 = farthest
    vis = (rank >= round(0.3 * k)) & (torch.rand(n, k, generator=g) > 0.05)
    masks = np.zeros((n, canvas, canvas), dtype=bool)
    for i, p in enumerate(kp.numpy()):
        v = p[ConvexHull(p).vertices]
        masks[i] = polygon2mask((canvas, canvas), v[:, ::-1])
    masks = torch.from_numpy(masks)
    # mirrored copies
    perm = list(range(k))
    for a, b in pairs:
        perm[a], perm[b] = b, a
    kp_m = kp_noisy[:, perm].clone()
    kp_m[..., 0] = canvas - 1 - kp_m[..., 0]
    cams_m = cams.mirror(float(canvas), reflection=FLIP_X)  # the true shape is symmetric about x = 0
    return {
        "keypoints": torch.cat([kp_noisy, kp_m]),
        "visible": torch.cat([vis, vis[:, perm]]),
        "masks": torch.cat([masks, masks.flip(-1)]),
        "R_true": torch.cat([cams.R, cams_m.R]),
        "pairs": pairs,
    }


class _Rows:
    """The fields of a collection the mixture fit reads (keypoints, visibility, masks), indexable by rows."""

    def __init__(self, keypoints: torch.Tensor, visible: torch.Tensor, masks: torch.Tensor):
        self.keypoints, self.visible, self.masks = keypoints, visible, masks

    def __len__(self) -> int:
        return self.keypoints.shape[0]

    def __getitem__(self, rows) -> "_Rows":
        return _Rows(self.keypoints[rows], self.visible[rows], self.masks[rows])


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


def instrument_mixture(clock: Clock) -> None:
    """Wrap the fit's parts (module attributes, so every caller goes through the wrappers)."""
    import carvi_torch.pipeline as pipeline
    import carvi_torch.viewpoints.factorization as factorization
    import carvi_torch.viewpoints.mixture as mixture
    import carvi_torch.viewpoints.sfm as sfm

    factorize, polish, group_sfm = factorization.factorize, sfm.bundle_polish, mixture._group_sfm
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

    # the planar factorisation calls it from its own module, rigid_sfm from sfm's
    factorization.factorize = sfm.factorize = clock.wrap("factorize", counted_factorize)
    sfm.bundle_polish = clock.wrap("polish", counted_polish)
    mixture._group_sfm = kind_group_sfm
    for name in ("keypoint_fit", "hull_agreements", "kmeans_labels"):
        setattr(mixture, name, clock.wrap(name.replace("_labels", ""), getattr(mixture, name), prefixed=False))
    mixture.fit_mixture_of_shapes = mixture_fit
    pipeline.estimate_viewpoints = class_viewpoints


def profile_table(clock: Clock) -> tuple[list[str], dict]:
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


def profile_mixture(data: str, overrides: list[str], out: Path, key: str | None = None) -> dict:
    """``--profile-mixture``: the timed ``reconstruct stage=cameras`` run, its table and its JSON record."""
    from carvi_torch import reconstruct

    clock = Clock()
    instrument_mixture(clock)
    with tempfile.TemporaryDirectory() as tmp:
        rc = reconstruct.main(["--data", data, "--out", tmp, "stage=cameras", "progress=false", *overrides])
    if rc:
        raise SystemExit(rc)
    lines, rec = profile_table(clock)
    print("\n".join(lines))
    write_record(out, {"command": shlex.join(["python", *sys.argv]), "data": data, "overrides": overrides,
                       "load_average_after": os.getloadavg()[0], **rec}, key)
    print(f"wrote {out}" + (f", key {key}" if key else ""))
    return rec


def timed_child(cmd: list[str], **kw) -> dict:
    """Run ``cmd`` to its end (its output dropped; a failure raises ``SystemExit`` with the end of its error
    output): its CPU seconds (user + system, its waited-for children included), wall seconds and the 1-minute
    load average before and after."""
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), cpu_seconds(children=True)
    res = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **kw)
    wall, cpu = time.perf_counter() - t0, cpu_seconds(children=True) - c0
    if res.returncode:
        raise SystemExit(f"{shlex.join(cmd)} failed ({res.returncode}):\n{res.stderr[-3000:]}")
    return {"cpu_seconds": round(cpu, 2), "wall_seconds": round(wall, 2),
            "load_average_before": load0, "load_average_after": os.getloadavg()[0]}


def cameras_digest(out: Path) -> str:
    """SHA-256 over every ``<class>/cameras.json`` of a run (sorted by class): equal runs, equal digests."""
    h = hashlib.sha256()
    for f in sorted(out.glob("*/cameras.json")):
        h.update(f.parent.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()


def reconstruct_cameras(data: str, out: Path, overrides: list[str]) -> list[str]:
    """The command line of one timed run: ``reconstruct stage=cameras`` of ``data`` into ``out``."""
    return [sys.executable, "-m", "carvi_torch.reconstruct", "--data", data, "--out", str(out), "stage=cameras",
            "progress=false", *overrides]


def cameras_cpu(data: str, variants: list[str], rounds: int, command=reconstruct_cameras) -> dict:
    """``--cameras-cpu``: every variant (a space-separated list of overrides) run ``rounds`` times, interleaved
    (the order reversed every other round), each into a fresh folder; per run the timings of
    :func:`timed_child`, its groups per class and its cameras' digest; per variant the least CPU seconds,
    and the ratios of each variant's CPU seconds to the first variant's, per round and of the least."""
    if len(set(variants)) != len(variants):
        raise ValueError(f"--variants names one variant twice: {variants}")
    data = str(Path(data).resolve())  # the children run in the repository root
    runs: dict[str, list] = {v: [] for v in variants}
    order = 0
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(rounds):
            for v in variants if r % 2 == 0 else variants[::-1]:
                out = Path(tmp) / f"r{r}_{variants.index(v)}"
                rec = {"round": r, "order": order, **timed_child(command(data, out, v.split()), cwd=ROOT)}
                summary = out / "summary.json"
                classes = json.loads(summary.read_text())["classes"] if summary.is_file() else {}
                rec["groups"] = {c: (s.get("sfm_groups") or {}).get("groups", 1) for c, s in sorted(classes.items())}
                rec["fitted"] = [c for c, s in sorted(classes.items()) if (s.get("sfm_groups") or {}).get("candidates")]
                rec["cameras_sha256"] = cameras_digest(out)
                runs[v].append(rec)
                order += 1
                print(f"round {r} {v}: CPU {rec['cpu_seconds']:.1f} s, wall {rec['wall_seconds']:.1f} s, load "
                      f"{rec['load_average_before']:.1f} -> {rec['load_average_after']:.1f}", flush=True)
    first = runs[variants[0]]
    best = {v: min(x["cpu_seconds"] for x in rs) for v, rs in runs.items()}
    return {"data": data, "variants": variants, "rounds": rounds, "runs": runs, "least_cpu_seconds": best,
            "cpu_over_first": {v: {"least": round(best[v] / best[variants[0]], 3),
                                   "per_round": [round(x["cpu_seconds"] / f["cpu_seconds"], 3)
                                                 for x, f in zip(rs, first)]} for v, rs in runs.items()},
            "same_cameras_every_round": {v: len({x["cameras_sha256"] for x in rs}) == 1 for v, rs in runs.items()}}


def _record_target(args, default_key: str) -> tuple[Path, str | None]:
    """``--out`` (under ``--key``); ``--key`` alone: that key of docs/data/viewpoints.json; neither:
    ``default_key`` of outputs/viewpoints.json (:func:`carvi_torch.io.outputs.record_target`)."""
    return record_target(args.out, args.key, ROOT / "docs" / "data" / "viewpoints.json", default_key,
                         ROOT / "outputs" / "viewpoints.json")


def main_cameras_cpu(args, argv: list[str]) -> dict:
    """``--cameras-cpu``: run, print and write (default: key ``cameras_cpu`` of ``outputs/viewpoints.json``)."""
    rec = {"command": shlex.join(["python", "tools/bench_viewpoints.py", *argv]),
           **cameras_cpu(args.cameras_cpu, args.variants, max(1, args.rounds))}
    for v in args.variants:
        r = rec["cpu_over_first"][v]
        print(f"{v}: least CPU {rec['least_cpu_seconds'][v]:.1f} s, / first {r['least']:.2f} (per round "
              + ", ".join(f"{x:.2f}" for x in r["per_round"]) + "); groups kept "
              + str({c: g for c, g in rec["runs"][v][0]["groups"].items() if g > 1}))
    out, key = _record_target(args, "cameras_cpu")
    write_record(out, rec, key)
    print(f"wrote {out}" + (f", key {key}" if key else ""))
    return rec


def _best(fn, rounds: int):
    """``fn()``'s result and its best wall seconds over ``rounds`` calls."""
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def kernel_row(both, vcfg, rounds: int) -> dict:
    """``--kernels`` on one class with its mirrors: the bundle adjustment from the factorisation's cameras,
    compiled and in torch, and the hull agreements under the SfM cameras, batched and per row."""
    from carvi_torch.cameras import geodesic_angle
    from carvi_torch.viewpoints import class_sfm
    from carvi_torch.viewpoints.bundle import joint_bundle_adjust
    from carvi_torch.viewpoints.choice import hull_agreement, hull_agreement_reference

    start = class_sfm(both, vcfg, polish_iters=0)
    rows = start.valid.nonzero().squeeze(1)
    cams, shape = start.cameras[rows], torch.nan_to_num(start.shape)
    args = (cams, shape, both.keypoints[rows], both.visible[rows])
    runs = {n: _best(lambda n=n: joint_bundle_adjust(*args, iters=100, tol=vcfg.sfm_tol, native=n), rounds)
            for n in (True, False)}
    (nat, t_nat), (ref, t_ref) = runs[True], runs[False]
    sfm = class_sfm(both, vcfg)
    hrows = sfm.valid.nonzero().squeeze(1)
    hull_args = (sfm.shape, sfm.cameras[hrows], both.masks[hrows])
    (h_fast, t_fast), (h_ref, t_hull_ref) = (_best(lambda f=f: f(*hull_args), rounds)
                                             for f in (hull_agreement, hull_agreement_reference))
    angle = torch.rad2deg(geodesic_angle(nat.cameras.R.double(), ref.cameras.R.double())).max()
    return {"rows": len(rows), "keypoints": int(shape.shape[0]), "solves": [nat.iterations, ref.iterations],
            "bundle_ms_per_solve": {"compiled": 1e3 * t_nat / max(nat.iterations, 1),
                                    "torch": 1e3 * t_ref / max(ref.iterations, 1)},
            "bundle_max_angle_deg": float(angle), "hull_rows": len(hrows),
            "hull_seconds": {"batched": t_fast, "reference": t_hull_ref},
            "hull_equal": bool(torch.equal(h_fast, h_ref))}


def main_kernels(args, argv: list[str]) -> dict:
    """``--kernels``: every class of the file, one thread; table and record (default key ``kernels``)."""
    from carvi_torch.io.coco import load_coco

    torch.set_num_threads(1)
    vcfg = Config().viewpoints
    rows = {}
    print("| class | rows | solves compiled / torch | ms per solve: compiled / torch | largest angle (deg) | hull "
          "agreements: batched / reference (s) | equal |\n|---|---:|---:|---:|---:|---:|---|")
    for name, coll in sorted(load_coco(args.kernels).collections.items()):
        r = rows[name] = kernel_row(coll.with_mirrors(), vcfg, max(1, args.rounds))
        b, h = r["bundle_ms_per_solve"], r["hull_seconds"]
        print(f"| {name} | {r['rows']} | {r['solves'][0]} / {r['solves'][1]} | {b['compiled']:.3f} / "
              f"{b['torch']:.3f} ({b['compiled'] / b['torch']:.3f}x) | {r['bundle_max_angle_deg']:.1e} | "
              f"{h['batched']:.4f} / {h['reference']:.4f} ({h['batched'] / h['reference']:.3f}x) | {r['hull_equal']} |")
    total = {k: sum(r["hull_seconds"][k] for r in rows.values()) for k in ("batched", "reference")}
    print(f"hull agreements, all classes: {total['batched']:.3f} / {total['reference']:.3f} s "
          f"({total['batched'] / total['reference']:.3f}x)")
    rec = {"command": shlex.join(["python", "tools/bench_viewpoints.py", *argv]), "data": args.kernels,
           "threads": 1, "rounds": max(1, args.rounds), "classes": rows, "hull_seconds_all": total}
    out, key = _record_target(args, "kernels")
    write_record(out, rec, key)
    print(f"wrote {out}" + (f", key {key}" if key else ""))
    return rec


def build_parser() -> argparse.ArgumentParser:
    """The command line (the module docstring is its help)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=2000, help="instances before mirroring (default 2000)")
    ap.add_argument("--k", type=int, default=12, help="keypoints (default 12)")
    ap.add_argument("--canvas", type=int, default=128, help="canvas side in pixels (default 128)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--max-outer", type=int, default=None,
                    help="SfM's outer steps at most (default: the config's viewpoints.sfm_max_outer, 200)")
    ap.add_argument("--inner", type=int, default=None,
                    help="SfM's power steps per outer step (default: the config's viewpoints.sfm_inner, 10)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="viewpoint settings of the pipeline's config for SfM, the mixture and refinement (e.g. "
                         "viewpoints.sfm_polish=alternate viewpoints.sfm_native=false); default: the defaults")
    ap.add_argument("--max-iters", type=int, default=100, help="refinement iterations")
    ap.add_argument("--groups", type=int, default=1,
                    help="also time the mixture fit with at most this many rigid shapes (default 1: not run)")
    ap.add_argument("--shapes", type=int, default=1,
                    help=f"instances come in this many proportions of one shape (1 to {len(STRETCHES)}, default 1); "
                         "with --groups, a class the mixture fit splits")
    ap.add_argument("--cold-too", action="store_true",
                    help="with --groups: also time the fit without warm starts (every keypoint fit searches the "
                         "sphere, every SfM starts cold), in the same run")
    ap.add_argument("--group-threads", type=int, default=Config().viewpoints.sfm_group_threads,
                    help="with --groups: Python threads of the mixture fit (its initialisations side by side; "
                         "default the pipeline's sfm_group_threads, %(default)s)")
    ap.add_argument("--threads-min-objects", type=int, default=None,
                    help="with --groups: the class size from which the fit uses its threads "
                         "(default sfm_mixture.THREADS_MIN_OBJECTS; 0: always, to measure small classes)")
    ap.add_argument("--one-thread-too", action="store_true",
                    help="with --groups: also time the warm fit on one Python thread, in the same run, and check "
                         "that it gives the same result")
    ap.add_argument("--out", default=None, help="JSON record (default outputs/viewpoints.json, under the default key; "
                                                "with --key alone docs/data/viewpoints.json, the pages' records)")
    ap.add_argument("--key", default=None, help="write the record under this key of --out's JSON object, its other "
                                                "keys kept (default with no --out: viewpoints_speed[...], named "
                                                "after the options that differ from the defaults)")
    ap.add_argument("--profile-mixture", metavar="DATA", default=None,
                    help="instead: profile the pipeline's mixture fit on this COCO file (module docstring)")
    ap.add_argument("--profile-set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="--profile-mixture: reconstruct overrides (default none: the defaults)")
    ap.add_argument("--cameras-cpu", metavar="DATA", default=None,
                    help="instead: CPU seconds of reconstruct stage=cameras on this COCO file per --variants, "
                         "interleaved (module docstring)")
    mixture = f"sfm_groups={Config().viewpoints.sfm_groups}"  # the default mixture, named
    ap.add_argument("--variants", nargs="+", default=["sfm_groups=1", mixture], metavar="OVERRIDES",
                    help="--cameras-cpu: the variants, each a quoted space-separated list of overrides; ratios "
                         f"to the first (default: sfm_groups=1 {mixture}, the default)")
    ap.add_argument("--rounds", type=int, default=2, help="--cameras-cpu: runs of each variant; --kernels: "
                                                           "repeats of each timing, the best kept (default 2)")
    ap.add_argument("--kernels", metavar="DATA", default=None,
                    help="instead: the bundle adjustment (compiled / torch) and the hull agreements (batched / "
                         "reference) per class of this COCO file (module docstring)")
    return ap


def main(argv=None) -> dict:
    args = build_parser().parse_args(argv)
    if args.cameras_cpu:
        return main_cameras_cpu(args, list(sys.argv[1:] if argv is None else argv))
    if args.kernels:
        return main_kernels(args, list(sys.argv[1:] if argv is None else argv))
    if args.profile_mixture:
        default = ROOT / "docs" / "data" / "viewpoints.json" if args.key else ROOT / "outputs" / "profile_mixture.json"
        return profile_mixture(args.profile_mixture, args.profile_set, Path(args.out) if args.out else default,
                               args.key)
    return main_speed(args)


@dataclasses.dataclass
class _Bench:
    """The benchmark's class on its device (originals then mirrors: ``2n`` rows) and the run's settings."""

    args: argparse.Namespace
    dev: torch.device
    vcfg: object  # the pipeline's viewpoint settings (Config().viewpoints)
    kp: torch.Tensor  # (2n, K, 2) keypoints
    vis: torch.Tensor  # (2n, K) bool
    rows: _Rows  # the same rows as the mixture fit reads them (masks included)
    R_true: torch.Tensor  # (2n, 3, 3) the true rotations (CPU)
    dist: torch.Tensor | None = None  # (2n, H, W) distance maps of the masks, once timed

    def sync(self) -> None:
        """Wait for the device, so that the clock reads finished work."""
        if self.dev.type == "cuda":
            torch.cuda.synchronize()

    def timed(self, fn):
        """``fn()`` and its seconds (the device synchronised before the clock stops)."""
        t0 = time.perf_counter()
        out = fn()
        self.sync()
        return out, time.perf_counter() - t0


@dataclasses.dataclass
class _Stages:
    """The one-shape stages' results and seconds, and the mixture fits' record (``None``: not run)."""

    sfm: object  # SfMResult
    ref: object  # refine_cameras' result
    seconds: dict  # data_generation, distance_maps, sfm, refinement
    mixture: dict | None = None
    min_objects: int | None = None


def main_speed(args) -> dict:
    """The default run: time the viewpoint stages (and the mixture fit) on a generated class; print and write."""
    dev = torch.device(args.device)
    vcfg = Config().override(args.set).viewpoints  # the pipeline's viewpoint settings, with --set
    out, key = _record_target(args, "viewpoints_speed" + (f"_groups{args.groups}" if args.groups > 1 else "")
                              + (f"_shapes{args.shapes}" if args.shapes > 1 else "")
                              + (f"_n{args.n}" if args.n != 2000 else "")
                              + (f"_{dev.type}" if dev.type != "cpu" else ""))
    b, st = _time_stages(args, dev, vcfg)
    if args.groups > 1:
        st.mixture, st.min_objects = _mixture_fits(b, st)
    result = _record(b, st)
    _print_report(b, st, result)
    write_record(out, result, key)
    print(f"wrote {out}" + (f", key {key}" if key else ""))
    return result


def sfm_options(args, vcfg) -> SfMOptions:
    """The pipeline's SfM settings (``vcfg``, a ``ViewpointConfig``: the polish, its rounds, the tolerance, the
    compiled factorisation, the outer and inner steps), the tool's ``--max-outer`` and ``--inner`` where given."""
    max_outer = vcfg.sfm_max_outer if args.max_outer is None else args.max_outer
    inner = vcfg.sfm_inner if args.inner is None else args.inner
    return SfMOptions(max_outer=max_outer, inner=inner, tol=vcfg.sfm_tol, polish_iters=vcfg.sfm_polish_iters,
                      polish=vcfg.sfm_polish, native=vcfg.sfm_native)


def _time_stages(args, dev: torch.device, vcfg) -> tuple[_Bench, _Stages]:
    """Generate the class, then time its distance maps, rigid SfM and refinement (the pipeline's settings)."""
    t0 = time.perf_counter()
    data = make_class(args.n, args.k, args.canvas, args.seed, args.shapes)
    t_data = time.perf_counter() - t0
    kp = data["keypoints"].to(dev)
    vis = data["visible"].to(dev)
    masks = data["masks"].to(dev)
    b = _Bench(args, dev, vcfg, kp, vis, _Rows(kp, vis, masks), data["R_true"])
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    b.sync()
    b.dist, t_dist = b.timed(lambda: distance_to_mask(masks))
    sfm, t_sfm = b.timed(lambda: rigid_sfm(kp, vis, sfm_options(args, vcfg)))

    def refine():  # the pipeline's refinement settings (the planar-twin start and the keypoint support rule included)
        shape = supported_shape(sfm.shape, vis, vcfg.refine_min_support)
        return refine_cameras(shape, sfm.cameras, kp, vis, b.dist, max_iters=args.max_iters,
                              twin_flatness=vcfg.refine_twin_flatness)

    ref, t_ref = b.timed(refine)
    return b, _Stages(sfm, ref, {"data_generation": t_data, "distance_maps": t_dist, "sfm": t_sfm,
                                 "refinement": t_ref})


def _mixture_fits(b: _Bench, st: _Stages) -> tuple[dict, int]:
    """Time the mixture fit (warm; on one thread and cold too when asked) and the groups' refinement; the record
    of each fit and their comparisons, and the class size from which the fit used its threads."""
    args = b.args
    mixture = {}
    min_objects = (sfm_mixture.THREADS_MIN_OBJECTS if args.threads_min_objects is None
                   else args.threads_min_objects)
    variants = [("warm", True, args.group_threads)]
    if args.one_thread_too and args.group_threads != 1:
        variants.append(("warm_one_thread", True, 1))
    if args.cold_too:
        variants.append(("cold", False, args.group_threads))
    fits = {}
    for name, warm, threads in variants:
        mix, seconds = b.timed(lambda warm=warm, threads=threads: _fit_mixture(b, st.sfm, warm, threads, min_objects))
        fits[name] = mix
        R_mix = mix.single.cameras.R.clone()  # the groups' SfM cameras, in the class frame
        for gi in range(mix.k):
            R_mix[mix.groups[gi][0]] = mix.cameras(gi).R
        rep = viewpoint_report(R_mix.cpu(), b.R_true, valid=mix.single.valid.cpu())
        mixture[name] = {"seconds": seconds, "threads": threads, "max_groups": args.groups, **mix.summary(),
                         "sfm_geodesic_deg": rep["geodesic"]}
        if name == "warm":
            mixture[name].update(_refine_mixture(b, mix))
    for name in fits:
        # the viewpoint stage with the mixture: the one-shape SfM, the fit, the groups' refinement
        mixture[name]["stage_seconds"] = (st.seconds["sfm"] + mixture[name]["seconds"]
                                          + mixture["warm"]["refinement_seconds"])
    if "warm_one_thread" in fits:
        mixture["one_thread_over_threads"] = mixture["warm_one_thread"]["seconds"] / mixture["warm"]["seconds"]
        mixture["threads_same_result"] = _same_fit(fits["warm"], fits["warm_one_thread"])
    if "cold" in mixture:
        mixture["cold_over_warm"] = mixture["cold"]["seconds"] / mixture["warm"]["seconds"]
    return mixture, min_objects


def _fit_mixture(b: _Bench, sfm, warm: bool, threads: int, min_objects: int):
    """The pipeline's mixture fit (``sfm_group*`` settings) of the class, given its one-shape SfM ``sfm``."""
    args, vcfg = b.args, b.vcfg
    return fit_mixture_of_shapes(b.rows, b.dist,
                                 lambda sub, init_shape=None: rigid_sfm(sub.keypoints, sub.visible,
                                                                        sfm_options(args, vcfg),
                                                                        init_shape=init_shape),
                                 max_groups=args.groups, min_size=vcfg.sfm_group_min, gain=vcfg.sfm_group_gain,
                                 agreement_deg=vcfg.sfm_group_agreement_deg, rounds=vcfg.sfm_group_rounds,
                                 seed=args.seed, single=sfm, warm_start=warm, threads=threads,
                                 threads_min_objects=min_objects)


def _refine_mixture(b: _Bench, mix) -> dict:
    """The pipeline's refinement with the mixture (every group with its own mean shape): seconds and errors."""

    def refine():
        cams_mix, _valid = group_sfm_cameras(mix)
        refined_mix, _energy = refine_groups(mix, cams_mix, b.rows, b.dist,
                                             dataclasses.replace(b.vcfg, refine_iters=b.args.max_iters))
        return refined_mix

    refined_mix, t_ref_mix = b.timed(refine)
    rep = viewpoint_report(refined_mix.R.cpu(), b.R_true, valid=mix.single.valid.cpu())
    return {"refinement_seconds": t_ref_mix, "refined_geodesic_deg": rep["geodesic"]}


def _same_fit(a, b) -> bool:
    """Whether two mixture fits kept the same groups: labels, shapes, cameras and candidates."""
    return bool(
        a.k == b.k and torch.equal(a.labels, b.labels)
        and all(torch.equal(ga[1].shape, gb[1].shape) and torch.equal(ga[1].cameras.R, gb[1].cameras.R)
                for ga, gb in zip(a.groups, b.groups))
        and a.candidates == b.candidates)


def _record(b: _Bench, st: _Stages) -> dict:
    """The JSON record of a run: settings, environment, seconds, throughput, memory, results, errors."""
    args, dev, sfm, ref = b.args, b.dev, st.sfm, st.ref
    opts = sfm_options(args, b.vcfg)
    n_all = b.kp.shape[0]
    t_sfm, t_ref = st.seconds["sfm"], st.seconds["refinement"]
    rep_sfm = viewpoint_report(sfm.cameras.R.cpu(), b.R_true, valid=sfm.valid.cpu())
    rep_ref = viewpoint_report(ref.cameras.R.cpu(), b.R_true, valid=sfm.valid.cpu())
    for rep in (rep_sfm, rep_ref):
        rep.pop("per_instance_geodesic")
    return {
        "config": {"instances": args.n, "with_mirrors": n_all, "keypoints": args.k, "canvas": args.canvas,
                   "shapes": args.shapes,
                   "seed": args.seed, "device": str(dev), "max_outer": opts.max_outer, "inner": opts.inner,
                   "sfm_options": dataclasses.asdict(opts),
                   "twin_flatness": b.vcfg.refine_twin_flatness,
                   "refine_max_iters": args.max_iters},
        "environment": {"torch": torch.__version__, "python": platform.python_version(),
                        "cpu_threads": torch.get_num_threads(), "machine": platform.machine(),
                        "cuda_device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None},
        "seconds": {**st.seconds, "sfm_plus_refinement": t_sfm + t_ref},
        "instances_per_second": {"sfm": n_all / t_sfm, "refinement": n_all / t_ref,
                                 "sfm_plus_refinement": n_all / (t_sfm + t_ref)},
        "peak_memory_mb": {
            "process_rss": peak_rss_mb(),
            "cuda_allocated": (torch.cuda.max_memory_allocated(dev) / 2**20) if dev.type == "cuda" else None,
        },
        "sfm": {"iterations": sfm.iterations, "converged": sfm.converged, "valid": int(sfm.valid.sum()),
                "planar": sfm.planar, "reflection": sfm.reflection_votes,
                "median_residual_px": float(sfm.residual[sfm.valid].median()), "problems": sfm.problems},
        "refinement": {"iterations": ref.iterations, "converged_fraction": float(ref.converged.float().mean()),
                       "energy_before_median": float(ref.energy_before.median()),
                       "energy_after_median": float(ref.energy_after.median()),
                       "energy_raised": int((ref.energy_after > ref.energy_before).sum())},
        "viewpoint_error_deg": {"sfm": rep_sfm, "refined": rep_ref},
        "mixture_fit": st.mixture,
        "threads_min_objects": None if st.mixture is None else st.min_objects,
        "target_seconds_sfm_plus_refinement": 60.0,
    }


def _stage_rows(args, sec: dict, mixture: dict | None) -> list[tuple[str, float]]:
    """The table's rows: each stage's name and seconds."""
    rows = [("distance maps", sec["distance_maps"]), ("rigid SfM", sec["sfm"]), ("refinement", sec["refinement"]),
            ("SfM + refinement", sec["sfm_plus_refinement"])]
    if mixture is not None:
        rows.append((f"mixture fit (<= {args.groups})", mixture["warm"]["seconds"]))
        if "warm_one_thread" in mixture:
            rows.append(("  on one thread", mixture["warm_one_thread"]["seconds"]))
        if "cold" in mixture:
            rows.append(("  without warm starts", mixture["cold"]["seconds"]))
        rows.append(("  groups' refinement", mixture["warm"]["refinement_seconds"]))
        rows.append(("stage with mixture", mixture["warm"]["stage_seconds"]))
    return rows


def _print_report(b: _Bench, st: _Stages, result: dict) -> None:
    """Print the stages' table, the mixture fits, memory, and the SfM and refinement results."""
    args, dev, sfm, mixture = b.args, b.dev, st.sfm, st.mixture
    n_all = b.kp.shape[0]
    print(f"viewpoints benchmark: {n_all} instances ({args.n} + mirrors), K={args.k}, canvas {args.canvas}, "
          f"device {dev}, {torch.get_num_threads()} CPU threads")
    print(f"{'stage':<22}{'seconds':>10}{'inst/s':>12}")
    for name, sec in _stage_rows(args, result["seconds"], mixture):
        print(f"{name:<22}{sec:>10.2f}{n_all / sec:>12.0f}")
    for name, m in (mixture or {}).items():
        if isinstance(m, dict):
            print(f"mixture fit ({name}): {m['groups']} group(s) kept, sizes {m['sizes']}; SfM cameras: median "
                  f"{m['sfm_geodesic_deg']['median']:.2f} deg"
                  + (f" (refined {m['refined_geodesic_deg']['median']:.2f})" if "refined_geodesic_deg" in m else "")
                  + "; candidates: "
                  + "; ".join(f"k={c['k']} {c['init']}: cut {c['cut']:.0%}" for c in m["candidates"]))
    if mixture and "cold" in mixture:
        print(f"warm starts: {mixture['cold_over_warm']:.1f}x faster than without")
    if mixture and "warm_one_thread" in mixture:
        print(f"{args.group_threads} threads: {mixture['one_thread_over_threads']:.2f}x faster than one; same result: "
              f"{mixture['threads_same_result']}")
    print(f"peak RSS {result['peak_memory_mb']['process_rss']:.0f} MB"
          + (f", peak CUDA {result['peak_memory_mb']['cuda_allocated']:.0f} MB" if dev.type == "cuda" else ""))
    print(f"SfM: {sfm.iterations} outer iterations, converged={sfm.converged}, reflection "
          f"{sfm.reflection_votes['decided_by']} ({sfm.reflection_votes['for']}/{sfm.reflection_votes['against']})")
    errors = result["viewpoint_error_deg"]
    for name, rep in (("SfM", errors["sfm"]), ("refined", errors["refined"])):
        gsum = rep["geodesic"]
        print(f"{name:<8} geodesic error median {gsum['median']:.2f} deg, mean {gsum['mean']:.2f}, "
              f"acc@30 {gsum['acc_at_30']:.3f}, mirrored frame: {rep['mirrored']}")
    r = result["refinement"]
    print(f"refinement: {st.ref.iterations} iterations, energy median {r['energy_before_median']:.1f}"
          f" -> {r['energy_after_median']:.1f}, raised for {r['energy_raised']}")


if __name__ == "__main__":
    main()
