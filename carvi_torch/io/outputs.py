"""Atomic file writes and resumable output directories.

Every file the package writes goes through these helpers: the content is written
to a temporary file in the same directory and moved into place with
``os.replace``, so a reader (or a rerun after a crash) sees either the old file
or the complete new one, never a partial file.
"""
from __future__ import annotations

import errno
import hashlib
import io
import json
import math
import os
import re
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

__all__ = ["atomic_write", "write_json", "write_record", "read_json", "read_text", "write_npz", "write_bytes",
           "to_jsonable", "is_done", "safe_name", "record_target", "shown", "shown_names", "folder_within",
           "write_within", "first_link", "numbers"]


def _file_mode() -> int:
    """The mode a new file gets under this process's umask (``0o666 & ~umask``)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


#: Mode of written files: what ``open()`` would give (``mkstemp`` alone gives 0600).
FILE_MODE = _file_mode()


def atomic_write(path: str | os.PathLike, write: Callable[[io.BufferedWriter], None], sync: bool = True) -> Path:
    """Call ``write(fileobj)`` on a temporary file, then move it to ``path`` atomically.

    Parent directories are created. The file gets the mode the process's umask gives new files
    (:data:`FILE_MODE`). ``sync``: flush the file to the disk (``fsync``) before the move, so that it
    survives a crash of the machine, not only of the process; an object's files skip it (a damaged
    file is found and redone on resume: :func:`~carvi_torch.io.layout.finished`). Returns ``Path(path)``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, FILE_MODE)
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            if sync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def write_bytes(path: str | os.PathLike, data: bytes, sync: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (``sync``: :func:`atomic_write`)."""
    return atomic_write(path, lambda f: f.write(data), sync)


def folder_within(root: str | os.PathLike, rel: str | os.PathLike = "") -> Path:
    """``root/rel``, its folders below ``root`` made where missing and none of them a symbolic link, so that
    nothing written into it lands outside ``root`` (``root`` itself is the caller's: made with its parents
    where missing, and it may be a link).

    Raises:
        NotADirectoryError: a link or a file stands where one of the folders is (named; it is left alone).
        ValueError: ``rel`` is absolute or climbs out of ``root`` (``..``).

    Example:
        >>> folder_within("/tmp", "..")
        Traceback (most recent call last):
        ...
        ValueError: '..' is not a path inside /tmp
    """
    path, rel = Path(root), Path(rel)
    if rel.is_absolute() or ".." in rel.parts:
        raise ValueError(f"{str(rel)!r} is not a path inside {root}")
    path.mkdir(parents=True, exist_ok=True)
    for part in rel.parts:
        path = path / part
        try:
            os.mkdir(path)  # never through a link: a link standing there is an existing entry
        except FileExistsError:
            if path.is_symlink() or not path.is_dir():
                kind = "a symbolic link" if path.is_symlink() else "a file"
                raise NotADirectoryError(errno.ENOTDIR, f"{kind}, not a folder: nothing is written through it",
                                         str(path)) from None
    return path


def write_within(root: str | os.PathLike, rel: str | os.PathLike, write: Callable[[io.BufferedWriter], None] | bytes,
                 sync: bool = True) -> Path:
    """Write the file ``root/rel`` (``write``: bytes, or :func:`atomic_write`'s callable) atomically without
    following a symbolic link: its folders come from :func:`folder_within`, and a link standing at its own
    name is replaced by the file (``os.replace``), its target left alone. Returns the file's path."""
    rel = Path(rel)
    path = folder_within(root, rel.parent) / rel.name
    return atomic_write(path, write if callable(write) else (lambda f: f.write(write)), sync)


def first_link(root: str | os.PathLike, names) -> Path | None:
    """The first symbolic link among ``root/name`` for each of ``names`` (in their order) and, below each, at any
    depth (each folder's entries sorted by name), or ``None``: a writer that never writes through a link refuses
    a folder that holds one before it writes anything. Linked folders are named, never entered.

    Example:
        >>> with tempfile.TemporaryDirectory() as d:
        ...     (Path(d) / "a" / "b").mkdir(parents=True)
        ...     (Path(d) / "a" / "b" / "c").symlink_to(d)
        ...     first_link(d, ["x", "a"]).relative_to(d).as_posix(), first_link(d, ["x"])
        ('a/b/c', None)
    """
    root = Path(root)
    for name in names:
        if (root / name).is_symlink():
            return root / name
        for top, dirs, files in os.walk(root / name):  # os.walk enters no linked folder
            for entry in sorted(dirs + files):
                if os.path.islink(os.path.join(top, entry)):
                    return Path(top) / entry
    return None


#: Types that JSON writes as they are (exact types: ``np.float64`` subclasses ``float`` and goes the long way).
_PLAIN = (str, int, bool, type(None))


def to_jsonable(obj: Any) -> Any:
    """Convert tensors, numpy arrays and scalars, paths and tuples to JSON types.

    Non-finite floats become ``None`` (JSON has no NaN). Plain values return at once: a class's
    ``cameras.json`` holds about a hundred of them per object.

    Example:
        >>> to_jsonable({"R": np.eye(2), "s": np.float32(2.5), "t": (1, float("nan")), 3: Path("a")})
        {'R': [[1.0, 0.0], [0.0, 1.0]], 's': 2.5, 't': [1, None], '3': 'a'}
    """
    kind = type(obj)
    if kind in _PLAIN:
        return obj
    if kind is float:
        return obj if math.isfinite(obj) else None
    if kind is dict:
        return {k if type(k) is str else str(k): to_jsonable(v) for k, v in obj.items()}
    if kind is list or kind is tuple:
        return [to_jsonable(v) for v in obj]
    torch = sys.modules.get("torch")  # a tensor exists only where torch was imported
    if torch is not None and isinstance(obj, torch.Tensor):
        obj = obj.detach().cpu().numpy()
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1, sync: bool = True) -> Path:
    """Write ``obj`` (converted with :func:`to_jsonable`) as JSON, atomically (``sync``: :func:`atomic_write`)."""
    text = json.dumps(to_jsonable(obj), indent=indent)
    return write_bytes(path, text.encode("utf-8"), sync)


def write_record(path: str | os.PathLike, obj: Any, key: str | None = None) -> Path:
    """Write ``obj`` as JSON (:func:`write_json`), or, with ``key``, set that key of the JSON object in
    ``path`` to it: the file's other keys are kept, a missing file starts as ``{}``, atomically.
    Benchmark tools keep the records of one docs page in one file this way (``docs/data/``)."""
    if key is None:
        return write_json(path, obj)
    records = read_json(path) if Path(path).exists() else {}
    if not isinstance(records, dict):
        raise ValueError(f"{path}: not a JSON object of records; give another file or no key")
    records[key] = obj
    return write_bytes(path, records_text(records).encode("utf-8"))


def records_text(records: dict) -> str:
    """A JSON object of records, one record per line in compact JSON: a page's records stay small, and a
    record's rewrite changes one line of the file.

    Example:
        >>> print(records_text({"a": {"x": [1, 2]}, "b": 3}), end="")
        {
        "a": {"x":[1,2]},
        "b": 3
        }
    """
    lines = (f"{json.dumps(str(k))}: {json.dumps(to_jsonable(v), separators=(',', ':'))}" for k, v in records.items())
    return "{\n" + ",\n".join(lines) + "\n}\n"


def record_target(out: str | os.PathLike | None, key: str | None, pages_file: Path, default_key: str | None,
                  scratch: Path) -> tuple[Path, str | None]:
    """Where a benchmark tool writes its record (:func:`write_record`'s path and key): ``--out`` (under ``--key``
    when given, else the whole file); ``--key`` alone: that key of ``pages_file``, the records a docs page cites
    (the commands the pages give name their key); neither: ``default_key`` of ``scratch`` (a file under the
    ignored ``outputs/``), so that a plain run never rewrites a committed record.

    Example:
        >>> docs, scratch = Path("docs/data/b.json"), Path("outputs/b.json")
        >>> [record_target(o, k, docs, "run_cpu", scratch) for o, k in ((None, None), (None, "x"), ("my.json", None))]
        [(PosixPath('outputs/b.json'), 'run_cpu'), (PosixPath('docs/data/b.json'), 'x'), (PosixPath('my.json'), None)]
    """
    if out:
        return Path(out), key
    if key:
        return Path(pages_file), key
    return Path(scratch), default_key


def read_text(path: str | os.PathLike) -> str:
    """A UTF-8 text file (a leading byte order mark, as Windows editors write, is dropped); a missing
    file raises ``FileNotFoundError`` and bytes that are not UTF-8 ``ValueError``, both naming the file."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x} at byte {e.start}); "
                         "save it as UTF-8") from None


def read_json(path: str | os.PathLike, object_pairs_hook: Callable[[list], Any] | None = None) -> Any:
    """Read JSON (:func:`read_text`); a malformed file raises ``ValueError`` naming the file, line and
    column, and one nested too deeply for the parser ``ValueError`` naming the file.

    ``object_pairs_hook``: called with each object's ``(key, value)`` pairs in the file's order, its result
    standing for the object (:func:`json.loads`'s); ``None``: a ``dict``, a key given twice keeping its last value.

    Example:
        >>> with tempfile.TemporaryDirectory() as d:
        ...     p = write_bytes(Path(d) / "a.json", b'{"k": 1, "k": 2}')
        ...     read_json(p), read_json(p, object_pairs_hook=list)
        ({'k': 2}, [('k', 1), ('k', 2)])
    """
    path = Path(path)
    text = read_text(path)
    try:
        return json.loads(text, object_pairs_hook=object_pairs_hook)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: malformed JSON at line {e.lineno}, column {e.colno} (char {e.pos}): "
                         f"{e.msg}") from None
    except RecursionError:
        raise ValueError(f"{path}: JSON nested too deeply to read") from None


def write_npz(path: str | os.PathLike, sync: bool = True, **arrays: Any) -> Path:
    """Write a compressed ``.npz`` atomically (tensors are converted to numpy; ``sync``: :func:`atomic_write`).

    Never imports torch: a value can only be a tensor where torch is imported already, and a writer
    process, which passes numpy arrays, starts faster and stays smaller without it.
    """
    torch = sys.modules.get("torch")
    conv = {}
    for k, v in arrays.items():
        if torch is not None and isinstance(v, torch.Tensor):
            v = v.detach().cpu().numpy()
        conv[k] = np.asarray(v)
    return atomic_write(path, lambda f: np.savez_compressed(f, **conv), sync)


def is_done(*paths: str | os.PathLike) -> bool:
    """True when every path exists and is non-empty (a finished, atomically written output)."""
    return all(Path(p).is_file() and Path(p).stat().st_size > 0 for p in paths)


_SAFE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def safe_name(name) -> str:
    """A file or folder name for ``name`` (a class name or an object id) that cannot leave its folder.

    ``name`` itself (as a string) when it is 1 to 100 characters of ``A-Z a-z 0-9 . _ -`` starting
    with a letter or digit (so never ``.``, ``..``, hidden, absolute or nested); otherwise a readable
    spelling of it with the other characters replaced, plus a hash of the original, so that
    different names stay different.

    Example:
        >>> safe_name("car"), safe_name(17), safe_name("../../evil"), safe_name("")
        ('car', '17', 'evil-0fbfd372', 'x-e3b0c442')
    """
    text = str(name)
    if _SAFE.fullmatch(text) and not text.endswith("."):
        return text
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._-")[:60] or "x"
    return f"{slug}-{hashlib.sha256(text.encode('utf-8', 'surrogatepass')).hexdigest()[:8]}"


def numbers(value, shape: tuple, finite: bool = True) -> bool:
    """Whether ``value`` is nested lists of ``shape`` holding numbers (not booleans; finite ones where ``finite``).

    Example:
        >>> numbers([[1, 2.5], [3, 4]], (2, 2)), numbers([1, "2"], (2,)), numbers(None, ())
        (True, False, False)
        >>> numbers(float("nan"), ()), numbers(float("nan"), (), finite=False)
        (False, True)
    """
    if shape:
        return isinstance(value, list) and len(value) == shape[0] and all(numbers(v, shape[1:], finite)
                                                                          for v in value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return not finite or math.isfinite(value)
    except OverflowError:  # an integer too large for a float
        return False


def shown(value, width: int = 40) -> str:
    """``value`` (from a user's file) as a reason quotes it: its ``repr`` on one line, cut at ``width`` characters.

    Example:
        >>> shown([1, 2]), shown("x" * 50, 10)
        ('[1, 2]', "'xxxxxx...")
    """
    text = " ".join(repr(value).split())
    return text if len(text) <= width else text[:width - 3] + "..."


def shown_names(names: Sequence, first: int = 3, quoted: bool = False) -> str:
    """The first ``first`` of ``names`` (a sequence) as a reason lists them: joined by commas (each ``str``, or
    ``repr`` with ``quoted``), then how many more there are.

    Example:
        >>> shown_names(["m1", "m2", "m3", "m4", "m5"]), shown_names(["nose tip"], quoted=True), shown_names([7, 8], 1)
        ('m1, m2, m3 and 2 more', "'nose tip'", '7 and 1 more')
    """
    text = ", ".join(map(repr if quoted else str, names[:first]))
    return text + (f" and {len(names) - first} more" if len(names) > first else "")
