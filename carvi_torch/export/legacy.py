"""Reading the export layout of format 1 (``index.json`` + ``shard_XXXXX/<field>.npy``), deprecated.

Exports written before the zarr store (format 2) are still read, with a ``DeprecationWarning``,
through carvi_torch 0.3; 0.4 drops this module. Re-export a reconstruction to convert.
"""
from __future__ import annotations

import bisect
from pathlib import Path

import numpy as np

from ..io.outputs import read_json

__all__ = ["ShardReader", "is_shard_export", "REMOVED_IN"]

#: The version that stops reading format 1.
REMOVED_IN = "0.4"


def is_shard_export(root) -> bool:
    """Whether ``root`` is a local folder holding a format-1 export (and no zarr store)."""
    try:
        p = Path(root)
        return (p / "index.json").is_file() and not (p / "zarr.json").is_file()
    except TypeError:
        return False


class ShardReader:
    """Samples of a format-1 export: memory-mapped ``.npy`` files, opened lazily (per worker process)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.index = read_json(self.root / "index.json")
        self.fields = {k: {**v, "returns": v["dtype"]} for k, v in self.index["fields"].items()}
        self.class_names = self.index["classes"]
        starts, offset = [], 0
        for sh in self.index["shards"]:
            starts.append(offset)
            offset += sh["count"]
        self._starts = starts
        self.samples = [{"class": s["class"], "annotation_id": s.get("annotation_id", ""),
                         "source": s.get("source", ""), "quality": float("nan")} for s in self.index["samples"]]
        self._maps: dict[tuple[int, str], np.ndarray] = {}

    def __getstate__(self):  # memory maps are reopened in each worker
        state = dict(self.__dict__)
        state["_maps"] = {}
        return state

    def read(self, g: int, field: str) -> np.ndarray:
        """Field ``field`` of global sample ``g``."""
        shard = bisect.bisect_right(self._starts, g) - 1
        key = (shard, field)
        arr = self._maps.get(key)
        if arr is None:
            path = self.root / self.index["shards"][shard]["name"] / f"{field}.npy"
            try:
                arr = np.load(path, mmap_mode="r")
            except (OSError, ValueError, EOFError) as e:
                raise OSError(f"{path}: unreadable shard file ({type(e).__name__}: {e})") from None
            self._maps[key] = arr
        return np.array(arr[g - self._starts[shard]])
