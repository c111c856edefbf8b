"""The package's cache folder: ``$CARVI_TORCH_CACHE``, else ``~/.cache/carvi_torch``, and its rules.

Two things are kept there, each in a folder of its own: the compiled kernels (``kernels/``,
:mod:`carvi_torch.native_library`) and the generated embedded collection (``collections/``,
:mod:`carvi_torch.synthetic.cache`). Every folder is the user's own, mode 0700 (:func:`private_dir`), and a
file is read only when it is a regular file of this user that no one else may write (:func:`own_file_problem`):
what others can write is never loaded.

Example:
    >>> cache_root().name in ("carvi_torch",) or "CARVI_TORCH_CACHE" in os.environ
    True
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["cache_root", "private_dir", "own_file_problem"]


def cache_root() -> Path:
    """``$CARVI_TORCH_CACHE``, else ``~/.cache/carvi_torch`` (made by :func:`private_dir` when used)."""
    root = os.environ.get("CARVI_TORCH_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "carvi_torch"


def private_dir(path: Path) -> Path:
    """``path`` as a directory of this user, mode 0700 (created so; an existing one of ours is tightened).

    Raises ``PermissionError`` for a directory of another user or a symbolic link."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)  # the mode applies to the root only if created
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        raise PermissionError(f"the cache folder {path} is not a directory (a link?)")
    if os.name == "posix":
        if st.st_uid != os.getuid():
            raise PermissionError(f"the cache folder {path} belongs to uid {st.st_uid}, not to this user "
                                  f"({os.getuid()})")
        if stat.S_IMODE(st.st_mode) != 0o700:
            os.chmod(path, 0o700)
    return path


def own_file_problem(path: Path) -> str | None:
    """Why ``path`` is not a regular file of this user without group/other write bits (``None`` when it is)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return f"{path.name} is missing"
    if not stat.S_ISREG(st.st_mode):
        return f"{path.name} is not a regular file"
    if os.name == "posix" and st.st_uid != os.getuid():
        return f"{path.name} belongs to uid {st.st_uid}, not {os.getuid()}"
    if os.name == "posix" and st.st_mode & 0o022:
        return f"{path.name} is writable by others (mode {stat.S_IMODE(st.st_mode):o})"
    return None
