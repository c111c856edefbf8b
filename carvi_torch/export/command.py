"""``python -m carvi_torch.export``: the command line of the export.

This module imports nothing heavy: it parses the arguments and, when worker processes will be
used, starts the forkserver they fork from (which imports :data:`WORKER_MODULE` once) *before*
the main process imports torch, zarr and the rest of :mod:`carvi_torch.export.run`, so that the
two imports run side by side on two cores rather than one after the other.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import sys

from ..cli import CommandError, add_common, nonempty_paths, program, run_command, split_classes
from .settings import settings_problem

__all__ = ["main", "parser", "start_worker_server", "WORKER_MODULE"]

#: The module the export's worker processes run (imported once, by the forkserver).
WORKER_MODULE = "carvi_torch.export.objects"
#: The options that only the zarr store takes (option, argparse dest): ``--format cmr`` / ``ucmr`` name them in a
#: warning and go on without them.
ZARR_ONLY = (("--resolution", "resolution"), ("--points", "points"), ("--shard-size", "shard_size"),
             ("--mesh", "mesh"), ("--workers", "workers"), ("--seed", "seed"))


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=program("carvi_torch.export"),
                                 description="Export a reconstruction directory as a zarr v3 store for PyTorch "
                                             "training (read it with carvi_torch.training.LiftedDataset; layout in "
                                             "docs/export.md), or as CMR / U-CMR annotation files.")
    ap.add_argument("--recon", required=True, help="output directory of carvi_torch.reconstruct")
    ap.add_argument("--out", required=True,
                    help="folder to write: the zarr store, or the .mat / .json files of --format cmr / ucmr")
    ap.add_argument("--format", choices=["zarr", "cmr", "ucmr"], default="zarr",
                    help="zarr: the training store (default); cmr: one .mat per class; ucmr: one .json per class")
    ap.add_argument("--resolution", type=int, default=32, help="zarr: occupancy grid side (default 32)")
    ap.add_argument("--points", type=int, default=2048, help="zarr: surface points per object (default 2048)")
    ap.add_argument("--shard-size", type=int, default=256, help="zarr: samples per shard file (default 256)")
    ap.add_argument("--mesh", action="store_true",
                    help="zarr: also store every mesh (ragged mesh_vertices, mesh_faces)")
    ap.add_argument("--workers", type=int, default=None, help="zarr: worker processes (default: one per core; 0: none)")
    ap.add_argument("--seed", type=int, default=0, help="zarr: seed of the surface sampling (default 0)")
    add_common(ap)
    return ap


def start_worker_server() -> bool:
    """Start the forkserver now, preloading :data:`WORKER_MODULE` (True), where the platform has one
    (False elsewhere: workers are spawned later). A forkserver already running is left as it is."""
    if "forkserver" not in mp.get_all_start_methods():
        return False
    from multiprocessing import forkserver

    mp.get_context("forkserver").set_forkserver_preload([WORKER_MODULE])
    forkserver.ensure_running()
    return True


def main(argv=None) -> int:
    """Exit status: 0 exported; 2 a user error (a setting out of range included), an output that cannot be
    written, or a run none of whose objects could be exported (one ``error:`` line, ``--out`` as it was); 130
    interrupted by Ctrl-C (one line, ``--out`` as it was for the zarr store, or complete when Ctrl-C came
    while the finished store was swapped in, which the line says)."""
    args = parser().parse_args(argv)
    if args.format == "zarr":
        interrupted = f"interrupted; {args.out} is as it was before the export"
    else:
        interrupted = f"interrupted; the {args.format} files in {args.out} are each complete, rerun for the rest"
    return run_command(lambda: _main(args), interrupted)


def _main(args) -> int:
    nonempty_paths(args, "--recon", "--out")
    problem = settings_problem(args.resolution, args.points, args.shard_size, args.seed, args.workers)
    if problem is not None:  # before anything is started or written
        raise CommandError(f"{problem} (nothing was written)")
    if args.format == "zarr" and args.workers != 0:
        start_worker_server()
    from .run import export  # torch, zarr, ...: imported while the forkserver imports the worker module
    from .store import InterruptedAfterSwap

    try:
        if args.format != "zarr":
            from .formats import export_format

            done = export_format(args.recon, args.out, args.format, classes=split_classes(args.classes),
                                 progress=not args.quiet)
            print(f"wrote {len(done['files'])} {args.format} file(s) of {done['objects']} object(s) to {args.out}; "
                  f"skipped {len(done['skipped'])}")
            _ignored(args)
            return 0
        idx = export(args.recon, args.out, args.resolution, args.points, args.shard_size, args.seed,
                     progress=not args.quiet, classes=split_classes(args.classes), workers=args.workers,
                     mesh=args.mesh)
    except ValueError as e:  # a missing or unusable input: one line (an OSError is run_command's)
        print(f"error: {e}", file=sys.stderr)
        return 2
    except InterruptedAfterSwap as e:  # Ctrl-C while the finished store was swapped in: it is there, complete
        _exported(args, e.result)
        print(f"interrupted after the export finished; {args.out} holds the new store, complete", file=sys.stderr)
        return 130
    _exported(args, idx)
    return 0


def _ignored(args) -> None:
    """One warning line naming the zarr store's options that a CMR / U-CMR export was given and went without."""
    given = [opt for opt, dest in ZARR_ONLY if getattr(args, dest) != parser().get_default(dest)]
    if given:
        print(f"warning: {', '.join(given)}: for --format zarr only, ignored: --format {args.format} writes the "
              "cameras and mean shape alone", file=sys.stderr)


def _exported(args, idx: dict) -> None:
    print(f"exported {len(idx['samples'])} objects of {len(idx['classes'])} class(es) to {args.out} "
          f"({idx['seconds']:.1f} s); skipped {len(idx['skipped'])}")


if __name__ == "__main__":
    sys.exit(main())
