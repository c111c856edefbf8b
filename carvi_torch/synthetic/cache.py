"""The embedded collection's files, kept once generated: ``$CARVI_TORCH_CACHE/collections/<key>.npz``.

The default collection (:func:`~carvi_torch.synthetic.procedural.default_collection`) is deterministic: the same
settings and the same code give the same files, byte for byte. It is generated once per key and copied from here
afterwards (about 0.1 s against 3-6 s on the 2-core development host). The key (:func:`collection_key`) hashes
the generation settings, the source of every module of the package (any change of the code is another key), and
the Python, platform and library versions the files depend on.

An entry is one ``.npz`` read with ``allow_pickle=False`` (no object arrays: nothing in it is code): the files'
relative names, their bytes end to end with their offsets, and the SHA-256 of those bytes. It is read only where
:mod:`carvi_torch.user_cache`'s rules allow (a folder of this user, mode 0700; a regular file of this user that no
one else may write), and used only when every name is a plain relative path (``annotations.json``,
``meshes/car000.ply``) and the bytes match their hash; anything else (a damaged, truncated or foreign file) is a
miss: the collection is generated again and the entry replaced. Entries are written to a temporary file and moved
into place (``os.replace``); the :data:`KEEP` most recently used are kept, older ones removed. A cache that cannot
be read or written never stops a run: the collection is then generated as without one.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

from ..user_cache import cache_root, own_file_problem, private_dir

__all__ = ["collection_key", "entry_path", "load_files", "store_files", "KEEP"]

log = logging.getLogger("carvi_torch")

#: Entries kept (the most recently used); the default collection's is about 23 MB.
KEEP = 8
#: The distributions whose versions the files may depend on (meshing, rendering, encoding, writing).
LIBRARIES = ("numpy", "torch", "scipy", "scikit-image", "trimesh", "pycocotools")
_PACKAGE = Path(__file__).resolve().parents[1]
_NAME_PART = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")


def _source_digest() -> str:
    """SHA-256 of every ``.py`` file of the package (paths and contents, in path order)."""
    h = hashlib.sha256()
    for path in sorted(_PACKAGE.rglob("*.py")):
        h.update(path.relative_to(_PACKAGE).as_posix().encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return h.hexdigest()


def _versions() -> dict:
    from importlib import metadata

    out = {"python": sys.version, "machine": platform.machine(), "platform": sys.platform}
    for name in LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def collection_key(settings: dict) -> str:
    """24 hex digits of SHA-256 over ``settings`` (JSON), the package's source and :func:`_versions`.

    Example:
        >>> collection_key({"seed": 0}) == collection_key({"seed": 0}) != collection_key({"seed": 1})
        True
    """
    text = json.dumps({"settings": settings, "source": _source_digest(), "versions": _versions()}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def entry_path(key: str) -> Path:
    """Where the entry of ``key`` lives (whether or not it exists)."""
    return cache_root() / "collections" / f"{key}.npz"


def _plain_name(name: str) -> bool:
    """Whether ``name`` is a relative path of one or two plain parts (no ``..``, no absolute path, no odd names)."""
    parts = name.split("/")
    return 1 <= len(parts) <= 2 and all(_NAME_PART.fullmatch(p) and p not in (".", "..") for p in parts)


def load_files(key: str) -> dict[str, bytes] | None:
    """The files of the entry of ``key`` (relative name -> bytes), or ``None`` (a miss: no entry, or one that must
    not or cannot be used, said in the debug log)."""
    path = entry_path(key)
    if not path.is_file():
        return None
    why = own_file_problem(path)
    if why is not None:
        log.debug(f"collection cache entry not used: {why}")
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            names, offsets, blob, digest = [str(n) for n in z["names"]], z["offsets"], z["blob"], str(z["sha256"])
        if hashlib.sha256(blob.tobytes()).hexdigest() != digest:
            raise ValueError("its bytes do not match their SHA-256")
        if len(offsets) != len(names) + 1 or not all(map(_plain_name, names)) or offsets[-1] != len(blob):
            raise ValueError("its names or offsets are malformed")
    except Exception as e:  # noqa: BLE001 - damaged or foreign: generated again
        log.debug(f"collection cache entry {path.name} not used: {type(e).__name__}: {e}")
        return None
    data = blob.tobytes()
    try:
        os.utime(path)  # recently used: kept
    except OSError:
        pass
    return {n: data[int(a):int(b)] for n, a, b in zip(names, offsets[:-1], offsets[1:])}


def store_files(key: str, files: dict[str, bytes]) -> Path | None:
    """Keep ``files`` (relative name -> bytes) as the entry of ``key``, then remove all but the :data:`KEEP` most
    recently used entries; the entry's path, or ``None`` where the cache cannot be written (said in the debug
    log)."""
    names = sorted(files)
    if not all(map(_plain_name, names)):
        log.debug(f"collection cache not written: names that are not plain {[n for n in names if not _plain_name(n)]}")
        return None
    data = b"".join(files[n] for n in names)
    offsets = np.cumsum([0] + [len(files[n]) for n in names]).astype(np.int64)
    try:
        folder = private_dir(entry_path(key).parent)
        fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=folder)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, names=np.asarray(names, dtype=str), offsets=offsets,
                         blob=np.frombuffer(data, dtype=np.uint8), sha256=np.asarray(hashlib.sha256(data).hexdigest()))
            os.replace(tmp, folder / f"{key}.npz")
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        _prune(folder)
    except OSError as e:
        log.debug(f"collection cache not written: {e}")
        return None
    return folder / f"{key}.npz"


def _prune(folder: Path) -> None:
    """Remove all but the :data:`KEEP` most recently used entries of ``folder``."""
    entries = []
    for p in folder.glob("*.npz"):
        try:
            entries.append((p.stat().st_mtime, p))
        except OSError:
            continue
    for _, p in sorted(entries, reverse=True)[KEEP:]:
        p.unlink(missing_ok=True)
