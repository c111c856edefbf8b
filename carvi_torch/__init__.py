"""carvi_torch: lift object-detection datasets into 3D (see README.md and docs/).

``__version__`` is the installed package's version, read from its metadata (``pyproject.toml`` is the
one place that sets it); ``"unknown"`` for a source tree that is not installed.

A command (``python -m carvi_torch.X`` or ``carvi X``) spends its first seconds importing torch and the
stages; Ctrl-C then ends it with one line and exit status 130 (:func:`interrupted_while_starting`), not a
traceback, until the command's own handling takes over (``carvi_torch.cli.run_command``). Importing the
package from other code leaves Ctrl-C alone.

Example:
    >>> import carvi_torch
    >>> from carvi_torch.cli import version
    >>> carvi_torch.__version__ == version()
    True
"""
import os
import signal
import sys
import threading
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("carvi_torch")
except PackageNotFoundError:  # a source tree on sys.path, not installed
    __version__ = "unknown"


def interrupted_while_starting(signum, frame) -> None:
    """Ctrl-C before a command's body runs: one line, exit status 130 (nothing is written that early)."""
    sys.stderr.write("interrupted while starting; nothing was written\n")
    sys.stderr.flush()
    os._exit(130)


def _started_as_command() -> bool:
    """Whether this import is a command's start: ``python -m carvi_torch.X`` (``argv[0]`` is ``-m`` while the
    module is found) or the ``carvi`` script; in the main thread, with Python's own Ctrl-C handler in place."""
    argv0 = sys.argv[0] if sys.argv else ""
    return ((argv0 == "-m" or os.path.basename(argv0) in ("carvi", "carvi.exe"))
            and threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler)


if _started_as_command():
    signal.signal(signal.SIGINT, interrupted_while_starting)
