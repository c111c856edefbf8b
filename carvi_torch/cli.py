"""``carvi``: one command for every front end, and the options they share.

    carvi reconstruct [--data annotations.json] [--out DIR] [key=value ...]
    carvi evaluate --data annotations.json --recon DIR
    carvi export --recon DIR --out DIR
    carvi report --recon DIR [--out DIR/report]
    carvi datasets {voc,synthetic,procedural} ...
    carvi --version

Every command spells its shared options the same way: ``--classes a,b`` (the classes to work on),
``--quiet`` (no progress bars; warnings and errors only), ``--version``, ``--help``.

Example:
    >>> main(["--version"])  # doctest: +ELLIPSIS
    carvi_torch ...
    0
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

__all__ = ["main", "add_common", "split_classes", "version", "program"]

#: Subcommand -> (module with ``main(argv)``, one line of help).
COMMANDS = {
    "reconstruct": ("carvi_torch.reconstruct", "viewpoints and shapes for every annotated object"),
    "evaluate": ("carvi_torch.evaluate", "errors of reconstructions against ground truth"),
    "export": ("carvi_torch.export", "a training dataset from a reconstruction"),
    "datasets": ("carvi_torch.datasets", "convert or generate annotations"),
    "report": ("carvi_torch.report", "an HTML page of a finished run: every object, worst first"),
}


#: The usage name of the subcommand ``carvi`` is running (``None``: none is; a front end run directly).
_running: str | None = None


def version() -> str:
    """The installed package's version (``carvi_torch.__version__``, from the package metadata)."""
    from . import __version__

    return __version__


def program(module: str) -> str:
    """The name a front end's usage line shows: ``carvi <command>`` while ``carvi`` runs it, otherwise
    ``python -m <module>``.

    Example:
        >>> program("carvi_torch.report")
        'python -m carvi_torch.report'
    """
    return _running or f"python -m {module}"


def add_common(ap: argparse.ArgumentParser, classes: bool = True, quiet: bool = True) -> None:
    """The options every command shares: ``--version``, ``--classes a,b``, ``--quiet``."""
    ap.add_argument("--version", action="version", version=f"carvi_torch {version()}")
    if classes:
        ap.add_argument("--classes", metavar="A,B", help="comma-separated class names to work on (default: all)")
    if quiet:
        ap.add_argument("--quiet", action="store_true", help="no progress bars; warnings and errors only")


def split_classes(value: str | None) -> list[str] | None:
    """``"a, b"`` -> ``["a", "b"]``; ``None`` or empty -> ``None`` (every class)."""
    names = [c.strip() for c in (value or "").split(",") if c.strip()]
    return names or None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="carvi", description="Lift object-detection datasets into 3D.",
                                 epilog="\n".join(f"  {k:12s} {h}" for k, (_, h) in COMMANDS.items()),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--version", action="version", version=f"carvi_torch {version()}")
    ap.add_argument("command", choices=sorted(COMMANDS), help="what to do (each has its own --help)")
    if not argv or argv[0] in ("-h", "--help", "--version"):
        try:
            ap.parse_args(argv or ["--help"])
        except SystemExit as e:
            return int(e.code or 0)
    ns, rest = ap.parse_known_args(argv[:1])
    module = importlib.import_module(COMMANDS[ns.command][0])
    global _running
    _running = f"{ap.prog} {ns.command}"
    try:
        return int(module.main(argv[1:]) or 0)
    finally:
        _running = None


if __name__ == "__main__":
    from carvi_torch.cli import main as _main  # the module the front ends import, which holds _running

    sys.exit(_main())
