"""Executors run the pipeline's classes: here (:mod:`~carvi_torch.executors.local`) or on a Ray cluster
(:mod:`~carvi_torch.executors.ray`, imported only when a run asks for it).

:func:`run` is the entry point of a reconstruction run (``python -m carvi_torch.reconstruct``).
"""
from __future__ import annotations

from ..config import Config
from . import local
from .common import exit_status

__all__ = ["run", "exit_status"]


def run(cfg: Config, workers: int | None = None, threads: int | None = None) -> dict:
    """Run ``cfg`` on its executor (``cfg.executor``: :func:`carvi_torch.executors.local.run` or
    :func:`carvi_torch.executors.ray.run`); return the summary. ``workers``, ``threads``: the local
    executor's writer processes and torch threads."""
    if cfg.executor == "ray":
        from .ray import run as run_on_ray

        return run_on_ray(cfg)
    return local.run(cfg, workers=workers, threads=threads)
