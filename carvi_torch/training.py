"""Read an export (``python -m carvi_torch.export``) as a ``torch.utils.data.Dataset``.

Example:
    >>> from torch.utils.data import DataLoader
    >>> ds = LiftedDataset("exports/default", fields=["mask", "viewpoint"], min_quality=0.5)  # doctest: +SKIP
    >>> loader = DataLoader(ds, batch_size=32, shuffle=True, num_workers=2,
    ...                     collate_fn=collate_lifted)                                    # doctest: +SKIP
    >>> batch = next(iter(loader)); batch["mask"].shape                                   # doctest: +SKIP
    torch.Size([32, 128, 128])

The export is a zarr v3 store (:mod:`carvi_torch.export.store`): ``root`` is its local path, a URL
that zarr's fsspec stores open (``s3://bucket/export``, with ``storage_options``), or a zarr store
object. Arrays are opened lazily in each process, so ``DataLoader(num_workers > 0)`` works and
an export larger than memory is fine. A format-1 export (``index.json`` + shards of ``.npy``
files) is still read, with a ``DeprecationWarning``, through carvi_torch 0.3.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset
from torch.utils.data._utils.collate import default_collate

from .io.layout import other_settings_text, settings_record

__all__ = ["LiftedDataset", "collate_lifted", "ZarrReader"]


class ZarrReader:
    """Samples of a zarr export: per class group, its metadata at open, its arrays on demand."""

    def __init__(self, root, storage_options: dict | None = None):
        from .export.store import ATTRS_KEY, FORMAT_VERSION

        self.root, self.storage_options = root, storage_options
        try:
            group = self._open()
        except Exception as e:  # noqa: BLE001 - zarr's "no group here" errors differ by store
            local = isinstance(root, Path) or (isinstance(root, str) and "://" not in root)
            if local and not Path(root).exists():
                raise FileNotFoundError(f"{root}: no such export (write one with python -m carvi_torch.export)") \
                    from None
            raise ValueError(f"{root}: not a zarr export ({type(e).__name__}: {e}); write one with python -m "
                             f"carvi_torch.export") from None
        attrs = group.attrs.asdict().get(ATTRS_KEY)
        if attrs is None:
            raise ValueError(f"{root}: not a carvi_torch export (no '{ATTRS_KEY}' attribute on the root group)")
        if attrs.get("format_version", 0) > FORMAT_VERSION:
            raise ValueError(f"{root}: export format {attrs['format_version']} is newer than this reader's "
                             f"({FORMAT_VERSION}); update carvi_torch")
        self.attrs = attrs
        self.fields = attrs["fields"]
        self.class_names = attrs["classes"]
        self.samples = []
        alike = not settings_record(attrs.get("made_with_other_settings"))  # a store without the field
        for c in self.class_names:
            if c not in group:
                continue
            g = group[c]
            ga = g.attrs.asdict()
            q = g["quality"][:] if "quality" in g else np.full(ga["count"], np.nan, np.float32)
            run = g["made_with_run_settings"][:] if "made_with_run_settings" in g else np.full(ga["count"], alike)
            category = {"class_name": ga.get("category_name", c), "category_id": ga.get("category_id")}
            for row in range(ga["count"]):
                self.samples.append({"class": c, "row": row, "annotation_id": ga["annotation_ids"][row],
                                     "source": ga["sources"][row], "quality": float(q[row]),
                                     "made_with_run_settings": bool(run[row]), **category})
        self._group = None
        self._arrays: dict[tuple[str, str], object] = {}  # opened once per process: metadata is read once
        self._offsets: dict[str, np.ndarray] = {}

    def _open(self):
        import zarr

        root = str(self.root) if isinstance(self.root, Path) else self.root
        return zarr.open_group(root, mode="r", storage_options=self.storage_options) if isinstance(root, str) \
            else zarr.open_group(root, mode="r")

    def __getstate__(self):  # arrays are reopened in each worker
        state = dict(self.__dict__)
        state["_group"], state["_arrays"] = None, {}
        return state

    def _array(self, cls: str, field: str):
        arr = self._arrays.get((cls, field))
        if arr is None:
            if self._group is None:
                self._group = self._open()
            arr = self._arrays[(cls, field)] = self._group[cls][field]
        return arr

    def read(self, g: int, field: str) -> np.ndarray:
        """Field ``field`` of global sample ``g`` (one chunk read; the ragged mesh fields: a row range)."""
        s = self.samples[g]
        try:
            if field.startswith("mesh_"):
                off = self._offsets.get(s["class"])
                if off is None:
                    off = self._offsets[s["class"]] = self._array(s["class"], "mesh_offsets")[:]
                col = 0 if field == "mesh_vertices" else 1
                return np.asarray(self._array(s["class"], field)[int(off[s["row"], col]):int(off[s["row"] + 1, col])])
            return np.asarray(self._array(s["class"], field)[s["row"]])
        except Exception as e:  # noqa: BLE001 - name the array that failed
            raise OSError(f"{self.root}/{s['class']}/{field}: unreadable chunk of sample {s['row']} "
                          f"({type(e).__name__}: {e})") from None


class LiftedDataset(Dataset):
    """Samples of a carvi_torch export.

    Args:
        root: the export (a path or URL of its zarr store, or a zarr store).
        classes: keep only these class names (default: all).
        fields: field names to return (default: all that were exported; ``docs/export.md`` lists them).
        transform: called on each sample dict (after conversion to tensors).
        min_quality: keep only objects whose ``quality`` is at least this (objects without one are dropped).
        storage_options: passed to zarr's fsspec store for a URL.

    Each item is a dict of tensors (one per field, with the dtype and shape of ``docs/export.md``;
    fields stored as float16 come back as float32) plus the strings ``class_name`` (the category's name as
    the annotation file gives it), ``class_key`` (the class's folder key: what ``classes`` and
    :attr:`class_names` hold, a safe spelling of the name), ``category_id`` (the COCO category id as a string;
    ``""`` and ``class_name`` = ``class_key`` for a store written before the export recorded categories),
    ``source`` and ``annotation_key`` (the annotation id as a string, also for string ids).

    Where a run folder held objects made with other settings than its ``config.yaml``'s (a rerun with another
    ``carve.resolution`` resumes them), opening the store warns, :attr:`attrs` holds the record
    (``made_with_other_settings``) and :attr:`made_with_run_settings` says which items were made with the run's
    settings (also each item's field of that name): ``Subset(ds, np.flatnonzero(ds.made_with_run_settings))``
    keeps those.
    """

    def __init__(self, root, classes: Iterable[str] | None = None, fields: Sequence[str] | None = None,
                 transform: Callable | None = None, min_quality: float | None = None,
                 storage_options: dict | None = None):
        from .export.legacy import REMOVED_IN, ShardReader, is_shard_export

        if is_shard_export(root):
            warnings.warn(f"{root}: the shard layout (index.json + .npy files) is deprecated and is read until "
                          f"carvi_torch {REMOVED_IN}; re-export it as a zarr store with python -m "
                          f"carvi_torch.export", DeprecationWarning, stacklevel=2)
            self.reader = ShardReader(root)
        else:
            self.reader = ZarrReader(root, storage_options)
        known = self.reader.fields
        self.fields = list(fields) if fields is not None else list(known)
        bad = [f for f in self.fields if f not in known]
        if bad:
            raise ValueError(f"unknown field(s) {bad}; available: {sorted(known)}")
        self.transform = transform
        self.class_names = self.reader.class_names
        made = self._made = settings_record(self.attrs.get("made_with_other_settings"))
        if made:
            other = sum(not s.get("made_with_run_settings", False) for s in self.reader.samples)
            warnings.warn(f"{root}: its objects were made with other settings than their run's config.yaml: "
                          + other_settings_text(made)
                          + " (oldest first, then the run's; the export's made_with_other_settings); "
                          f"made_with_run_settings is false for {other} of its {len(self.reader.samples)} objects",
                          stacklevel=2)
        wanted = set(classes) if classes is not None else None
        if wanted is not None and wanted - set(self.class_names):
            raise ValueError(f"class(es) {sorted(wanted - set(self.class_names))} not in the export; available: "
                             f"{self.class_names}")
        self._rows = [i for i, s in enumerate(self.reader.samples)
                      if (wanted is None or s["class"] in wanted)
                      and (min_quality is None or (not math.isnan(s["quality"]) and s["quality"] >= min_quality))]
        self._dtypes = {f: getattr(torch, known[f].get("returns") or known[f]["dtype"]) for f in self.fields}

    @property
    def attrs(self) -> dict:
        """The export's description (the root's ``carvi_export`` attribute: classes, fields, ``skipped`` objects,
        ``made_with_other_settings``, ...); ``{}`` for the shard layout."""
        return getattr(self.reader, "attrs", {})

    @property
    def made_with_run_settings(self) -> np.ndarray:
        """``(len(self),)`` bool: per item, whether its object was made with the run's settings (the store's field
        ``made_with_run_settings``; for a store written before it, every item ``True`` unless the store records
        other settings (``made_with_other_settings``), then ``False``: unknown)."""
        return np.array([self.reader.samples[g].get("made_with_run_settings", not self._made)
                         for g in self._rows], dtype=bool)

    def __len__(self) -> int:
        return len(self._rows)

    def __getitem__(self, i: int) -> dict:
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        g = self._rows[i]
        out = {f: torch.from_numpy(self.reader.read(g, f)).to(self._dtypes[f]) for f in self.fields}
        meta = self.reader.samples[g]
        out["class_name"] = meta.get("class_name", meta["class"])
        out["class_key"] = meta["class"]
        cid = meta.get("category_id")
        out["category_id"] = "" if cid is None else str(cid)
        out["source"] = meta.get("source", "") or ""
        out["annotation_key"] = str(meta.get("annotation_id", ""))
        if self.transform is not None:
            out = self.transform(out)
        return out


def collate_lifted(batch: list[dict]) -> dict:
    """Stack tensor fields along a new batch axis; keep strings and the ragged mesh fields as lists.

    Classes have different keypoint counts ``K``: when a batch mixes classes, ``keypoints`` and
    ``visible`` are zero-padded to the largest ``K`` of the batch (padded keypoints are not visible).
    ``mesh_vertices`` / ``mesh_faces`` stay lists of ``(V_i, 3)`` / ``(F_i, 3)`` tensors (what
    ``pytorch3d.structures.Meshes(verts=..., faces=...)`` takes).
    """
    out = {}
    for k in batch[0]:
        vals = [b[k] for b in batch]
        if isinstance(vals[0], str) or k.startswith("mesh_"):
            out[k] = vals
            continue
        shapes = {tuple(v.shape) for v in vals}
        if len(shapes) > 1:
            size = [max(s[d] for s in shapes) for d in range(vals[0].dim())]
            padded = []
            for v in vals:
                p = v.new_zeros(size)
                p[tuple(slice(0, n) for n in v.shape)] = v
                padded.append(p)
            vals = padded
        out[k] = default_collate(vals)
    return out
