"""``carvi``: one command for every front end, and the options they share.

    carvi reconstruct [--data annotations.json] [--out DIR] [key=value ...]
    carvi evaluate --data annotations.json --recon DIR
    carvi export --recon DIR --out DIR
    carvi report --recon DIR [--out DIR/report]
    carvi datasets {voc,synthetic,procedural} ...
    carvi --version

Every command spells its shared options the same way: ``--classes a,b`` (the classes to work on),
``--quiet`` (no progress bars; warnings and errors only), ``--version``, ``--help``; and ends the same
way (:func:`run_command`): a user error or an output that cannot be written is one ``error:`` line and
exit status 2, Ctrl-C one line saying what is kept and exit status 130 (never a traceback).

Example:
    >>> main(["--version"])  # doctest: +ELLIPSIS
    carvi_torch ...
    0
"""
from __future__ import annotations

import argparse
import importlib
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Callable, Sequence

from .runtime import os_error_line  # re-exported: the commands' shared ending names OS errors with it
from .runtime import folders_to_make, remove_empty

__all__ = ["main", "add_common", "split_classes", "version", "program", "run_command", "CommandError",
           "os_error_line", "writable_folder", "writable_file", "positive_int", "nonneg_int", "nonempty_paths"]

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


class CommandError(Exception):
    """A user error a command reports as one ``error:`` line (exit status 2)."""


def nonempty_paths(args: argparse.Namespace, *options: str) -> None:
    """Raise :class:`CommandError` where one of the path ``options`` (``"--out"``; one the command does not have is
    passed over) was given as empty text: an empty path would be taken as the current folder, or as no option at
    all (a default), without a word.

    Example:
        >>> try:
        ...     nonempty_paths(argparse.Namespace(out="", data="a.json"), "--data", "--out", "--gt")
        ... except CommandError as e:
        ...     print(e)
        --out is empty; give a path ('.' for the current folder)
    """
    for option in options:
        value = getattr(args, option.lstrip("-").replace("-", "_"), None)
        if any(v == "" for v in (value if isinstance(value, list) else [value])):
            raise CommandError(f"{option} is empty; give a path ('.' for the current folder)")


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (anything else: argparse's error saying so, exit 2)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text}")
    return v


def nonneg_int(text: str) -> int:
    """An argparse type: an integer >= 0 (anything else: argparse's error saying so, exit 2; it named this
    function for text that is no integer).

    Example:
        >>> nonneg_int("3")
        3
    """
    try:
        v = int(text)
    except ValueError:
        v = -1
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return v


def nonneg_float(text: str) -> float:
    """An argparse type: a finite number >= 0 (anything else: argparse's error saying so, exit 2)."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return v


def _take_over_ctrl_c() -> None:
    """Ctrl-C raises ``KeyboardInterrupt`` again where the package's start had it end the process
    (:func:`carvi_torch.interrupted_while_starting`): the command's body handles it from here."""
    import signal

    import carvi_torch

    if signal.getsignal(signal.SIGINT) is carvi_torch.interrupted_while_starting:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def run_command(body: Callable[[], int | None], interrupted: str) -> int:
    """Run a command's body and turn how it ends into an exit status: its own (0 by default); 2 with one
    ``error:`` line for a :class:`CommandError` or an ``OSError`` (an output that cannot be made or written,
    an input that cannot be read); 130 with the line ``interrupted`` on Ctrl-C.

    Example:
        >>> def body():
        ...     raise FileExistsError(17, "File exists", "out")
        >>> run_command(body, "interrupted")
        2
    """
    _take_over_ctrl_c()
    try:
        return int(body() or 0)
    except KeyboardInterrupt:
        print(interrupted, file=sys.stderr)
        return 130
    except CommandError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: {os_error_line(e)}", file=sys.stderr)
        return 2


def writable_folder(path: str | os.PathLike, option: str = "--out") -> Path:
    """Make the output folder ``path`` (and its parents) and check that a file can be written in it, before a
    command does its work; raises :class:`CommandError` naming ``option`` where it cannot (a file in the way,
    a read-only place). Nothing outside ``path`` is written."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise CommandError(f"{option} {out} is a file, not a folder")
    made = folders_to_make(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as e:
        remove_empty(made)  # a failed check leaves nothing behind
        raise CommandError(f"{option} {out}: cannot write there ({os_error_line(e)})") from e
    return out


def writable_file(path: str | os.PathLike, option: str = "--out") -> Path:
    """Check, before a command does its work, that the output file ``path`` can be made: it is not a folder,
    and the nearest existing folder above it is a folder this process may write; raises :class:`CommandError`
    naming ``option``. Nothing is written (an error when the file is written is still one ``error:`` line)."""
    from .runtime import unwritable_above

    out = Path(path)
    if out.is_dir():
        raise CommandError(f"{option} {out} is a folder; give the file to write")
    why = unwritable_above(out)
    if why:
        raise CommandError(f"{option} {out}: {why}")
    return out


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
    try:  # the command's imports (torch, ...) take seconds: Ctrl-C then is one line too
        module = importlib.import_module(COMMANDS[ns.command][0])
    except KeyboardInterrupt:
        print("interrupted; nothing was written", file=sys.stderr)
        return 130
    global _running
    _running = f"{ap.prog} {ns.command}"
    try:
        return int(module.main(argv[1:]) or 0)
    finally:
        _running = None


if __name__ == "__main__":
    from carvi_torch.cli import main as _main  # the module the front ends import, which holds _running

    sys.exit(_main())
