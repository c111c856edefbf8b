"""Read an export (``python -m carvi_torch.export``) as a ``torch.utils.data.Dataset``.

Example:
    >>> from torch.utils.data import DataLoader
    >>> ds = LiftedDataset("exports/default", fields=["mask", "viewpoint"])      # doctest: +SKIP
    >>> loader = DataLoader(ds, batch_size=32, shuffle=True, num_workers=2,
    ...                     collate_fn=collate_lifted)                          # doctest: +SKIP
    >>> batch = next(iter(loader)); batch["mask"].shape                         # doctest: +SKIP
    torch.Size([32, 128, 128])

Shards are memory-mapped (``numpy.load(mmap_mode="r")``), opened lazily in each worker,
so an export larger than memory is fine and ``DataLoader(num_workers > 0)`` works.
"""
from __future__ import annotations

import bisect
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset
from torch.utils.data._utils.collate import default_collate

from .io.outputs import read_json

__all__ = ["LiftedDataset", "collate_lifted"]

_META = ("class_name", "source")


class LiftedDataset(Dataset):
    """Samples of a carvi_torch export.

    Args:
        root: the export directory (with ``index.json``).
        classes: keep only these class names (default: all).
        fields: field names to return (default: all; see ``index.json["fields"]`` / ``docs/export.md``).
        transform: called on each sample dict (after conversion to tensors).

    Each item is a dict of tensors (one per field, with the dtype and shape of ``docs/export.md``)
    plus ``class_name``, ``source`` and ``annotation_key`` (the annotation id as a string, also for
    string ids) strings.
    """

    def __init__(self, root: str | Path, classes: Iterable[str] | None = None,
                 fields: Sequence[str] | None = None, transform: Callable | None = None):
        self.root = Path(root)
        self.index = read_json(self.root / "index.json")
        known = self.index["fields"]
        self.fields = list(fields) if fields is not None else list(known)
        bad = [f for f in self.fields if f not in known]
        if bad:
            raise ValueError(f"unknown field(s) {bad}; available: {sorted(known)}")
        self.transform = transform
        self.class_names = self.index["classes"]
        wanted = set(classes) if classes is not None else None
        if wanted is not None:
            missing = wanted - set(self.class_names)
            if missing:
                raise ValueError(f"class(es) {sorted(missing)} not in the export; available: {self.class_names}")
        # global sample i -> (shard, row)
        starts, offset = [], 0
        for sh in self.index["shards"]:
            starts.append(offset)
            offset += sh["count"]
        self._starts = starts
        samples = self.index["samples"]
        self._rows = [i for i, s in enumerate(samples) if wanted is None or s["class"] in wanted]
        self._samples = samples
        self._maps: dict[tuple[int, str], np.ndarray] = {}

    def __len__(self) -> int:
        return len(self._rows)

    def _array(self, shard: int, field: str) -> np.ndarray:
        key = (shard, field)
        arr = self._maps.get(key)
        if arr is None:
            name = self.index["shards"][shard]["name"]
            path = self.root / name / f"{field}.npy"
            try:
                arr = np.load(path, mmap_mode="r")
            except (OSError, ValueError, EOFError) as e:
                raise OSError(f"{path}: unreadable shard file ({type(e).__name__}: {e})") from None
            self._maps[key] = arr
        return arr

    def __getstate__(self):  # memory maps are reopened in each worker
        state = dict(self.__dict__)
        state["_maps"] = {}
        return state

    def __getitem__(self, i: int) -> dict:
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        g = self._rows[i]
        shard = bisect.bisect_right(self._starts, g) - 1
        row = g - self._starts[shard]
        out = {f: torch.from_numpy(np.array(self._array(shard, f)[row])) for f in self.fields}
        meta = self._samples[g]
        out["class_name"] = meta["class"]
        out["source"] = meta.get("source", "")
        out["annotation_key"] = str(meta.get("annotation_id", ""))
        if self.transform is not None:
            out = self.transform(out)
        return out


def collate_lifted(batch: list[dict]) -> dict:
    """Stack tensor fields along a new batch axis; keep strings as lists.

    Classes have different keypoint counts ``K``: when a batch mixes classes, ``keypoints`` and
    ``visible`` are zero-padded to the largest ``K`` of the batch (padded keypoints are not visible).
    """
    out = {}
    for k in batch[0]:
        vals = [b[k] for b in batch]
        if isinstance(vals[0], str):
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
