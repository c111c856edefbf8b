"""Process resources every stage shares: CPU cores, torch threads, stage timers, peak memory.

Nothing here knows a pipeline stage; every stage may import it.

Example:
    >>> with torch_threads(1):
    ...     torch.get_num_threads()
    1
"""
from __future__ import annotations

import contextlib
import os
import sys
import time
import zlib
from typing import Iterator

import torch

try:  # POSIX only; peak memory is unknown elsewhere (Windows)
    import resource
except ImportError:  # pragma: no cover - exercised by tests that hide the module
    resource = None

__all__ = ["cores", "env_count", "torch_threads", "cpu_single_thread", "StageTimer", "peak_rss_mb",
           "maxrss_to_mb", "stable_hash", "intra_op_threads"]


def cores() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


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
    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def cpu_single_thread(device: torch.device | str) -> Iterator[None]:
    """Run the enclosed torch ops with one intra-op thread when ``device`` is the CPU.

    The iterative solvers (SfM, refinement) are hundreds of small tensor ops; intra-op
    threads only add synchronisation to them (measured: rigid SfM of 4,000 instances took
    3.0 s with 1 thread and 26 s with 2 on a 2-core machine busy with other work). The
    previous thread count is restored on exit. No effect on other devices.
    """
    if torch.device(device).type != "cpu" or torch.get_num_threads() == 1:
        yield
        return
    with torch_threads(1):
        yield


class StageTimer:
    """Wall seconds per named stage, summed over calls; CUDA work is synchronised at each stop.

    Example:
        >>> timer = StageTimer(torch.device("cpu"))
        >>> with timer("sfm"):
        ...     pass
        >>> list(timer.seconds)
        ['sfm']
    """

    def __init__(self, device: torch.device | str = "cpu", seconds: dict | None = None):
        self.device = torch.device(device)
        self.seconds: dict[str, float] = {} if seconds is None else seconds

    @contextlib.contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
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


def stable_hash(name: str) -> int:
    """A hash of ``name`` that is the same in every process (seeds per class).

    Example:
        >>> stable_hash("car") == stable_hash("car")
        True
    """
    return zlib.crc32(name.encode()) % (2 ** 31)


def intra_op_threads(workers: int) -> int:
    """Intra-op threads of this process during a run: ``CARVI_THREADS`` if set, else the CPU
    cores left to it beside ``workers`` writer processes (at least one)."""
    env = env_count("CARVI_THREADS", 1)
    return env if env is not None else max(1, cores() - workers)
