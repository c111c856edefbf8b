"""Make input datasets (COCO keypoint JSON) for carvi_torch.

Subcommands::

    python -m carvi_torch.datasets synthetic --meshes DIR --out DIR [--views N] [--test-views N]
        [--seed S] [--image-size W H | --canvas S] [--keypoint-noise P] [--boundary-noise P]
    python -m carvi_torch.datasets procedural --out DIR [--instances N] [--views N] [--seed S] ...
    python -m carvi_torch.datasets voc --keypoints DIR [--masks DIR] --out annotations.json

``synthetic`` renders meshes with 3-D keypoints (PASCAL3D+ ``.npz``, or any trimesh mesh with
a ``.json`` of keypoints beside it) from random photograph-like cameras; ``procedural``
builds and renders the embedded procedural classes (the default data of
``python -m carvi_torch.reconstruct``); ``voc`` converts Berkeley keypoint XML files (and
VOC/SBD masks) through :mod:`carvi_torch.io.voc`. Each writes ``annotations.json`` (and,
for synthetic data, ``gt.json`` and ``meshes/``) into ``--out``. ``synthetic`` and ``procedural`` write only
into a new or empty folder, or over an earlier dataset of theirs, which they replace whole (its ``meshes/``
and ``images/`` are cleared first, so no file of the earlier models stays); any other ``--out`` is refused
before anything is written, and so is a ``--meshes`` inside ``--out`` (or the other way round). ``synthetic``
skips a model it cannot render (an unreadable file, a malformed keypoint file, no faces or no extent, no
keypoints, keypoints far off the mesh: :mod:`carvi_torch.synthetic.meshes`) with one ``warning:`` line naming
the file and renders the rest; only when no model is left is it an error.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import warnings
from pathlib import Path
from typing import Callable, Sequence

from .cli import (CommandError, add_common, nonempty_paths, nonneg_float, nonneg_int, positive_int, program,
                  run_command, split_classes, writable_file, writable_folder)
from .runtime import check_replaceable, folders_to_make, remove_empty

__all__ = ["build_parser", "main", "DATASET_NAMES"]

#: What ``synthetic`` and ``procedural`` write into ``--out`` (``images/``: the photographs a dataset may have).
DATASET_NAMES = frozenset({"annotations.json", "gt.json", "meshes", "images"})


def _add_render_options(p: argparse.ArgumentParser, views_default: int, views_help: str) -> None:
    p.add_argument("--views", type=positive_int, default=views_default, help=views_help)
    p.add_argument("--test-views", type=nonneg_int, default=0,
                   help="the first N renders of each model get split 'test', the others 'pool' (default 0)")
    p.add_argument("--seed", type=nonneg_int, default=0,
                   help="random seed, an integer >= 0; the same seed writes the same files (default 0)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--image-size", type=positive_int, nargs=2, metavar=("W", "H"), default=None,
                      help="image width and height in pixels (default 320 240)")
    size.add_argument("--canvas", type=positive_int, metavar="S", default=None,
                      help="square S x S renders instead of --image-size")
    p.add_argument("--keypoint-noise", type=nonneg_float, default=0.0, metavar="P",
                   help="standard deviation (pixels) of Gaussian noise on visible keypoints (default 0)")
    p.add_argument("--boundary-noise", type=nonneg_float, default=0.0, metavar="P",
                   help="standard deviation (pixels) of a smooth random displacement of the mask "
                        "boundary along its normal (default 0)")
    p.add_argument("--device", default="cpu",
                   help="torch device for rasterisation: cpu, cuda, cuda:N or auto (CUDA when available; default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


#: What ``synthetic``'s and ``procedural``'s ``--help`` say about ``--out``.
_OUT_RULE = ("--out must be a new or empty folder or an earlier dataset of 'synthetic' or 'procedural', which is "
             "replaced: its annotations.json and gt.json are rewritten and its meshes/ and images/ folders deleted "
             "first; any other --out is refused before anything is written.")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m carvi_torch.datasets``."""
    parser = argparse.ArgumentParser(
        prog=program("carvi_torch.datasets"),
        description="Make COCO keypoint datasets for carvi_torch: render meshes with keypoints, build the "
                    "embedded procedural classes, or convert PASCAL VOC keypoint annotations.")
    add_common(parser, classes=False, quiet=False)
    sub = parser.add_subparsers(dest="command", metavar="{synthetic,procedural,voc}")

    syn = sub.add_parser(
        "synthetic", help="render meshes with 3-D keypoints into masks + 2-D keypoints",
        description="Render every model of --meshes (PASCAL3D+ .npz files, or .ply/.obj/.off/.stl/.glb/.gltf "
                    "meshes with a .json of {'class', 'keypoints': {name: [x, y, z]}} beside them) from random "
                    "photograph-like scaled orthographic cameras. Writes OUT/annotations.json (COCO keypoints, "
                    "RLE masks), OUT/gt.json (true cameras) and OUT/meshes/<model>.ply. A model that cannot be "
                    "rendered (unreadable, no faces or extent, no keypoints, keypoints far off the mesh) is "
                    "skipped with a warning naming its file; exit status 2 when none can be. " + _OUT_RULE)
    syn.add_argument("--meshes", required=True, metavar="DIR", help="directory of models (outside --out)")
    syn.add_argument("--out", required=True, metavar="DIR",
                     help="output directory: new, empty, or an earlier dataset (replaced whole)")
    syn.add_argument("--sides", choices=("class", "as-given"), default="class",
                     help="left/right keypoint names: 'class' (default) renames a pair that one model names from "
                          "the other side than every other model of its class (a warning names it); 'as-given' "
                          "keeps the stored names")
    _add_render_options(syn, 30, "renders per model (default 30)")

    proc = sub.add_parser(
        "procedural", help="build and render the embedded procedural classes (car, aeroplane, chair, bottle)",
        description="Build --instances random instances of each procedural class (meshes from parts, with "
                    "keypoints) and render each --views times (default once: many instances, one photograph "
                    "each, like PASCAL VOC). Same outputs as 'synthetic'. " + _OUT_RULE)
    proc.add_argument("--out", required=True, metavar="DIR",
                      help="output directory: new, empty, or an earlier dataset (replaced whole)")
    proc.add_argument("--instances", type=positive_int, default=40, help="instances per class (default 40)")
    proc.add_argument("--classes", default=None, metavar="A,B",
                      help="comma-separated classes to build (default: aeroplane,bottle,car,chair)")
    _add_render_options(proc, 1, "renders per instance (default 1)")

    voc = sub.add_parser(
        "voc", help="convert Berkeley PASCAL VOC keypoint XML (and masks) to COCO keypoint JSON",
        description="Convert Berkeley keypoint annotations (voc2011_keypoints XML files with figure-ground "
                    "polygons) and optional VOC/SBD segmentation masks into one COCO keypoint JSON file "
                    "(delegates to carvi_torch.io.voc).")
    voc.add_argument("--keypoints", required=True, metavar="DIR", help="directory of keypoint XML files")
    voc.add_argument("--masks", default=None, metavar="DIR",
                     help="directory of VOC/SBD object segmentation masks (default: the XML polygons)")
    voc.add_argument("--annotations", default=None, metavar="DIR",
                     help="VOC Annotations/ directory (image sizes and occluded/truncated flags; optional)")
    voc.add_argument("--out", required=True, metavar="annotations.json", help="output JSON file")
    voc.add_argument("--classes", default=None, metavar="A,B",
                     help="comma-separated VOC classes to convert (default: every class)")
    return parser


def _image_size(args) -> tuple[int, int]:
    if args.canvas is not None:
        return (args.canvas, args.canvas)
    if args.image_size is not None:
        return tuple(args.image_size)
    from .synthetic.render import DEFAULT_IMAGE_SIZE

    return DEFAULT_IMAGE_SIZE


def _print_summary(summary: dict) -> None:
    print(f"wrote {summary['images']} renders of {summary['models']} models "
          f"({', '.join(summary['categories'])}) in {summary['seconds']:.1f} s")
    print(f"  {summary['annotations']}")
    print(f"  {summary['gt']}")


def _checked_device(text: str):
    """The ``torch.device`` of ``--device`` (:meth:`~carvi_torch.config.Config.resolve_device`'s: ``cpu``, ``cuda``,
    ``cuda:N`` or ``auto``), checked before any work: :class:`CommandError` in one line for a device that is none of
    these, a CUDA device on a machine without one, or a CUDA index beyond the machine's devices."""
    import torch

    from .config import Config, ConfigError

    try:
        dev = Config(device=text).resolve_device()
    except ConfigError:
        try:
            cuda = torch.device(text).type == "cuda"
        except RuntimeError:
            cuda = False
        why = ("this machine has no CUDA device (use --device cpu)" if cuda
               else "the renders run on cpu, cuda, cuda:N or auto")
        raise CommandError(f"--device {text!r}: {why}") from None
    count = torch.cuda.device_count() if dev.type == "cuda" else 0
    if dev.type == "cuda" and (dev.index or 0) >= count:
        raise CommandError(f"--device {text}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return dev


def _check_apart(meshes: str, out: str) -> None:
    """:class:`CommandError` when ``--meshes`` and ``--out`` overlap (after links): a dataset written into ``--out``
    replaces its ``meshes/`` and ``images/`` and writes files there, so models inside it would be lost, and an
    ``--out`` inside the folder of models would mix outputs with the inputs."""
    m, o = Path(meshes).resolve(), Path(out).resolve()
    if m == o:
        raise CommandError(f"--meshes {meshes} and --out {out} are the same folder; the dataset would replace the "
                           "models: choose another --out (nothing was written)")
    if o in m.parents:
        raise CommandError(f"--meshes {meshes} lies inside --out {out}, whose meshes/ and images/ a new dataset "
                           "replaces: keep the models elsewhere or choose another --out (nothing was written)")
    if m in o.parents:
        raise CommandError(f"--out {out} lies inside --meshes {meshes}: choose an --out outside the folder of "
                           "models (nothing was written)")


def _read_models(args) -> list:
    """The models of ``--meshes`` (:func:`~carvi_torch.synthetic.meshes.load_models`): each warning (a model skipped,
    a left/right pair renamed) printed as one ``warning:`` line; :class:`CommandError` when none can be used."""
    from .synthetic.meshes import load_models

    with warnings.catch_warnings(record=True) as caught:  # one "warning:" line each, not Python's form
        warnings.simplefilter("always", UserWarning)
        try:
            return load_models(args.meshes, sides=args.sides)
        except (FileNotFoundError, ValueError) as e:
            raise CommandError(str(e)) from None
        finally:
            for w in caught:  # every warning the loaders gave, as the command always showed them
                print(f"warning: {w.message}", file=sys.stderr)


def _synthetic_job(args) -> Callable[[], dict]:
    """Check ``synthetic``'s inputs and read its models (:class:`CommandError` on a user error); returns the
    render, which says each view left out (an empty mask) on a ``warning:`` line."""
    from .synthetic.render import render_dataset

    if args.test_views > args.views:
        raise CommandError(f"--test-views ({args.test_views}) exceeds --views ({args.views})")
    device = _checked_device(args.device)
    models = _read_models(args)
    sources = {m.name: m.source or m.name for m in models}

    def render() -> dict:
        summary = render_dataset(models, args.out, views=args.views, test_views=args.test_views, seed=args.seed,
                                 image_size=_image_size(args), keypoint_noise=args.keypoint_noise,
                                 boundary_noise=args.boundary_noise, progress=not args.quiet, device=device)
        for name, n in summary.get("empty_views", {}).items():
            print(f"warning: {sources[name]}: {n} of {args.views} views show no pixel of the mesh (seen edge-on?); "
                  "left out", file=sys.stderr)
        if not summary["images"]:
            raise CommandError(f"no view of any model shows a pixel of it; {args.out} holds no annotation")
        return summary

    return render


def _procedural_job(args) -> Callable[[], dict]:
    """Check ``procedural``'s inputs (:class:`CommandError` on a user error); returns the build and render."""
    from .synthetic.procedural import CATEGORIES, write_default_collection

    if args.test_views > args.views:
        raise CommandError(f"--test-views ({args.test_views}) exceeds --views ({args.views})")
    classes = split_classes(args.classes)
    if classes is not None:
        bad = [c for c in classes if c not in CATEGORIES]
        if bad:
            raise CommandError(f"unknown classes {bad}; choose from {list(CATEGORIES)}")
    device = _checked_device(args.device)
    return lambda: write_default_collection(args.out, instances_per_class=args.instances,
                                            views_per_instance=args.views, seed=args.seed, categories=classes,
                                            image_size=_image_size(args), test_views=args.test_views,
                                            keypoint_noise=args.keypoint_noise, boundary_noise=args.boundary_noise,
                                            progress=not args.quiet, device=device)


def _run_voc(args) -> int:
    from .io import voc

    return voc.run(args)


def _not_dataset(out: Path) -> list[str]:
    """The entries of the folder ``out`` that no dataset of ``synthetic``/``procedural`` holds (the temporary
    files of an interrupted write of one of its files excepted)."""
    def ours(name: str) -> bool:
        return name in DATASET_NAMES or any(name.startswith(f".{n}.") and name.endswith(".tmp") for n in DATASET_NAMES)

    return [p.name for p in out.iterdir() if not ours(p.name)]


def _clear_earlier(out: Path) -> None:
    """Remove an earlier dataset's completeness marker (``annotations.json``) and its folders of files, so that
    the new dataset holds only its own files."""
    (out / "annotations.json").unlink(missing_ok=True)
    for name in ("meshes", "images"):
        d = out / name
        if d.is_symlink() or d.is_file():
            d.unlink()
        elif d.is_dir():
            shutil.rmtree(d)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (0 success; 2 bad arguments or input, or an ``--out`` that cannot be
    written: one ``error:`` line, ``--out`` and then the inputs checked before the work, and the folders made
    for ``--out`` removed again on a user error in the inputs; 130 interrupted by Ctrl-C). ``synthetic`` skips
    each model it cannot render with a ``warning:`` line naming the file and renders the rest: exit status 2
    only when no model is left."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.error("choose what to make: synthetic, procedural or voc (each has --help)")
    jobs = {"synthetic": _synthetic_job, "procedural": _procedural_job}

    def body() -> int:
        nonempty_paths(args, "--meshes", "--keypoints", "--masks", "--annotations", "--out")
        if args.command == "voc":
            writable_file(args.out)
            return int(_run_voc(args) or 0)
        out = Path(args.out)
        check_replaceable(out, _not_dataset, "an earlier synthetic or procedural dataset", CommandError)
        if args.command == "synthetic":
            _check_apart(args.meshes, args.out)
        made = folders_to_make(out)
        writable_folder(out)
        try:
            job = jobs[args.command](args)
        except BaseException:  # a user error in the inputs (or Ctrl-C) before any work: remove what was made
            remove_empty(made)
            raise
        _clear_earlier(out)
        _print_summary(job())
        return 0

    return run_command(body, f"interrupted; {args.out} is incomplete, run the command again")


if __name__ == "__main__":
    sys.exit(main())
