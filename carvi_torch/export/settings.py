"""The export's settings and their ranges (light: the command line checks them before it imports anything
heavy, and :func:`~carvi_torch.export.run.export` checks them too)."""
from __future__ import annotations

__all__ = ["settings_problem", "RESOLUTION_RANGE"]

#: ``--resolution``'s range: 3 is the least that keeps the view grid's first and last depth layers empty
#: (docs/export.md); at 512 one object's two grids hold 2 x 512^3 cells already.
RESOLUTION_RANGE = (3, 512)


def settings_problem(resolution: int, points: int, shard_size: int, seed: int, workers: int | None,
                     options: bool = True) -> str | None:
    """What is wrong with the export's settings (one line naming the option, or the argument of
    :func:`~carvi_torch.export.run.export` where ``options`` is off), or None.

    Example:
        >>> settings_problem(32, 2048, 256, 0, None) is None, settings_problem(0, 2048, 256, 0, None)
        (True, '--resolution must be an integer from 3 to 512, got 0')
    """
    lo, hi = RESOLUTION_RANGE
    checks = [("--resolution", resolution, lo <= resolution <= hi, f"an integer from {lo} to {hi}"),
              ("--points", points, points >= 1, "an integer >= 1"),
              ("--shard-size", shard_size, shard_size >= 1, "an integer >= 1"),
              ("--seed", seed, seed >= 0, "an integer >= 0"),
              ("--workers", workers, workers is None or workers >= 0, "an integer >= 0")]
    for option, value, ok, what in checks:
        if not ok:
            name = option if options else option[2:].replace("-", "_")
            return f"{name} must be {what}, got {value}"
    return None
