"""``python -m carvi_torch.export``: a training dataset (a zarr v3 store) from a reconstruction directory.

- :mod:`~carvi_torch.export.run`: the export (:func:`export`);
- :mod:`~carvi_torch.export.command`: its command line (:func:`main`), light to import;
- :mod:`~carvi_torch.export.settings`: the settings' ranges, checked by both before anything is written;
- :mod:`~carvi_torch.export.store`: the zarr store's layout and fields;
- :mod:`~carvi_torch.export.source`: what the export reads (the run's configuration and annotations);
- :mod:`~carvi_torch.export.objects`: the per-object work (occupancy, depth, surface samples), run
  in worker processes; :mod:`~carvi_torch.export.raster`: its depth maps' numpy z-buffer;
- :mod:`~carvi_torch.export.formats`: CMR ``.mat`` and U-CMR ``.json`` annotation files;
- :mod:`~carvi_torch.export.legacy`: reading the deprecated shard layout (format 1).

This package's own import is light (the names below load on first use), so that export worker
processes, which import :mod:`~carvi_torch.export.objects`, start fast.
"""
from __future__ import annotations

__all__ = ["export", "main", "FIELDS", "DEFAULT_FIELDS", "view_occupancy", "canonical_occupancy", "depth_map",
           "ATTRS_KEY", "FORMAT_VERSION"]


def __getattr__(name: str):
    if name == "main":
        from .command import main

        return main
    if name in __all__:
        from . import run

        return getattr(run, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
