"""``python -m carvi_torch.reconstruct``: viewpoints and dense shapes for every annotated object.

Examples:
    python -m carvi_torch.reconstruct                                   # embedded procedural collection
    python -m carvi_torch.reconstruct --data annotations.json --out runs/voc
    python -m carvi_torch.reconstruct --data ann.json stage=cameras     # stop after viewpoints
    python -m carvi_torch.reconstruct --data ann.json cameras=gt imprint=false resolution=40
"""
from __future__ import annotations

import argparse
import sys

from .cli import add_common, nonempty_paths, program, run_command, split_classes
from .config import FIELD_DOCS, Config, ConfigError, load_config, override_text
from .io.coco import CocoFormatError

EPILOG_HEAD = """\
Outputs in --out: config.yaml (resolved), summary.json, run.log (the whole log, timestamped),
preview.png, report/index.html, input/ (the embedded collection, when there is no --data) and per class
<class>/cameras.json, <class>/meshes/<annotation_id>.ply, <class>/voxels/<annotation_id>.npz
(meshes and voxels in the reference camera frame, image pixels). A rerun skips finished objects.

key=value settings: a full dotted key (carve.resolution=40) or a short one where it names one
setting (resolution=40, carve_backend=torch). Text is taken as typed (out=007), a list as a,b or [a, b],
null unsets (data=null), integers are decimal, booleans true/false, yes/no, on/off or 1/0. Every key, with
its default:
"""


def settings_help(width: int = 100) -> str:
    """Every configuration key with its default, as ``key=value`` on the command line takes it back
    (:func:`~carvi_torch.config.override_text`: ``data=null``, ``imprint=true``), and its docstring, grouped by
    section."""
    import textwrap

    defaults = Config().flat()
    lines = []
    section = None
    for key, doc in FIELD_DOCS.items():
        head = key.rpartition(".")[0]
        if head != section:
            section = head
            lines.append(f"\n[{section}]" if section else "[run]")
        lines.append(f"  {key}={override_text(defaults[key])}")
        lines.extend(textwrap.wrap(doc, width, initial_indent="      ", subsequent_indent="      "))
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=program("carvi_torch.reconstruct"),
                                 description="Lift annotated objects into 3D: a camera viewpoint and a dense shape "
                                             "for every object (Carreira et al., 'Lifting Object Detection "
                                             "Datasets into 3D').",
                                 epilog=EPILOG_HEAD + settings_help(),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="COCO keypoint JSON (default: the embedded procedural collection)")
    ap.add_argument("--out", help="output directory (default: outputs/default)")
    ap.add_argument("--config", help="YAML config file (nested by section or flat; see configs/default.yaml)")
    add_common(ap)
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="settings (listed below)")
    return ap


def parse_args(argv=None) -> argparse.Namespace:
    """The command line, ``key=value`` settings anywhere among the options (``--out D a=1 --quiet b=2``).

    Example:
        >>> parse_args(["--out", "D", "resolution=40", "--quiet", "preview=false"]).overrides
        ['resolution=40', 'preview=false']
    """
    return build_parser().parse_intermixed_args(argv)


def _shorten(text: str, width: int) -> str:
    """``text`` cut to at most ``width`` characters at a word boundary, ``…`` marking the cut (a number or word
    is never cut in two, so a cut reason does not read as another; one word longer than ``width`` is cut).

    Example:
        >>> _shorten("views dropped from 15 to 2", 20), _shorten("short", 20)
        ('views dropped from…', 'short')
    """
    text = " ".join(str(text).split())
    if len(text) <= width:
        return text
    head = text[:width - 1]
    if text[width - 1] != " " and " " in head:
        head = head.rsplit(" ", 1)[0]
    return head.rstrip(" ,;:(") + "…"


def _main_reasons(c: dict) -> str:
    """The two most frequent skip reasons of a class, else its first warning."""
    reasons: dict[str, int] = {}
    for f in c.get("failures", []):
        key = _shorten(f.get("reason", ""), 48)
        reasons[key] = reasons.get(key, 0) + 1
    top = "; ".join(f"{k} (x{v})" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])[:2])
    if not top and c.get("warnings"):
        top = "warning: " + _shorten(c["warnings"][0], 60)
    return top or "-"


def _count(n, noun: str) -> str:
    """``1 thread``, ``2 threads`` (``None``: ``? threads``)."""
    return f"{'?' if n is None else n} {noun}{'' if n == 1 else 's'}"


def format_table(summary: dict) -> str:
    """The closing table: per class objects, reconstructed, skipped (with reasons), seconds."""
    rows = [("class", "objects", "recon.", "resumed", "skipped", "warnings", "seconds", "main reasons")]
    for name, c in summary.get("classes", {}).items():
        secs = sum((c.get("seconds") or {}).values())
        rows.append((name, str(c.get("objects", 0)), str(c.get("reconstructed", 0)), str(c.get("resumed", 0)),
                     str(c.get("skipped", len(c.get("failures", [])))), str(len(c.get("warnings", []))),
                     f"{secs:.1f}", _main_reasons(c)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(v.ljust(widths[i]) if i in (0, 7) else v.rjust(widths[i]) for i, v in enumerate(r))
             for r in rows]
    lines.insert(1, "-" * len(lines[0]))
    n_in = len(summary.get("input_problems", []))
    if n_in:
        lines.append(f"input problems reported at load: {n_in} (see summary.json)")
    if "total_seconds" in summary:
        cb = summary.get("carve_backend") or {}
        carving = {"fused": f"; carving: fused CPU kernel ({cb.get('variant')})", "torch": "; carving: torch"}.get(
            cb.get("backend"), "")
        lines.append(f"total {summary['total_seconds']:.1f} s on {summary.get('device')} "
                     f"({_count(summary.get('torch_threads'), 'thread')}{carving})")
        if cb.get("reason"):
            lines.append(f"the fused carving kernel was not used: {cb['reason']}")
    return "\n".join(lines)


#: The one line a run interrupted by Ctrl-C prints (its finished objects are files a rerun resumes).
INTERRUPTED = "interrupted; finished objects are kept, rerun to resume"


def main(argv=None) -> int:
    """Exit status: 0 the run made what it was asked for; 1 a class failed or nothing came out of it;
    2 a user error or an output that cannot be written (one ``error:`` line); 130 interrupted by Ctrl-C (one
    line)."""
    return run_command(lambda: _main(argv), INTERRUPTED)


def _main(argv=None) -> int:
    args = parse_args(argv)
    nonempty_paths(args, "--data", "--out", "--config")
    try:
        cfg = load_config(args.config, args.overrides)
        extra = {k: v for k, v in (("data", args.data), ("out", args.out), ("classes", args.classes)) if v}
        if "classes" in extra:
            extra["classes"] = split_classes(extra["classes"])
        if args.quiet:
            extra["progress"] = False
        cfg = cfg.override(extra) if extra else cfg
        from .executors import exit_status, run

        summary = run(cfg)
    except (ConfigError, CocoFormatError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(format_table(summary))
    print(f"outputs in {cfg.out}")
    status = exit_status(summary, cfg.stage)
    if status:
        print("error: a class failed or no object was reconstructed (see the table and summary.json)",
              file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
