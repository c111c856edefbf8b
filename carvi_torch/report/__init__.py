"""The report of a run: one page (``index.html``) to look at every object and class of a finished
``reconstruct --out DIR`` folder, offline, from disk.

    python -m carvi_torch.report --recon DIR [--out DIR/report]

Modules: :mod:`.inputs` (what is read: typed records), :mod:`.cards` (one object's overlay and mesh
data), :mod:`.mesh_data` (the 3D view's decimated mesh script), :mod:`.charts` (a class's figure),
:mod:`.page` (the HTML), :mod:`.build` (all of it, in order);
``static/`` holds the page's script, style sheet and the vendored three.js (``static/vendor/VENDOR.md``).
"""
from __future__ import annotations

__all__ = ["build_report", "Report", "ReportError", "main"]


def __getattr__(name: str):
    """``build_report``, ``Report`` and ``ReportError``, imported on first use: importing the package alone (as a
    run's writer processes do for :mod:`.mesh_data`) loads neither torch nor matplotlib."""
    if name in ("build_report", "Report"):
        from . import build

        return getattr(build, name)
    if name == "ReportError":
        from .inputs import ReportError

        return ReportError
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main(argv=None) -> int:
    """``python -m carvi_torch.report``; exit status 0; 2 when ``--recon`` is not a finished run or ``--out``
    cannot take the report (one ``error:`` line); 130 interrupted by Ctrl-C (one line)."""
    import argparse

    from ..cli import add_common, nonneg_int, positive_int, program, run_command

    ap = argparse.ArgumentParser(prog=program("carvi_torch.report"),
                                 description="An HTML report of a finished run: per-class panels and one card per "
                                             "object (overlay, interactive 3D mesh), worst first. Open "
                                             "OUT/index.html in a browser; it needs no network.")
    ap.add_argument("--recon", required=True, help="the run's output folder (reconstruct --out)")
    ap.add_argument("--out", help="where to write the report (default: RECON/report)")
    ap.add_argument("--per-page", type=positive_int, default=24, help="cards per page (default: 24)")
    ap.add_argument("--workers", type=nonneg_int, help="processes making the cards (default: none on 2 cores or fewer "
                                                "or below 100 objects, else one per core but one, at most 4; "
                                                "0: all in this process)")
    add_common(ap, classes=False)
    args = ap.parse_args(argv)
    where = args.out or f"{args.recon}/report"
    return run_command(lambda: _main(args), f"interrupted; the report in {where} is incomplete, run the command "
                                            "again")


def _main(args) -> int:
    import sys

    from ..cli import nonempty_paths

    nonempty_paths(args, "--recon", "--out")
    this = sys.modules[__name__]  # the package's names, looked up as attributes (imported on first use)
    build_report, ReportError = this.build_report, this.ReportError

    try:
        rep = build_report(args.recon, args.out, per_page=args.per_page, workers=args.workers)
    except ReportError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"report of {rep.cards} objects in {rep.index} ({rep.seconds:.1f} s)")
    return 0
