"""What every stage and command shares about the process it runs in.

- resources: CPU cores (:func:`cores`), torch threads (:func:`torch_threads`, :func:`intra_op_threads`), stage
  timers (:class:`StageTimer`), peak memory and CPU time (:func:`peak_rss_mb`, :func:`cpu_seconds`);
- output folders before a run writes: :func:`unwritable_above`, :func:`check_replaceable`, :func:`os_error_line`,
  :func:`folders_to_make` and :func:`remove_empty` (a failed command leaves no folder it made);
- Ctrl-C and signals: :func:`watch_interrupts`, :func:`deferred_interrupt`, :func:`ignore_interrupt`;
- child processes: :func:`start_method`, :class:`LeanProcessPool`, :func:`watch_parent`, :func:`processes_marked`,
  :func:`child_pythonpath`;
- moving objects between devices: :func:`to_device`, :func:`fields_to_device`;
- logging to the terminal (tqdm-safe) and to ``run.log``: :func:`log_to_terminal`, :func:`log_to_file`;
- locks between processes: :class:`FileLock` (an advisory ``flock``), :class:`FolderLock` (one run per folder).

Nothing here knows a pipeline stage; every stage may import it. torch is imported on first use
only, so that processes that never need it (the writers) start fast.

Example:
    >>> import torch
    >>> with torch_threads(1):
    ...     torch.get_num_threads()
    1
"""
from __future__ import annotations

import contextlib
import copy
import errno
import logging
import os
import signal
import sys
import threading
import time
import types
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable, Iterator

try:  # POSIX only; peak memory is unknown elsewhere (Windows)
    import resource
except ImportError:  # pragma: no cover - exercised by tests that hide the module
    resource = None
try:  # POSIX only; nothing is locked elsewhere (Windows): FileLock.lock
    import fcntl
except ImportError:  # pragma: no cover - Windows (tests set it to None)
    fcntl = None

__all__ = ["cores", "env_count", "torch_threads", "cpu_single_thread", "StageTimer", "peak_rss_mb", "cpu_seconds",
           "maxrss_to_mb", "stable_hash", "InterruptWatch", "watch_interrupts", "intra_op_threads", "log",
           "log_to_terminal", "log_to_file", "TqdmHandler", "deferred_interrupt", "ignore_interrupt",
           "unwritable_above", "folders_to_make", "remove_empty", "check_replaceable", "os_error_line", "watch_parent",
           "pid_alive", "processes_marked", "gone_within", "FileLock", "FolderLock", "FolderBusy", "NO_LOCKS"]


def cores() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)



def unwritable_above(path: str | os.PathLike) -> str | None:
    """Why ``path`` (a file or folder that may not exist yet) cannot be made, judged by the nearest existing
    path above it: ``"<it> is a file, not a folder"`` or ``"<it> is not writable"``; ``None`` when it can.
    Nothing is created.

    Example:
        >>> unwritable_above(os.devnull + "/run/x") is None, unwritable_above(os.devnull + "/run/x")
        (False, '/dev/null is a file, not a folder')
    """
    probe = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        return f"{probe} is a file, not a folder"
    return None if os.access(probe, os.W_OK | os.X_OK) else f"{probe} is not writable"


def folders_to_make(out: str | os.PathLike) -> list[Path]:
    """``out`` and those of its parents that do not exist yet, deepest first: what ``mkdir(parents=True)`` makes,
    and what :func:`remove_empty` removes again after a failure.

    Example:
        >>> [p.name for p in folders_to_make(Path(os.devnull).parent / "no" / "such")]
        ['such', 'no']
    """
    made = []
    for p in (Path(out), *Path(out).parents):
        if p.exists() or p.is_symlink():
            break
        made.append(p)
    return made


def remove_empty(folders: list[Path]) -> None:
    """Remove ``folders`` (deepest first, as :func:`folders_to_make` gives them) while they are empty: a command
    that fails leaves none of the folders it made behind, and nothing else is touched."""
    for p in folders:
        try:
            p.rmdir()
        except OSError:
            break


def check_replaceable(out: Path, others: Callable[[Path], list[str]], what: str,
                      error: type[Exception] = ValueError) -> None:
    """Refuse, before anything is written, an output folder ``out`` that is a file, or a folder holding
    anything but ``what`` (an earlier output of this command, which it replaces): ``others(out)`` names the
    entries of the existing folder ``out`` that are not (none: ``out`` may be written over). Raises ``error``.

    Example:
        >>> check_replaceable(Path(os.devnull), lambda out: [], "an earlier report")
        Traceback (most recent call last):
        ...
        ValueError: --out /dev/null is a file, not a folder
    """
    from .io.outputs import shown_names

    if out.exists() and not out.is_dir():
        raise error(f"--out {out} is a file, not a folder")
    other = sorted(others(out)) if out.is_dir() else []
    if other:
        raise error(f"--out {out}: not empty and not {what} (it holds "
                    f"{shown_names(other, 1, quoted=True)}); choose another --out "
                    "(nothing was written)")


def os_error_line(e: OSError, said: str | os.PathLike | None = None) -> str:
    """One line for an operating-system error: the path(s) and the system's reason. A path equal to ``said``
    (one the message around it names already) is left out; a different one (a parent folder that could not
    be made) is kept.

    Example:
        >>> os_error_line(IsADirectoryError(21, "Is a directory", "out/annotations.json"))
        'out/annotations.json: Is a directory'
        >>> os_error_line(NotADirectoryError(20, "Not a directory", "file/sub"), said="file/sub/")
        'Not a directory'
    """
    names = [str(n) for n in (e.filename, e.filename2) if n is not None]  # a path, or a descriptor's number
    if said is not None:
        names = [n for n in names if os.path.normpath(n) != os.path.normpath(os.fspath(said))]
    reason = e.strerror or str(e)
    return f"{' -> '.join(names)}: {reason}" if names else reason


def env_count(name: str, minimum: int) -> int | None:
    """The integer environment variable ``name`` (at least ``minimum``), or None when unset.

    Example:
        >>> env_count("CARVI_SURELY_UNSET_VARIABLE", 1) is None
        True
    """
    env = os.environ.get(name)
    if env is None:
        return None
    try:
        return max(minimum, int(env))
    except ValueError:
        raise ValueError(f"{name} must be an integer, got {env!r}") from None


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the enclosed code with ``n`` torch intra-op threads; the previous count is restored."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def cpu_single_thread(device) -> Iterator[None]:
    """Run the enclosed torch ops with one intra-op thread when ``device`` is the CPU.

    The iterative solvers (SfM, refinement) are hundreds of small tensor ops; intra-op
    threads only add synchronisation to them (measured: rigid SfM of 4,000 instances took
    3.0 s with 1 thread and 26 s with 2 on a 2-core machine busy with other work). The
    previous thread count is restored on exit. No effect on other devices.
    """
    import torch

    if torch.device(device).type != "cpu" or torch.get_num_threads() == 1:
        yield
        return
    with torch_threads(1):
        yield


class StageTimer:
    """Wall seconds per named stage, summed over calls; CUDA work is synchronised at each stop.

    Example:
        >>> timer = StageTimer("cpu")
        >>> with timer("sfm"):
        ...     pass
        >>> list(timer.seconds)
        ['sfm']
    """

    def __init__(self, device="cpu", seconds: dict | None = None):
        import torch

        self.device = torch.device(device)
        self.seconds: dict[str, float] = {} if seconds is None else seconds

    @contextlib.contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.device.type == "cuda":
                sys.modules["torch"].cuda.synchronize(self.device)
            self.add(stage, time.perf_counter() - t0)

    def add(self, stage: str, seconds: float) -> None:
        """Book ``seconds`` to ``stage``."""
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds


def maxrss_to_mb(value: float, platform: str = sys.platform) -> float:
    """``ru_maxrss`` in MB: the kernel reports kilobytes on Linux and bytes on macOS.

    Example:
        >>> maxrss_to_mb(2048, "linux"), maxrss_to_mb(2 * 2 ** 20, "darwin")
        (2.0, 2.0)
    """
    return value / (2.0 ** 20 if platform == "darwin" else 1024.0)


def peak_rss_mb(children: bool = False) -> float | None:
    """Peak resident memory (MB) of this process, or of its largest finished child process;
    ``None`` where the platform does not say (no ``resource`` module)."""
    if resource is None:
        return None
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return maxrss_to_mb(resource.getrusage(who).ru_maxrss)


def cpu_seconds(children: bool = False) -> float:
    """CPU seconds (user + system) of this process so far, or of its finished and waited-for child processes
    (``children``); NaN where the platform does not say (no ``resource`` module). Benchmarks take differences.

    Example:
        >>> cpu_seconds() >= 0 and cpu_seconds(children=True) >= 0
        True
    """
    if resource is None:
        return float("nan")
    r = resource.getrusage(resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class InterruptWatch:
    """Whether a Ctrl-C (SIGINT) arrived while a :func:`watch_interrupts` block ran.

    Code that turns the exceptions of bad input into one-line reasons calls :meth:`check` after each
    object: an interrupt that a library swallowed and turned into another exception is raised again
    as ``KeyboardInterrupt`` (seen once: a Ctrl-C during loading came out of pycocotools' mask
    decoding as numpy's ``TypeError`` about an old-style ``__array__`` method, the run went on).
    """

    def __init__(self) -> None:
        self.seen = False

    def check(self) -> None:
        """Raise ``KeyboardInterrupt`` when an interrupt arrived since the block began."""
        if self.seen:
            raise KeyboardInterrupt


def _replaceable_sigint():
    """The SIGINT handler now in place when a block may put its own in for a while, else ``None``: Python
    delivers signals to the main thread only, and a SIGINT that is ignored (a job started with `&`) or left
    to the system (a handler set outside Python) stays as it is.

    Example:
        >>> _replaceable_sigint() is signal.getsignal(signal.SIGINT)
        True
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    handler = signal.getsignal(signal.SIGINT)
    return handler if callable(handler) else None


@contextlib.contextmanager
def watch_interrupts() -> Iterator[InterruptWatch]:
    """Record SIGINTs while the block runs (the previous handler still runs, so Ctrl-C still raises
    ``KeyboardInterrupt`` where it lands); outside the main thread, or when SIGINT is ignored or left
    to the system, nothing is installed and the watch never fires.

    Example:
        >>> with watch_interrupts() as watch:
        ...     watch.check()  # no Ctrl-C: nothing happens
        >>> watch.seen
        False
    """
    watch = InterruptWatch()
    previous = _replaceable_sigint()
    if previous is None:
        yield watch
        return

    def handler(signum, frame):
        watch.seen = True
        previous(signum, frame)

    signal.signal(signal.SIGINT, handler)
    try:
        yield watch
    finally:
        signal.signal(signal.SIGINT, previous)


def stable_hash(name: str) -> int:
    """A hash of ``name`` that is the same in every process (seeds per class).

    Example:
        >>> stable_hash("car") == stable_hash("car")
        True
    """
    return zlib.crc32(name.encode()) % (2 ** 31)


def intra_op_threads(workers: int, device="cpu") -> int:
    """Intra-op threads of this process during a run: ``CARVI_THREADS`` if set; else, on the CPU, the cores
    less half the ``workers`` writer processes' count; on a GPU, the cores less the writers (at least one).

    On the CPU the writers need about a quarter of the main process's CPU time (meshing and writing 13.6 s
    against 55.9 s for 1,000 cars on 2 cores, one thread), so their processes share the cores the carving and
    the selection's kernels use: on 2 cores, 2 threads beside the one writer take 0.786x the time of one thread
    (docs/benchmarks.md, records ``benchmark_cpu_1000_today`` and ``benchmark_cpu_1000_one_thread``). Only that
    case is measured; on 16 cores the rule gives 12 threads beside 8 writers. On a GPU the main process
    mostly launches kernels and the writers limit the run. ``device``: a str or a torch.device (``None``: the CPU).

    Example:
        >>> from unittest import mock
        >>> with mock.patch.dict(os.environ, {}, clear=False), mock.patch(__name__ + ".cores", lambda: 16):
        ...     _ = os.environ.pop("CARVI_THREADS", None)
        ...     intra_op_threads(8), intra_op_threads(15, "cuda:1"), intra_op_threads(1, None)
        (12, 1, 16)
    """
    env = env_count("CARVI_THREADS", 1)
    if env is not None:
        return env
    gpu = device is not None and str(device).split(":")[0].lower() != "cpu"  # torch is not imported here
    return max(1, cores() - (workers if gpu else workers // 2))


def to_device(obj, device, _memo: dict | None = None):
    """``obj`` with every tensor it holds on ``device``: tensors and objects with a ``to`` method of their own
    (:class:`~carvi_torch.collection.ClassCollection`, the cameras) through it; other dataclasses as shallow
    copies, field by field (:func:`fields_to_device`); lists, tuples and dicts element by element; anything
    else (numbers, strings, ``None``) as is. An object reached twice is moved once, and stays shared.

    Example:
        >>> import dataclasses, torch
        >>> @dataclasses.dataclass
        ... class Result:
        ...     x: torch.Tensor
        ...     parts: list
        ...     note: str = "kept"
        >>> r = to_device(Result(torch.ones(2), [(torch.zeros(1), 3)]), "meta")
        >>> r.x.device.type, r.parts[0][0].device.type, r.parts[0][1], r.note
        ('meta', 'meta', 3, 'kept')
    """
    import dataclasses

    memo = {} if _memo is None else _memo
    if id(obj) in memo:
        return memo[id(obj)][1]
    if callable(getattr(obj, "to", None)) and not isinstance(obj, type):
        moved = obj.to(device)
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        moved = fields_to_device(obj, device, _memo=memo)
    elif isinstance(obj, tuple) and hasattr(obj, "_fields"):  # a named tuple
        moved = type(obj)(*(to_device(v, device, memo) for v in obj))
    elif isinstance(obj, (list, tuple)):
        moved = type(obj)(to_device(v, device, memo) for v in obj)
    elif isinstance(obj, dict):  # a subclass (an ordered or default dict) stays one, through a shallow copy
        moved = {} if type(obj) is dict else copy.copy(obj)
        moved.update((k, to_device(v, device, memo)) for k, v in obj.items())
    else:
        return obj
    memo[id(obj)] = (obj, moved)  # the original is held too, so that its id is not reused meanwhile
    return moved


def fields_to_device(obj, device, keep: tuple = (), _memo: dict | None = None):
    """A shallow copy of the dataclass ``obj`` with each field through :func:`to_device`, but the fields named
    in ``keep``, which the copy shares with ``obj`` as they are."""
    import dataclasses

    memo = {} if _memo is None else _memo
    moved = copy.copy(obj)
    for f in dataclasses.fields(obj):
        if f.name not in keep:
            object.__setattr__(moved, f.name, to_device(getattr(obj, f.name), device, memo))
    return moved


@contextlib.contextmanager
def without_main_module() -> Iterator[None]:
    """Processes started meanwhile skip this process's main module.

    ``spawn`` and ``forkserver`` children import the parent's ``__main__`` again (as ``__mp_main__``) so
    that functions defined there can be unpickled. The package's worker processes run functions of its
    own modules only, and a run's main module (``carvi_torch.reconstruct``, the ``carvi`` script) imports
    torch and the whole package: about 160 MB and a second or more of CPU per worker, for nothing.
    ``__main__`` is a blank module while the processes start (``multiprocessing`` reads it then), this
    process's own again after.
    """
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


@contextlib.contextmanager
def deferred_interrupt() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) back until the block ends, then raise the ``KeyboardInterrupt``: for work that
    must not stop half-way (a zarr write, whose event-loop thread a ``KeyboardInterrupt`` would leave
    running, or the renames that swap a finished store in). Outside the main thread it does nothing
    (Python delivers signals to the main thread only), and so it does where SIGINT is ignored.

    Example:
        >>> import signal
        >>> try:
        ...     with deferred_interrupt():
        ...         signal.raise_signal(signal.SIGINT)
        ...         print("the block finished")
        ... except KeyboardInterrupt:
        ...     print("then interrupted")
        the block finished
        then interrupted
    """
    previous = _replaceable_sigint()
    if previous is None:
        yield
        return
    caught: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            raise KeyboardInterrupt


def ignore_interrupt() -> None:
    """Ignore Ctrl-C in this (worker) process: a terminal sends SIGINT to the whole process group, and the
    main process handles it (it stops its workers), so that no worker prints a traceback of its own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def start_method() -> str:
    """How the package's worker processes start: ``forkserver`` where available, else ``spawn`` (never ``fork``).

    Example:
        >>> start_method() in ("forkserver", "spawn")
        True
    """
    import multiprocessing as mp

    return "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this host (another user's counts: a reused pid is alive).

    Example:
        >>> pid_alive(os.getpid())
        True
    """
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's (a reused pid)
        return True
    return True


def processes_marked(needle: str) -> list[int]:
    """The pids of the running processes whose environment holds ``needle``, read from Linux's ``/proc`` (none
    where there is no ``/proc``). A process started with a unique environment variable passes it to every
    process it starts (forkserver, workers, resource tracker): the tests and the stress tool find a run's
    processes by it.

    Example:
        >>> processes_marked("CARVI_NO_SUCH_MARKER=" + "0" * 32)
        []
    """
    pids = []
    for p in Path("/proc").iterdir() if os.path.isdir("/proc") else ():
        try:
            if p.name.isdigit() and needle.encode() in (p / "environ").read_bytes():
                pids.append(int(p.name))
        except OSError:  # gone meanwhile, or another user's
            continue
    return pids


def gone_within(needle: str, seconds: float, poll: float = 0.1) -> list[int]:
    """Wait until no process holds ``needle`` (:func:`processes_marked`) or ``seconds`` have passed; SIGKILL
    those left, by pid, and return their pids (empty: every one was gone in time)."""
    deadline = time.monotonic() + seconds
    while processes_marked(needle) and time.monotonic() < deadline:
        time.sleep(poll)
    left = processes_marked(needle)
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:  # gone meanwhile
            pass
    return left


def watch_parent(run_pid: int, period: float = 0.5) -> None:
    """Process initializer: exit this process as soon as the run that started it (``run_pid``) is gone.

    A process started by the forkserver is that server's child, and the server itself lives as long as
    its children do, so the run's own pid is watched (where ``os.kill(pid, 0)`` can tell, on POSIX),
    and the parent too (re-parenting: under spawn the parent is the run)."""
    parent = os.getppid()
    posix = os.name == "posix"

    def watch():
        while True:
            time.sleep(period)
            if os.getppid() != parent or (posix and run_pid != parent and not pid_alive(run_pid)):
                os._exit(0)

    threading.Thread(target=watch, name="carvi-run-watch", daemon=True).start()


class LeanProcessPool(ProcessPoolExecutor):
    """A process pool whose processes start without the parent's main module (:func:`without_main_module`)
    whenever it starts one (``_spawn_process``, the one place a pool does; on a Python that names it
    otherwise its processes start as in a plain pool, only heavier). Submit module-level functions of
    importable modules, never ones defined in ``__main__``."""

    def _spawn_process(self):
        with without_main_module():
            super()._spawn_process()

    def stop(self) -> None:
        """Terminate the worker processes (the work in progress is dropped), then shut the pool down without
        waiting; before the shutdown, which would let an idle process exit on its own first. The pool keeps its
        processes in ``_processes``, the only handle there is to them."""
        for p in list((getattr(self, "_processes", None) or {}).values()):
            p.terminate()
        self.shutdown(wait=False, cancel_futures=True)


def child_pythonpath(code: str | os.PathLike, inherited: str | None = None) -> str:
    """``PYTHONPATH`` for a child process that runs the ``carvi_torch`` of the source tree ``code``: that
    tree first, then the entries this process inherited (``inherited``, default ``$PYTHONPATH``), so
    dependencies installed outside the environment (a private ``--target`` folder, say) stay importable.

    Example:
        >>> child_pythonpath("/src/old", inherited=os.pathsep.join(["/deps", "/src/new"])).split(os.pathsep)
        ['/src/old', '/deps', '/src/new']
        >>> child_pythonpath("/src/new", inherited="")
        '/src/new'
    """
    rest = os.environ.get("PYTHONPATH", "") if inherited is None else inherited
    return os.pathsep.join([os.fspath(code), *(p for p in rest.split(os.pathsep) if p)])


class TqdmHandler(logging.StreamHandler):
    """A log handler that writes through ``tqdm.write``, so messages do not tear progress bars."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            from tqdm.auto import tqdm

            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # noqa: BLE001 - logging must never raise
            self.handleError(record)


#: The package's logger; modules log through children of it (``carvi_torch.<module>``).
log = logging.getLogger("carvi_torch")


@contextlib.contextmanager
def _handler(h: logging.Handler) -> Iterator[None]:
    before = log.level
    log.setLevel(logging.DEBUG)
    log.addHandler(h)
    try:
        yield
    finally:
        log.removeHandler(h)
        h.close()
        log.setLevel(before)


def log_to_terminal(quiet: bool = False):
    """Context: the package's log on the terminal (INFO, or WARNING when ``quiet``), through ``tqdm.write``."""
    h = TqdmHandler(sys.stderr)
    h.setLevel(logging.WARNING if quiet else logging.INFO)
    h.setFormatter(logging.Formatter("%(message)s"))
    return _handler(h)


class _AppendNoFollow(logging.FileHandler):
    """A log file opened without following a symbolic link (``OSError`` where the path is one): the log
    stays inside the run's folder."""

    def _open(self):
        fd = os.open(self.baseFilename, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
        return open(fd, "a", encoding=self.encoding, errors=self.errors)


def log_to_file(path: str | os.PathLike):
    """Context: every record of the package's log (DEBUG and up, timestamped) appended to ``path``."""
    h = _AppendNoFollow(path, encoding="utf-8")
    h.setLevel(logging.DEBUG)
    h.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    return _handler(h)


#: The errors of ``flock`` where the file system has no locks (Lustre without ``-o flock``, some NFS).
NO_LOCKS = (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP)


class FileLock:
    """An open lock file, for an advisory ``flock`` between processes: :meth:`lock` takes it, :meth:`release` (or
    the context's end, or the process's) lets it go. The file is created where missing (``mode``, less the
    umask), opened without following a link and closed on ``exec``; one this process may not open for writing
    (another user's in a shared folder, or one on a read-only mount) is opened read-only, as a local ``flock``
    needs no write access (NFS's does for an exclusive lock: :meth:`lock` says so). The file stays after the
    release.

    Example:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "lock"
        >>> with FileLock(path) as a, FileLock(path) as b:  # shared: both hold it, and an exclusive lock waits
        ...     a.lock(exclusive=False) and b.lock(exclusive=False)
        ...     with FileLock(path) as c:
        ...         try:
        ...             c.lock(wait=False)
        ...         except BlockingIOError:
        ...             print("held by a and b")
        True
        held by a and b
        >>> with FileLock(path) as c:
        ...     c.lock(wait=False)
        True
    """

    def __init__(self, path: str | os.PathLike, mode: int = 0o666):
        self.path = Path(path)
        flags = getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
        self.read_only = False
        try:
            self.fd: int | None = os.open(self.path, os.O_RDWR | os.O_CREAT | flags, mode)
        except OSError as e:
            if e.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
                raise
            try:
                self.fd, self.read_only = os.open(self.path, os.O_RDONLY | flags), True
            except FileNotFoundError:  # none to lock, and none can be made here: why not
                raise e from None

    def lock(self, exclusive: bool = True, wait: bool = True) -> bool:
        """Take the lock, ``exclusive`` or shared; while another holder (another process, or another
        :class:`FileLock` of this one) keeps it from this, wait (``wait``) or raise :class:`BlockingIOError`.
        ``False`` where the platform has no ``flock`` (nothing is locked), an ``OSError`` of :data:`NO_LOCKS` where
        the file system has none, or where it locks this file only when opened for writing (NFS emulates ``flock``
        with POSIX locks: ``EBADF`` on a read-only descriptor)."""
        if fcntl is None:
            return False
        try:
            fcntl.flock(self.fd, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | (0 if wait else fcntl.LOCK_NB))
        except OSError as e:
            if e.errno == errno.EBADF and self.read_only and self.fd is not None:
                raise OSError(errno.ENOLCK, f"{self.path} is open read-only, and this file system locks only files "
                                            "open for writing") from e
            raise
        return True

    def release(self) -> None:
        """Unlock (closing the file); a second call does nothing."""
        if self.fd is not None:
            fd, self.fd = self.fd, None
            os.close(fd)  # closing the last descriptor drops the flock

    def __enter__(self) -> "FileLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


class FolderBusy(Exception):
    """Another process holds :class:`FolderLock` on the folder (the message names it and that process)."""


class FolderLock(FileLock):
    """An exclusive lock on a folder for one process: a :class:`FileLock` on ``folder/name`` (a hidden file), held
    until :meth:`release` (or the context's end, or the process's). Two runs into one ``--out`` would overwrite
    each other's ``config.yaml``, ``summary.json`` and files; the second is refused instead (:class:`FolderBusy`,
    naming the last holder's pid, which the file holds). On a file system or platform without locks the folder
    is used unlocked, with a warning.

    Example:
        >>> import tempfile
        >>> d = tempfile.mkdtemp()
        >>> with FolderLock(d):
        ...     try:
        ...         FolderLock(d)
        ...     except FolderBusy as e:
        ...         print("busy")
        busy
        >>> FolderLock(d).release()
    """

    NAME = ".carvi_torch.lock"

    def __init__(self, folder: str | os.PathLike, name: str = NAME):
        super().__init__(Path(folder) / name)
        try:
            if not self.lock(exclusive=True, wait=False):
                raise OSError(errno.ENOSYS, "this platform has no flock")
        except BlockingIOError:
            holder = os.pread(self.fd, 32, 0).decode("ascii", "replace").strip() or "?"
            self.release()
            raise FolderBusy(f"{folder}: another process (pid {holder}) is writing into it") from None
        except OSError as e:
            if e.errno not in NO_LOCKS:
                self.release()
                raise
            log.warning(f"{folder}: this file system cannot lock it ({e.strerror}); make sure no other run writes "
                        "into it meanwhile")
        except BaseException:
            self.release()
            raise
        with contextlib.suppress(OSError):  # the pid, for another run's message (not where the file is read-only)
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, str(os.getpid()).encode(), 0)
