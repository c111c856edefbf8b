"""The export's zarr v3 store: one group per class, one array per field, one chunk per sample.

Layout (``docs/export.md`` has the full table)::

    <out>/zarr.json                 root group; attributes["carvi_export"]: format version, classes,
                                    canvas size, resolution, points, fields, skipped objects, ...
    <out>/<class>/zarr.json         class group; attributes: annotation_ids, image_ids, sources, class_extent,
                                    category_name, category_id (the COCO category the folder key stands for)
    <out>/<class>/<field>/...       array (N, *sample shape); chunk = one sample, shard = ``shard_size`` samples

The store is written into a hidden folder inside ``<out>`` (``.carvi-export-partial-<pid>``) and swapped
in only when it is complete (:meth:`StoreWriter.close`): an export that stops half-way (Ctrl-C, an error)
leaves ``<out>`` as it was, an earlier export included, and writes nothing outside ``<out>``.

Reading one sample reads one chunk of every field it asks for (zarr's sharding codec keeps
the chunks of ``shard_size`` samples in one file, so a store of 100,000 objects is not
millions of files). Any zarr v3 reader opens it: ``zarr.open_group(out, mode="r")["car"]["mask"][0]``.

Example:
    >>> import tempfile, numpy as np
    >>> d = tempfile.mkdtemp()
    >>> w = StoreWriter(d, shard_size=2, fields=["quality"])
    >>> for q in (0.5, 0.25, 1.0):
    ...     w.add("car", {"quality": np.float32(q)}, {"annotation_id": 1, "image_id": 1, "source": ""})
    >>> w.close({"classes": ["car"]})["counts"]
    {'car': 3}
    >>> import zarr
    >>> zarr.open_group(d, mode="r")["car"]["quality"][:].tolist()
    [0.5, 0.25, 1.0]
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import BloscCodec

from ..runtime import check_replaceable, deferred_interrupt, folders_to_make, os_error_line, pid_alive, remove_empty

__all__ = ["FieldSpec", "FIELDS", "DEFAULT_FIELDS", "MESH_FIELDS", "StoreWriter", "FORMAT_VERSION", "ATTRS_KEY",
           "PARTIAL_PREFIX", "InterruptedAfterSwap", "group_name_problem"]

#: The store's format: 3 centres ``occupancy_view``'s depth axis on the object's depth extent and records
#: ``view_depth``; a format-2 store (no ``view_depth``) centred it on the mean vertex depth with cubic cells.
#: :class:`carvi_torch.training.LiftedDataset` reads any format up to this one.
FORMAT_VERSION = 3
#: The root group's attribute that holds the export's description.
ATTRS_KEY = "carvi_export"


@dataclass(frozen=True)
class FieldSpec:
    """One exported field: the dtype kept on disk, the dtype :class:`~carvi_torch.training.LiftedDataset`
    returns, the per-sample shape (symbolic) and its meaning."""

    dtype: str
    shape: str
    doc: str
    returns: str | None = None  # None: as stored

    @property
    def out_dtype(self) -> str:
        return self.returns or self.dtype


#: Every exported field (also written to the root group's attributes).
FIELDS: dict[str, FieldSpec] = {
    "mask": FieldSpec("bool", "(C, C)", "canvas mask, [row = y, col = x], canvas pixels"),
    "keypoints": FieldSpec("float32", "(K, 2)", "canvas keypoints (x, y); 0 where not visible"),
    "visible": FieldSpec("bool", "(K,)", "keypoint visibility"),
    "crop_box": FieldSpec("float32", "(4,)", "image region of the canvas: x0, y0, x1, y1 (image pixels, "
                                             "centres of the canvas corner pixels)"),
    "canvas_scale": FieldSpec("float32", "()", "a in canvas = a * image + b"),
    "canvas_offset": FieldSpec("float32", "(2,)", "b in canvas = a * image + b"),
    "R": FieldSpec("float32", "(3, 3)", "camera rotation, rows = image x, image y (down), view direction, "
                                        "in the class frame"),
    "s": FieldSpec("float32", "()", "camera scale, image pixels per class-frame unit"),
    "t": FieldSpec("float32", "(2,)", "image position of the class-frame origin (image pixels)"),
    "viewpoint": FieldSpec("float32", "(3,)", "azimuth, elevation, roll (radians) in the class frame, as "
                                               "PASCAL3D+ defines them"),
    "quality": FieldSpec("float32", "()", "predicted reliability in [0, 1] (cameras.json 'quality'; NaN when "
                                          "the run wrote none)"),
    "made_with_run_settings": FieldSpec("bool", "()", "made with the run's settings (its config.yaml's): so its "
                                                      "voxels file records, or, where it records none (an older "
                                                      "run's), the run folder records no other settings"),
    "occupancy_view": FieldSpec("bool", "(R, R, R)", "any-overlap occupancy in the view frame, [depth, y, x]: the "
                                                     "canvas square in x, y and R cells of depth view_depth[1] "
                                                     "centred on view_depth[0] (the whole object)"),
    "view_depth": FieldSpec("float32", "(2,)", "depth centre (canvas depth of the object's depth midpoint; the "
                                               "class-frame origin is at 0) and depth of one occupancy_view "
                                               "cell (C/R unless the object is deeper), canvas pixels"),
    "occupancy_canonical": FieldSpec("bool", "(R, R, R)", "any-overlap occupancy in the class frame, [z, y, x] over "
                                                          "[-E, E]^3 (E = class_extent)"),
    "depth": FieldSpec("float16", "(C, C)", "depth of the mesh's first surface per canvas pixel, canvas pixels, "
                                            "relative to view_depth[0]; +inf where the ray misses",
                       returns="float32"),
    "points": FieldSpec("float16", "(P, 3)", "surface points in the class frame (area-uniform samples)",
                        returns="float32"),
    "normals": FieldSpec("float16", "(P, 3)", "outward unit normals at the points, class frame", returns="float32"),
    "annotation_id": FieldSpec("int64", "()", "COCO annotation id (-1 for a string id: see annotation_key)"),
    "image_id": FieldSpec("int64", "()", "COCO image id (-1 for a string id)"),
    "class_index": FieldSpec("int64", "()", "index into the classes of the root group's attributes"),
    # the optional mesh (ragged: concatenated over the class's samples, located by mesh_offsets)
    "mesh_vertices": FieldSpec("float32", "(V_i, 3)", "mesh vertices in the class frame (ragged)"),
    "mesh_faces": FieldSpec("int32", "(F_i, 3)", "mesh triangles, indices into this sample's vertices (ragged)"),
}
#: The fields a plain export writes (``--mesh`` adds :data:`MESH_FIELDS`).
DEFAULT_FIELDS = [k for k in FIELDS if not k.startswith("mesh_")]
MESH_FIELDS = ["mesh_vertices", "mesh_faces"]
#: Rows per chunk of the ragged mesh arrays.
MESH_CHUNK_ROWS = 4096
#: Chunks zarr encodes per batch when writing (its ``codec_pipeline.batch_size``, 1 by default: one
#: batch per chunk costs more in zarr's bookkeeping than the compression itself). The bytes written
#: are the same.
WRITE_BATCH = 256
#: Names of the export's own hidden folders inside ``<out>``: the store being written (``-partial-<pid>``)
#: and, for the moment of the swap, the earlier one (``-old-<pid>``).
PARTIAL_PREFIX = ".carvi-export-partial-"
OLD_PREFIX = ".carvi-export-old-"


def _compressor(dtype: str) -> BloscCodec:
    """Blosc-zstd; bit-shuffled for booleans (8 voxels per byte before zstd), byte-shuffled otherwise."""
    return BloscCodec(cname="zstd", clevel=5, shuffle="bitshuffle" if dtype == "bool" else "shuffle",
                      typesize=np.dtype(dtype).itemsize)


class _ClassArrays:
    """The arrays of one class group, appended to in whole shards."""

    def __init__(self, group: zarr.Group, fields: list[str], shard_size: int):
        self.group, self.fields, self.shard_size = group, fields, shard_size
        self.buf: dict[str, list] = {k: [] for k in fields}
        self.meta: dict[str, list] = {"annotation_ids": [], "image_ids": [], "sources": []}
        self.count = 0
        self.ragged_rows = {k: 0 for k in MESH_FIELDS}
        self.lengths: dict[str, list[int]] = {k: [] for k in MESH_FIELDS}
        self.arrays: dict[str, zarr.Array] = {}

    def _array(self, name: str, shape: tuple, ragged: bool):
        """The field's array, grown to ``shape`` (created at that shape on the first flush: one metadata
        write, not two)."""
        if name in self.arrays:
            arr = self.arrays[name]
            arr.resize(shape)
            return arr
        dtype = FIELDS[name].dtype
        chunks = (MESH_CHUNK_ROWS, 3) if ragged else (1, *shape[1:])
        shards = None if ragged else (self.shard_size, *shape[1:])
        fill = 0 if dtype != "bool" else False
        self.arrays[name] = self.group.create_array(name, shape=shape, chunks=chunks, shards=shards, dtype=dtype,
                                                    compressors=_compressor(dtype), fill_value=fill,
                                                    dimension_names=None)
        return self.arrays[name]

    def add(self, sample: dict, meta: dict) -> None:
        for k in self.fields:
            self.buf[k].append(np.asarray(sample[k]))
        for k, key in (("annotation_ids", "annotation_id"), ("image_ids", "image_id"), ("sources", "source")):
            self.meta[k].append(meta[key])
        if len(self.buf[self.fields[0]]) >= self.shard_size:
            self.flush()

    def flush(self) -> None:
        n = len(self.buf[self.fields[0]]) if self.fields else 0
        if n == 0:
            return
        with deferred_interrupt(), zarr.config.set({"codec_pipeline.batch_size": WRITE_BATCH}):
            for k in self.fields:
                if k in MESH_FIELDS:
                    self._append_ragged(k, self.buf[k])
                    continue
                block = np.stack(self.buf[k]).astype(FIELDS[k].dtype)
                arr = self._array(k, (self.count + n, *block.shape[1:]), ragged=False)
                arr[self.count:self.count + n] = block
        self.count += n
        self.buf = {k: [] for k in self.fields}

    def _append_ragged(self, name: str, items: list) -> None:
        block = np.concatenate(items).astype(FIELDS[name].dtype)
        start = self.ragged_rows[name]
        arr = self._array(name, (start + len(block), 3), ragged=True)
        arr[start:] = block
        self.ragged_rows[name] = start + len(block)
        self.lengths[name].extend(len(it) for it in items)

    def close(self, extent: float, category: dict | None = None) -> None:
        self.flush()
        with deferred_interrupt():
            self._close(extent, category or {})

    def _close(self, extent: float, category: dict) -> None:
        attrs = {**self.meta, "count": self.count, "class_extent": extent,
                 **{f"category_{k}": v for k, v in category.items()}}
        if self.lengths[MESH_FIELDS[0]]:
            lengths = np.array([self.lengths[k] for k in MESH_FIELDS], dtype=np.int64).T  # (N, 2)
            off = np.concatenate([np.zeros((1, 2), np.int64), np.cumsum(lengths, axis=0)])
            self.group.create_array("mesh_offsets", data=off, chunks=off.shape, compressors=_compressor("int64"))
            attrs["mesh_offsets"] = "rows [i, i + 1) of mesh_vertices (column 0) and mesh_faces (column 1)"
        self.group.attrs.update(attrs)


def group_name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a class group of the store, ``None`` where it can. Zarr v3 reserves, for a node's
    name, the empty string, names holding ``/``, names made of periods alone and names starting with ``__``; and a
    group's child named ``zarr.json`` would stand where the group's own metadata file goes (any case: file systems
    that ignore case). The export's hidden folders' names are taken too. A class key (a safe folder name) breaks
    none of these rules but the ``zarr.json`` one.

    Example:
        >>> group_name_problem("car") is None, group_name_problem("Zarr.JSON"), group_name_problem("__x")
        (True, "the group's own metadata file is zarr.json", "zarr reserves names starting with '__'")
    """
    if not name or "/" in name or set(name) == {"."}:
        return "zarr reserves it (empty, holding '/' or made of periods)"
    if name.startswith("__"):
        return "zarr reserves names starting with '__'"
    if name.lower() == "zarr.json":
        return "the group's own metadata file is zarr.json"
    return "the export's hidden folders take it" if _own(name) else None


def _own(name: str) -> bool:
    """Whether ``name`` is one of the export's hidden folders (a store in progress, or one being swapped)."""
    return name.startswith((PARTIAL_PREFIX, OLD_PREFIX))


def _remove_stale(out: Path) -> None:
    """Remove the hidden folders of exports into ``out`` that were killed (their process is gone, or is this
    one: called before this export makes its own, so a folder with this pid is left from a killed process whose
    pid came round again, as a container's fixed pid does)."""
    for p in out.iterdir() if out.is_dir() else ():
        pid = p.name.rpartition("-")[2]
        if _own(p.name) and p.is_dir() and (not pid.isdigit() or int(pid) == os.getpid() or not pid_alive(int(pid))):
            shutil.rmtree(p, ignore_errors=True)


def _earlier_export(out: Path) -> dict | None:
    """The ``carvi_export`` attribute of the store at ``out`` (None where ``out`` holds no export's root
    ``zarr.json``)."""
    import json

    try:
        attrs = json.loads((out / "zarr.json").read_text()).get("attributes", {}).get(ATTRS_KEY)
    except (OSError, ValueError, AttributeError):
        return None
    return attrs if isinstance(attrs, dict) else None


def _not_export(out: Path) -> list[str]:
    """The entries of the folder ``out`` that an earlier export did not write (the new store's files replace
    that export's once it is complete): all but the export's own hidden folders where ``out`` holds no export's
    root ``zarr.json``; else anything beside its ``zarr.json`` and class groups (the folders of its ``classes``),
    and anything in a class group but its ``zarr.json`` and arrays (of its ``fields``, and ``mesh_offsets``),
    named ``class/entry``: a file of the user's (notes, checkpoints) is never removed with the earlier export."""
    other = [p.name for p in out.iterdir() if not _own(p.name)]
    attrs = _earlier_export(out) if other else None
    if attrs is None:
        return other
    classes = {c for c in attrs.get("classes") or () if isinstance(c, str)}
    fields = attrs.get("fields")
    arrays = {"zarr.json", "mesh_offsets", *FIELDS, *(fields if isinstance(fields, dict) else ())}
    foreign = [n for n in other if n != "zarr.json" and not (n in classes and (out / n).is_dir())]
    for c in sorted(classes & set(other)):
        if (out / c).is_dir():
            foreign += [f"{c}/{p.name}" for p in (out / c).iterdir() if p.name not in arrays]
    return foreign


def _swap_in(tmp: Path, out: Path) -> None:
    """Replace the contents of ``out`` (an earlier export, or nothing) by those of ``tmp`` (the complete new
    store), then remove ``tmp`` (called with Ctrl-C held back: see :meth:`StoreWriter.close`). The earlier
    root ``zarr.json`` goes first and the new one comes last, so that a reader during the swap finds no store
    rather than a mixed one."""
    old = out / f"{OLD_PREFIX}{os.getpid()}"
    old.mkdir()
    for p in sorted((p for p in out.iterdir() if not _own(p.name)), key=lambda p: p.name != "zarr.json"):
        p.rename(old / p.name)
    for p in sorted(tmp.iterdir(), key=lambda p: p.name == "zarr.json"):
        p.rename(out / p.name)
    tmp.rmdir()
    shutil.rmtree(old)


class InterruptedAfterSwap(KeyboardInterrupt):
    """Ctrl-C that arrived while the complete store was being swapped in: the new store is in place at
    ``out``. ``result`` is what the export returns (the root attributes written, plus what the caller adds)."""

    def __init__(self, result: dict):
        super().__init__("interrupted after the new store was swapped in")
        self.result = result


class StoreWriter:
    """Writes samples class by class into a zarr v3 store at ``out`` (created, or replaced when it holds
    an earlier export's store and nothing else: ``ValueError`` naming the first entry the export did not write,
    checked when the writer is made and again before the swap): into a hidden folder inside ``out`` first,
    swapped in by :meth:`close`; :meth:`abort` removes it, leaving ``out`` as it was."""

    def __init__(self, out: str | Path, shard_size: int = 256, fields: list[str] | None = None):
        self.out = Path(out)
        check_replaceable(self.out, _not_export, "an earlier export")
        self.made = folders_to_make(self.out)  # removed by abort() when empty
        self.swapped = False
        self.tmp = self.out / f"{PARTIAL_PREFIX}{os.getpid()}"
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            _remove_stale(self.out)
            with deferred_interrupt():
                self.root = zarr.open_group(str(self.tmp), mode="w", zarr_format=3)
        except OSError as e:
            self.abort()
            why = os_error_line(e, said=self.out)
            raise ValueError(f"{self.out}: cannot write the store there ({why}; nothing was written)") from e
        except BaseException:  # Ctrl-C (held back until the group was made)
            self.abort()
            raise
        self.shard_size = max(1, int(shard_size))
        self.fields = list(fields) if fields is not None else list(DEFAULT_FIELDS)
        self.classes: dict[str, _ClassArrays] = {}
        self.extent: dict[str, float] = {}
        #: ``{class key: {"name": category name, "id": category id}}`` (the class groups' ``category_*``).
        self.categories: dict[str, dict] = {}

    def add(self, cls: str, sample: dict, meta: dict) -> None:
        """Append one sample (a dict with every field) of class ``cls``; ``meta``: annotation_id, image_id,
        source (ids as given: ints or strings)."""
        if cls not in self.classes:
            with deferred_interrupt():
                group = self.root.create_group(cls)
            self.classes[cls] = _ClassArrays(group, self.fields, self.shard_size)
        self.classes[cls].add(sample, meta)

    def finish(self, cls: str) -> None:
        """Write what ``cls`` buffers now (called when its last sample is added, so that it is written while
        other classes are computed)."""
        if cls in self.classes:
            self.classes[cls].flush()

    def close(self, attrs: dict) -> dict:
        """Flush every class, write the root attributes (``attrs`` plus the fields, format version and ``counts``:
        samples per class of ``attrs["classes"]``, 0 for one without any) and swap the complete store in at
        ``out``; returns the root attributes written. Ctrl-C waits until the swap is done, and then raises
        :class:`InterruptedAfterSwap` (the new store is complete; :attr:`swapped` is true)."""
        for cls, arrays in self.classes.items():
            arrays.close(self.extent.get(cls, 1.0), self.categories.get(cls))
        fields = {k: {"dtype": FIELDS[k].dtype, "returns": FIELDS[k].out_dtype, "shape": FIELDS[k].shape,
                      "doc": FIELDS[k].doc} for k in self.fields}
        desc = {"format_version": FORMAT_VERSION, **attrs, "fields": fields,
                "counts": {c: self.classes[c].count if c in self.classes else 0
                           for c in attrs.get("classes", self.classes)}}
        with deferred_interrupt():
            self.root.attrs[ATTRS_KEY] = desc
        check_replaceable(self.out, _not_export, "an earlier export")  # nothing of the user's came meanwhile
        try:
            with deferred_interrupt():
                _swap_in(self.tmp, self.out)
                self.swapped = True
        except KeyboardInterrupt:
            if self.swapped:
                raise InterruptedAfterSwap(desc) from None
            raise
        return desc

    def abort(self) -> None:
        """Remove the store in progress: ``out`` is left as it was before (the folders this writer made for it,
        ``out`` and parents, are removed where empty; nothing else)."""
        shutil.rmtree(self.tmp, ignore_errors=True)
        remove_empty(self.made)
