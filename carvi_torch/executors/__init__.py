"""Executors run the pipeline's classes: here (:mod:`~carvi_torch.executors.local`) or on a cluster.

:func:`run` is the entry point of a reconstruction run (``python -m carvi_torch.reconstruct``).
"""
from .common import exit_status
from .local import run

__all__ = ["run", "exit_status"]
