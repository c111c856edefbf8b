"""The carving comparison as a picture: seconds per object of each variant, loop and floor.

Reads the JSON of ``tools/benchmark.py`` runs (default: the 1- and 2-thread pair kept in
``docs/benchmarks/``) and draws one panel per run: horizontal bars on a log scale for the
batched carvings (exact -- the default backend, the fused CPU kernel where it runs, and the torch
backend -- and nearest pixel), the reference-structure loops (bilinear and
nearest pixel) and the floors (each carving's own ``grid_sample`` calls, and the naive floors
of the loops), with the issue's two targets marked on each batched bar's own scale: a tenth of
the reference-structure loop of the same kind, and twice its own floor.

    python tools/figure_carving.py [--runs A.json B.json] [--out docs/figures/carving_speed.png]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_RUNS = [ROOT / "docs" / "benchmarks" / "carving_cpu_1000_threads1.json",
                ROOT / "docs" / "benchmarks" / "carving_cpu_1000_threads2.json"]

#: (key in seconds_per_object, label, kind): kind picks the colour.
ROWS = [
    ("batched", "batched, exact (default backend)", "batched"),
    ("batched_torch", "batched, exact, torch backend", "batched"),
    ("floor_batched", "  floor: the torch backend's grid_sample calls", "floor"),
    ("batched_nearest", "batched, nearest pixel", "batched"),
    ("floor_batched_nearest", "  its floor: its grid_sample calls", "floor"),
    ("loop_reference_structure", "loop, reference structure (bilinear)", "loop"),
    ("loop_reference_structure_nearest", "loop, reference structure, nearest pixel", "loop"),
    ("floor_loop_naive", "naive floor (every voxel), bilinear", "floor"),
    ("floor_loop_naive_nearest", "naive floor (every voxel), nearest pixel", "floor"),
]
COLOURS = {"batched": "#1f77b4", "loop": "#d62728", "floor": "#7f7f7f"}


def draw(runs: list[Path], out: Path) -> Path:
    data = [json.loads(p.read_text()) for p in runs]
    fig, axes = plt.subplots(1, len(data), figsize=(6.2 * len(data), 4.2), sharey=True, squeeze=False)
    for ax, d, path in zip(axes[0], data, runs):
        cs = d["carving"]
        s = cs["seconds_per_object"]
        rows = [r for r in ROWS if r[0] in s]
        y = list(range(len(rows)))[::-1]
        ax.barh(y, [s[k] for k, _, _ in rows], color=[COLOURS[c] for _, _, c in rows])
        # targets on each batched bar: 10x its loop of the same kind, 2x its own floor
        right = {k: s[k] for k, _, _ in rows}
        for key, loop, floor in (("batched", "loop_reference_structure", "floor_batched"),
                                 ("batched_torch", "loop_reference_structure", "floor_batched"),
                                 ("batched_nearest", "loop_reference_structure_nearest", "floor_batched_nearest")):
            if key not in s or loop not in s:
                continue
            yi = y[[r[0] for r in rows].index(key)]
            ax.plot([s[loop] / 10] * 2, [yi - 0.42, yi + 0.42], color="black", lw=1.5)
            ax.plot([2 * s[floor]] * 2, [yi - 0.42, yi + 0.42], color="black", lw=1.5, ls=":")
            right[key] = max(s[key], s[loop] / 10, 2 * s[floor])
        for yi, (k, _, _) in zip(y, rows):
            ax.text(right[k] * 1.08, yi, f"{s[k]:.4f}", va="center", fontsize=8)
        ax.set_xscale("log")
        ax.set_yticks(y, [label for _, label, _ in rows], fontsize=8)
        ax.set_xlabel("seconds per object (20 proposals, 60^3), log scale")
        backend = cs.get("carve_backend", "torch")
        ax.set_title(f"{cs['torch_threads']} torch thread(s), {cs['objects']} objects, default backend {backend}\n"
                     f"({path.name})", fontsize=9)
        ax.set_xlim(min(s[k] for k, _, _ in rows) / 2, max(s[k] for k, _, _ in rows) * 2.5)
    handles = [plt.Line2D([], [], color="black", lw=1.5, label="target: a tenth of the loop of its kind"),
               plt.Line2D([], [], color="black", lw=1.5, ls=":", label="target: twice its own floor")]
    fig.legend(handles=handles, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=130)
    plt.close(fig)
    return out


def main(argv=None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", type=Path, default=DEFAULT_RUNS, help="benchmark.py JSON files")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "carving_speed.png")
    args = ap.parse_args(argv)
    missing = [str(p) for p in args.runs if not p.is_file()]
    if missing:
        raise SystemExit(f"benchmark JSON not found: {', '.join(missing)} (run tools/benchmark.py first)")
    out = draw(args.runs, args.out)
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    main()
