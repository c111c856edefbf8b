"""Worked example of the hand-off: train a small network on a carvi_torch export, on the CPU.

The network sees only an object's canvas mask and predicts its viewpoint (azimuth as
(cos, sin), and elevation), supervised by the cameras the reconstruction estimated. The
loss printed per epoch should fall.

    python -m carvi_torch.reconstruct --out runs/default
    python -m carvi_torch.export --recon runs/default --out exports/default
    python tools/train_example.py --export exports/default --epochs 8 [--min-quality 0.3]

With no --export, it reconstructs and exports the embedded procedural collection first
(a few minutes) into outputs/train_example/ of the checkout; an --export that holds no export is
an error.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.utils.data import DataLoader, random_split

from carvi_torch.training import LiftedDataset, collate_lifted

ROOT = Path(__file__).resolve().parents[1]


class ViewpointNet(nn.Module):
    """mask (B, 1, C, C) -> (cos azimuth, sin azimuth, elevation) (B, 3)."""

    def __init__(self, classes: int):
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(1, 16, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.ReLU(),
            nn.AdaptiveAvgPool2d(4), nn.Flatten())
        self.embed = nn.Embedding(classes, 16)
        self.head = nn.Sequential(nn.Linear(64 * 16 + 16, 128), nn.ReLU(), nn.Linear(128, 3))

    def forward(self, mask, cls):
        return self.head(torch.cat([self.features(mask), self.embed(cls)], dim=1))


def targets(batch):
    az, el = batch["viewpoint"][:, 0], batch["viewpoint"][:, 1]
    return torch.stack([torch.cos(az), torch.sin(az), el], dim=1)


def build_parser() -> argparse.ArgumentParser:
    """The command line (the module docstring is its help)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--export", help="export (zarr store) directory; it must hold one (default: "
                                     "outputs/train_example/export, built from the embedded collection when absent)")
    ap.add_argument("--epochs", type=int, default=8, help="passes over the training objects (default 8)")
    ap.add_argument("--batch-size", type=int, default=32, help="objects per batch (default 32)")
    ap.add_argument("--workers", type=int, default=2, help="DataLoader worker processes (default 2; 0: none)")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of the weights, the train / validation split and the shuffling (default 0)")
    ap.add_argument("--min-quality", type=float, default=None,
                    help="train and validate only on objects whose quality is at least this (default: all)")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    torch.manual_seed(args.seed)
    export = Path(args.export) if args.export else ROOT / "outputs" / "train_example" / "export"
    if args.export and not any((export / name).is_file() for name in ("zarr.json", "index.json")):
        print(f"error: --export {export}: no export there (python -m carvi_torch.export makes one; without "
              "--export this example builds one from the embedded collection)", file=sys.stderr)
        return 2
    if not args.export and not (export / "zarr.json").is_file():  # the zarr store of python -m carvi_torch.export
        _build_export(export)  # only the default's: a given --export holds one (a zarr store or a format-1 export)
    ds = LiftedDataset(export, fields=["mask", "viewpoint", "class_index"], min_quality=args.min_quality)
    if len(ds) < 2:  # one object to train on and one to validate on, at least
        kept = f"--min-quality {args.min_quality} keeps {len(ds)} of {len(ds.reader.samples)}" \
            if args.min_quality is not None else f"it holds {len(ds)}"
        print(f"error: {export}: {kept} object(s); training needs at least 2 (one to train on, one to validate on)"
              + ("; lower --min-quality" if args.min_quality is not None else ""), file=sys.stderr)
        return 2
    n_val = max(1, len(ds) // 5)
    train, val = random_split(ds, [len(ds) - n_val, n_val], generator=torch.Generator().manual_seed(args.seed))
    kw = dict(batch_size=args.batch_size, num_workers=args.workers, collate_fn=collate_lifted)
    train_loader = DataLoader(train, shuffle=True, **kw)
    val_loader = DataLoader(val, **kw)
    net = ViewpointNet(len(ds.class_names))
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    print(f"{len(train)} training / {len(val)} validation objects, classes {ds.class_names}")
    print("epoch  train loss  val loss  val median azimuth error (deg)  seconds")
    for epoch in range(1, args.epochs + 1):
        t0 = time.perf_counter()
        train_loss = _train_epoch(net, opt, train_loader)
        val_loss, med = _validate(net, val_loader)
        secs = time.perf_counter() - t0
        print(f"{epoch:5d}  {train_loss:10.4f}  {val_loss:8.4f}  {med:30.1f}  {secs:7.1f}")
    return 0


def _build_export(export: Path) -> None:
    """Reconstruct the embedded collection beside ``export`` and export it there (child processes)."""
    recon = export.parent / "recon"
    print(f"no export at {export}: reconstructing the embedded collection into {recon}")
    subprocess.run([sys.executable, "-m", "carvi_torch.reconstruct", "--out", str(recon), "preview=false",
                    "report=false"],
                   check=True, cwd=ROOT)
    subprocess.run([sys.executable, "-m", "carvi_torch.export", "--recon", str(recon), "--out", str(export)],
                   check=True, cwd=ROOT)


def _train_epoch(net: ViewpointNet, opt, loader) -> float:
    """One pass over ``loader`` with Adam steps; the mean training loss per object."""
    net.train()
    total, count = 0.0, 0
    for batch in loader:
        pred = net(batch["mask"][:, None].float(), batch["class_index"])
        loss = F.mse_loss(pred, targets(batch))
        opt.zero_grad()
        loss.backward()
        opt.step()
        total += float(loss.detach()) * len(pred)
        count += len(pred)
    return total / count


def _validate(net: ViewpointNet, loader) -> tuple[float, float]:
    """The mean validation loss per object and the median azimuth error (degrees) over ``loader``."""
    net.eval()
    vtotal, vcount, errs = 0.0, 0, []
    with torch.no_grad():
        for batch in loader:
            pred = net(batch["mask"][:, None].float(), batch["class_index"])  # (B, 3)
            y = targets(batch)
            vtotal += float(F.mse_loss(pred, y)) * len(pred)
            vcount += len(pred)
            d = torch.atan2(pred[:, 1], pred[:, 0]) - torch.atan2(y[:, 1], y[:, 0])
            errs.append(torch.rad2deg(torch.atan2(torch.sin(d), torch.cos(d)).abs()))
    return vtotal / vcount, float(torch.cat(errs).median())


if __name__ == "__main__":
    sys.exit(main())
