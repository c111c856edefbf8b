"""Where an export reads from: a reconstruction directory's configuration and the annotations it ran on."""
from __future__ import annotations

from pathlib import Path

from ..config import Config, read_run_config
from ..io.outputs import read_json

__all__ = ["recon_config", "data_path", "unfinished"]


def recon_config(recon: Path) -> Config:
    """The resolved configuration of a reconstruction directory (its ``config.yaml``)."""
    p = recon / "config.yaml"
    if not p.is_file():
        raise FileNotFoundError(f"{recon}: no config.yaml (is this a reconstruction directory?)")
    return read_run_config(p)


def data_path(recon: Path, cfg: Config) -> Path:
    """The annotations a run read: its summary's path (absolute), else its config's; a relative path
    is looked up beside the run, then from the current folder."""
    summ = recon / "summary.json"
    data = read_json(summ).get("data") if summ.is_file() else None
    data = data or cfg.data
    if not data:
        return recon / "input" / "annotations.json"
    p = Path(data)
    if p.is_absolute():
        return p
    for base in (recon, recon.parent):
        if (base / p).is_file():
            return base / p
    return p


def unfinished(recon: Path) -> bool:
    """Whether the run in ``recon`` has not finished (interrupted, or still running): its ``summary.json`` is
    missing, unreadable, or has no ``total_seconds`` (which a run writes when its last class is done)."""
    try:
        summary = read_json(recon / "summary.json")
    except (OSError, ValueError):
        return True
    return not isinstance(summary, dict) or "total_seconds" not in summary
