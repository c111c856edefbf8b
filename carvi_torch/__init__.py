"""carvi_torch: lift object-detection datasets into 3D (see README.md and docs/).

``__version__`` is the installed package's version, read from its metadata (``pyproject.toml`` is the
one place that sets it); ``"unknown"`` for a source tree that is not installed.

Example:
    >>> import carvi_torch
    >>> from carvi_torch.cli import version
    >>> carvi_torch.__version__ == version()
    True
"""
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("carvi_torch")
except PackageNotFoundError:  # a source tree on sys.path, not installed
    __version__ = "unknown"
