"""Run configuration: nested dataclasses, one per stage, one docstring per field.

A run's settings are the dataclass defaults, then a ``--config FILE`` (YAML, nested by
section or flat), then ``key=value`` overrides on the command line. The resolved
configuration is written next to the outputs as ``config.yaml``; ``configs/default.yaml``
is the defaults rendered the same way, for users to copy (a test keeps it equal to them).

Keys. Every setting has a full dotted name, ``<section>.<field>`` (``carve.resolution``),
or its bare name for the run-wide fields (``seed``). Shorter spellings are accepted where
they name one setting: the field alone (``resolution``) and ``<section>_<field>``
(``carve_backend``, ``mesh_format``). Enumerated settings take their values from the
``Literal`` types of the modules that own them.

Values. On the command line a text setting (``out``, ``data``, ``device``, ...) takes the text after ``=`` as
typed (``out=007`` is the folder ``007``; quotes around the whole value are removed: ``data='null'``); a list
(``classes``) takes ``a,b`` or ``[a, b]``; ``null`` or nothing unsets a setting that may be unset (``data=null``).
A YAML file's values are YAML's, but a text setting refuses a boolean, list or mapping (quote it) and takes a
number as it was written (``out: 1.50``). Integers are read in decimal everywhere (``seed=010`` is 10, not YAML
1.1's octal 8); booleans are ``true/false``, ``yes/no``, ``on/off`` or ``1/0``. A file that gives a key twice,
or one setting under two names, or a key that is not text (``on:``, ``123:``), is refused.

Example:
    >>> cfg = Config().override(["resolution=32", "imprint=false", "carve.backend=torch"])
    >>> cfg.carve.resolution, cfg.carve.imprint, cfg.carve.backend
    (32, False, 'torch')
    >>> resolve_key("mesh_format")
    'mesh.format'
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
import sys
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path, PurePath
from typing import Any, Literal, Optional

import yaml

from .carve import Backend, Interpolation
from .io.outputs import read_text
from .marching import Mesher
from .mesh import MeshFormat
from .viewpoints import CameraSource
from .viewpoints.choice import CameraKeep
from .viewpoints.frame import FrameChoice
from .viewpoints.sfm import PolishMethod

__all__ = ["Config", "ConfigError", "load_config", "read_run_config", "settings_changed", "object_settings",
           "flatten_settings", "NEUTRAL_SETTINGS", "resolve_key", "all_keys", "FIELD_DOCS", "override_text",
           "NULL_WORDS", "InputConfig", "ViewpointConfig", "SurrogateConfig", "CarveConfig", "SelectConfig",
           "MeshConfig", "StudyConfig", "Stage", "Executor"]

#: ``all`` runs every stage; ``cameras`` stops after viewpoint estimation.
Stage = Literal["all", "cameras"]
#: Who runs the classes: ``local`` (this process and its writer processes) or ``ray`` (tasks on a Ray
#: cluster, ``carvi_torch.executors.ray``).
Executor = Literal["local", "ray"]


class ConfigError(ValueError):
    """A configuration file or override is invalid (names the key and the problem)."""


def _positive(section, *names: str) -> None:
    for name in names:
        if getattr(section, name) < 1:
            raise ConfigError(f"{name} must be >= 1, got {getattr(section, name)}")


def _within(value: float, lo: float, hi: float, name: str, lo_open=False, hi_open=False, note: str = "") -> None:
    ok = (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        interval = f"{'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
        raise ConfigError(f"{name} must be in {interval}{note}, got {value}")


@dataclass
class InputConfig:
    """How annotations become canvas tensors (and the embedded default collection)."""

    procedural_instances: int = 40
    """Instances per class of the embedded procedural collection (used when ``data`` is unset)."""
    canvas_size: int = 128
    """Side (pixels) of the square canvas every instance is cropped and scaled into."""
    canvas_margin: float = 0.1
    """Fraction of the canvas left empty on each side of the object's bounding box."""
    min_instances: int = 3
    """Classes with fewer usable instances are reported and skipped."""
    max_image_pixels: int = 200_000_000
    """Objects whose image has more pixels are skipped with their reason (a mask is decoded at one byte
    per pixel of its image)."""

    def validate(self) -> None:
        _positive(self, "procedural_instances", "min_instances", "max_image_pixels")
        _within(self.canvas_size, 16, 1024, "canvas_size", note=" (memory grows with its square per object)")
        _within(self.canvas_margin, 0, 0.5, "canvas_margin", hi_open=True)


#: Where the viewpoint stage runs (``viewpoints.device``).
ViewpointDevice = Literal["auto", "run", "cpu"]


@dataclass
class ViewpointConfig:
    """Rigid SfM (``carvi_torch.viewpoints.sfm``), its mixture of shapes and the silhouette refinement."""

    device: ViewpointDevice = "auto"
    """Where the viewpoint stage (SfM, the mixture of shapes, refinement, cameras for unseen images) runs:
    ``run`` on the run's ``device``; ``cpu`` on the CPU, its result then moved to the run's device (the
    canonical frame stays on the host, as in every run); ``auto`` the CPU for a class of fewer than
    ``gpu_min_objects`` objects when the run is on a GPU, else the run's device. On CUDA a small class's stage
    is hundreds of small steps of a few kernel launches each: on an H100 four 8-view CAD classes of 32-48
    objects took 108 s there against 6.3 s on 4 threads of the same machine's CPU, run side by side
    (docs/viewpoints.md, *CPU and CUDA*). ``summary.json`` names the device each class used
    (``viewpoint_device``). ``viewpoint_processes`` above 0 implies ``cpu``."""
    gpu_min_objects: int = 1000
    """``device=auto`` on a GPU run: a class of at least this many objects makes its viewpoints on the GPU, a
    smaller one on the CPU, with the run's torch threads (one in a CUDA run, beside the writers). Where the
    two meet, estimated from measured parts: SfM and refinement of 1,000 cars took 3.8 s on an H100 and of
    9,087 5.9 s; on one CPU thread 2,000 instances take 4.2 s on the 2-core development host, whose cores
    run the viewpoint stage 2.4x as fast as the GPU hosts' (docs/viewpoints.md), so about 2 s per 1,000 there
    and 5 s on a GPU host's core."""
    sfm_max_outer: int = 200
    """Outer (fill) iterations of the missing-data factorisation at most."""
    sfm_inner: int = 10
    """Inner (camera / shape) alternations per outer iteration."""
    sfm_native: bool = True
    """On the CPU, run the factorisation's outer loop, the joint bundle adjustment and the mixture's keypoint-only
    camera fits in compiled kernels (``carvi_torch/kernels/sfm_steps.h``, ``bundle_steps.h``, ``camera_steps.h``,
    built with the fused carving's on the first run, about 14 s; the same steps as the torch operators, equal to
    rounding): SfM with the mixture of shapes' fit, where small classes spend their time, takes about a seventh of
    the time, the many-class run 0.254x (docs/benchmarks.md, *Many classes*). ``false``, a GPU or no compiler:
    torch operators only."""
    sfm_tol: float = 1e-7
    """Stop when the relative change of the visible-entry residual falls below this."""
    sfm_polish_iters: int = 100
    """Bundle-polish rounds after the factorisation at most (``carvi_torch.viewpoints.sfm``; 0 = none); the
    polish also stops at ``sfm_tol``. Shape groups' SfM runs (the mixture's hard EM) take this too. With the
    joint polish a round is one damped Levenberg-Marquardt solve: most CAD classes at 8 views settle in
    4-25, the real VOC aeroplanes in about 40; bottle (rotationally symmetric) stops at the cap, sofa and
    train at some seeds. The
    alternation (``sfm_polish=alternate``) crawls: at 30 rounds most CAD classes at 8 views stop before their
    residual settles (boat: 0.1% lower every round), run to its end it needs about 300
    (docs/viewpoints.md, *Where a run's numbers move between machines*)."""
    sfm_polish: PolishMethod = "joint"
    """How the bundle polish minimises the visible-keypoint residual after the factorisation
    (``carvi_torch.viewpoints.sfm.bundle_polish``): ``joint`` (Levenberg-Marquardt over every camera and the
    shape at once, the cameras eliminated by the Schur complement: ``carvi_torch.viewpoints.bundle``) or
    ``alternate`` (every camera's fit to the shape, then the shape's exact solve, in turn). Shape groups' SfM
    runs take this too. ``joint`` settles where the alternation stops at its caps (boat within 12 degrees
    at every seed of the 8-view CAD renders; summed medians 233.8 -> 202.8 with four groups of at least 10,
    196.2 with this config's defaults, against the alternation's 30 rounds and the mixture's three larger
    groups) in 1.03x the many-class run's time. With one shape for a class whose models differ in
    proportions its settled cameras absorb the difference (CAD sofas at 30 views 17.3 degrees against 9.5);
    docs/viewpoints.md, *The joint bundle adjustment*."""
    sfm_template_start: bool = True
    """Also start the class's SfM from its template of 3-D keypoints (the category's ``keypoints_3d``, else the
    shipped PASCAL3D+ one of its name; ``viewpoints.frame``) and keep that solution when it places as many
    objects with a visible-keypoint RMS residual lower by more than ``viewpoints.TEMPLATE_START_MARGIN``
    (25%). Classes without a template and rotationally symmetric ones run one SfM."""
    sfm_groups: int = 4
    """Most rigid shapes per class (``carvi_torch.viewpoints.mixture``). A class whose members differ in
    proportions is split into groups, each with its own SfM shape, in one class frame, when one shape
    misfits it (``sfm_group_misfit``) and the split passes ``sfm_group_gain``, ``sfm_group_agreement_deg``
    and ``sfm_group_hull_gain``; every other class keeps one shape, bit for bit. 1 = one mean shape per
    class, as in the paper. Up to four groups of at least ``sfm_group_min`` (10) objects put the 8-view CAD
    sofas at 5.6 / 3.7 / 4.2 degrees over three render seeds (``sfm_groups=3 sfm_group_min=15
    sfm_group_gain=0.3``, 30 solves and the EM's two starts: 8.5 / 9.4 / 10.1; docs/viewpoints.md, *Small
    classes*)."""
    sfm_group_misfit: float = 0.025
    """The mixture is only fitted when the one-shape SfM misfits the class: the median over the objects of
    the keypoint RMS residual over the diagonal of the mask's box is at least this (0 = always fit). A gate
    of cost only: whether a split is kept is ``sfm_group_hull_gain``'s and the others' decision. On the
    8-view CAD renders the buses sit at 0.028-0.031 and keep a split wherever it is fitted (with the
    alternation's settings seed 1: 9.8 -> 3.8 degrees, seed 2: 8.1 -> 6.3); at 0.03 they were left on one
    shape there (docs/viewpoints.md)."""
    sfm_group_hull_gain: float = 0.01
    """A split into ``k`` groups is only kept when every usable start of that ``k`` raises the median
    agreement (IoU) of the masks with the convex hull of the projected group shape, under the SfM cameras,
    by at least this over one shape (a silhouette test the keypoint-only fit does not optimise); -1 = no
    such test."""
    sfm_group_min: int = 10
    """Fewest objects per shape group (a class with fewer than twice this keeps one shape)."""
    sfm_group_gain: float = 0.25
    """A split into one more group is kept when it cuts the keypoint residual by more than this fraction."""
    sfm_group_agreement_deg: float = 60.0
    """A split is only considered when its groups' frames agree within this many degrees (median over
    the objects; no ground truth)."""
    sfm_group_rounds: int = 12
    """Most hard-EM rounds per candidate split (the EM stops sooner once its groups settle). With 6 the
    8-view CAD sofas' four groups depended on the float path's rounding (shape error 6.3 against 11.1%
    at one render seed); with 12 every float path measured reaches the same groups (docs/viewpoints.md,
    *A mixture of rigid shapes*)."""
    sfm_group_threads: int = 2
    """Python threads that run the initialisations of each candidate split side by side, for
    classes of at least ``viewpoints.mixture.THREADS_MIN_OBJECTS`` objects (1: one after the other;
    same result either way)."""
    refine: bool = True
    """Silhouette refinement of the SfM cameras (``False`` = the -CRef ablation)."""
    refine_iters: int = 150
    """Refinement steps at most."""
    refine_keep: CameraKeep = "class"
    """Which camera an object with an SfM camera keeps (``carvi_torch.viewpoints.choice``). A refined camera is
    suspect when it raised the keypoint error by more than 1% of the mask's box diagonal while raising the
    agreement of the mask with the projected mean shape's hull by less than 0.05. ``class``: the whole class
    keeps its SfM cameras when more than a third of its refined cameras are suspect; ``objects``: every suspect
    object keeps its SfM camera; ``refined``: always the refined one (the paper's). With ``class`` and
    ``objects`` a tilted refined camera (``refine_max_tilt_deg``) keeps its SfM camera too. ``cameras.json``
    says which (``camera_choice``)."""
    refine_max_tilt_deg: float = 45.0
    """An object keeps its SfM camera when its refined camera shows the class's up direction (the direction
    most perpendicular to the SfM cameras' image x axes: photographs are taken level) tilted in the image by
    more than this many degrees and by 20 more than the SfM camera does (``refine_keep`` ``class`` or
    ``objects``; ``carvi_torch.viewpoints.choice``). 180 = off."""
    silhouette_weight: float = 1.0
    """Weight of the distance-to-mask penalty against the keypoint reprojection error."""
    silhouette_robust: float = 0.2
    """Robust (Geman-McClure) scale of the distance-to-mask penalty, a fraction of each mask's larger
    side; 0 = the paper's squared distance."""
    refine_twin_flatness: float = 0.1
    """Also refine a camera from its planar twin (the other camera under which the plane of its visible
    keypoints looks the same) when those keypoints are this flat (thickness: smallest over middle
    spread; 1 = every camera, 0 = off); the twin's result is kept when its energy is at least 2% lower
    (``viewpoints.camera_fit.TWIN_MARGIN``), or lower by less and the convex hull of the projected mean shape
    agrees better with the mask by more than 0.05 IoU (``viewpoints.camera_fit.twin_wins``). The flat
    instances are refined twice."""
    frame: FrameChoice = "best"
    """The canonical object frame the outputs are written in (``carvi_torch.viewpoints.frame``): ``best`` (a
    template of 3-D keypoints when one fits: the category's ``keypoints_3d`` or the shipped PASCAL3D+ ones;
    else ``symmetry+up``; else the SfM frame), ``template``, ``symmetry+up`` or ``sfm``."""
    refine_min_support: float = 0.1
    """Leave out of the refinement (and of the unseen-image path) every mean-shape keypoint shown by
    fewer than this fraction of the instances refined with that shape (the class, or its shape group):
    placed by SfM from too few views, it would pull every instance's camera through the silhouette term
    (``viewpoints.camera_fit.supported_shape``; 0 = use every keypoint)."""

    def validate(self) -> None:
        _positive(self, "refine_iters", "sfm_max_outer", "sfm_inner", "sfm_groups", "sfm_group_min",
                  "sfm_group_rounds", "sfm_group_threads")
        if self.sfm_polish_iters < 0:
            raise ConfigError(f"sfm_polish_iters must be >= 0 (0 = no polish), got {self.sfm_polish_iters}")
        if self.gpu_min_objects < 0:
            raise ConfigError(f"gpu_min_objects must be >= 0 (0 = every class on the GPU), got {self.gpu_min_objects}")
        if not self.refine_twin_flatness >= 0:
            raise ConfigError(f"refine_twin_flatness must be >= 0 (0 = off), got {self.refine_twin_flatness}")
        _within(self.refine_min_support, 0, 1, "refine_min_support", note=" (0 = every keypoint)")
        _within(self.refine_max_tilt_deg, 0, 180, "refine_max_tilt_deg", note=" (180 = off)")
        if self.silhouette_robust < 0:
            raise ConfigError(f"silhouette_robust must be >= 0 (0 = squared distance), got {self.silhouette_robust}")
        if self.silhouette_weight < 0:
            raise ConfigError(f"silhouette_weight must be >= 0 (0 = keypoints only), got {self.silhouette_weight}")
        _within(self.sfm_group_gain, 0, 1, "sfm_group_gain", hi_open=True)
        _within(self.sfm_group_agreement_deg, 0, 180, "sfm_group_agreement_deg", lo_open=True)
        _within(self.sfm_group_misfit, 0, 1, "sfm_group_misfit", note=" (0 = always fit the mixture)")
        _within(self.sfm_group_hull_gain, -1, 1, "sfm_group_hull_gain", note=" (-1 = no hull test)")


@dataclass
class SurrogateConfig:
    """Principal directions, clusters and the surrogate triplets of every reference."""

    mirrors: bool = True
    """Carve with the mirrored copies' silhouettes too (bilateral symmetry; articulated classes never
    do). SfM always uses the mirrored copies."""
    cluster_threshold_deg: float = 15.0
    """An instance joins a principal direction's cluster within this angle (front or back; at most 45)."""
    cluster_widen_step_deg: float = 5.0
    """Widen the threshold by this while the second-smallest cluster has too few members."""
    cluster_max_threshold_deg: float = 45.0
    """Never widen beyond this (at most 45)."""
    cluster_count_objects: bool = True
    """Count a cluster's distinct physical objects (``object_id``), not its members, when deciding to widen:
    views of one object alone would give every reference the same surrogate shape."""
    proposals: int = 20
    """Triplets (reconstruction proposals) sampled per reference instance."""
    symmetric_step_deg: float = 90.0
    """Rotationally symmetric classes: synthesise surrogate views every this many degrees."""
    symmetric_axis_in_image: bool = True
    """Rotationally symmetric classes: assume each photo sees the symmetry axis in its image plane."""
    symmetric_axis_through_silhouette: bool = True
    """Rotationally symmetric classes: the rotation axis passes through the centroid of each reference's
    silhouette (``False``: through the class mean shape's centroid, wherever the camera projects it)."""

    def validate(self) -> None:
        _positive(self, "proposals")
        _within(self.cluster_threshold_deg, 0, 45, "cluster_threshold_deg", lo_open=True,
                note=" (an instance is then near one principal direction at most)")
        if not self.cluster_widen_step_deg > 0:
            raise ConfigError(f"cluster_widen_step_deg must be > 0, got {self.cluster_widen_step_deg}")
        _within(self.cluster_max_threshold_deg, self.cluster_threshold_deg, 45, "cluster_max_threshold_deg",
                note=" (from cluster_threshold_deg to 45)")
        _within(self.symmetric_step_deg, 0, 360, "symmetric_step_deg", lo_open=True, hi_open=True)


@dataclass
class CarveConfig:
    """The imprinted visual hull of every proposal (``carvi_torch.carve``)."""

    resolution: int = 60
    """Voxel grid steps per axis."""
    imprint: bool = True
    """Imprint the reference silhouette (``False`` = the -SImp ablation)."""
    interpolation: Interpolation = "bilinear"
    """How the carving reads the distance maps at a voxel's projection: ``bilinear`` (the paper's) or
    ``nearest`` (the pixel it falls in, an approximation; it has no native kernel, so on the CPU it is
    slower than the default; docs/benchmarks.md)."""
    backend: Backend = "auto"
    """Who computes the carving's labels: ``auto`` (the native CPU kernel of ``carvi_torch.carve.native``
    where it applies -- CPU, bilinear -- and builds, else torch), ``torch`` (batched ``grid_sample``) or
    ``fused`` (the native kernel, an error where it cannot run). Every backend gives the same labels
    voxel for voxel; the kernel is about 2.3x faster on the CPU (docs/benchmarks.md)."""

    def validate(self) -> None:
        _within(self.resolution, 4, 2048, "resolution", note=" (the carving's bound)")


@dataclass
class SelectConfig:
    """Scoring the proposals against the class's average silhouettes."""

    plane_size: int = 64
    """Resolution of the average masks / proposal projections used for selection."""
    balance_objects: bool = True
    """Weight every member of a principal direction's average mask by 1 / (its physical object's views in
    that cluster, ``carvi_torch.surrogates.object_share``), so that each physical object (``object_id``)
    counts once however often it was photographed (``False``: every member counts once, the paper's
    average). Without repeated ``object_id`` (e.g. one annotation per object) nothing changes."""
    consensus: int = 5
    """The selected shape is the voxel-wise majority vote of this many best-ranked proposals
    (``carvi_torch.select.vote_proposals``); 1: the best proposal alone (the paper's)."""

    def validate(self) -> None:
        _within(self.plane_size, 2, 1024, "plane_size", note=" (memory grows with its square per proposal)")
        _positive(self, "consensus")


@dataclass
class MeshConfig:
    """Meshes of the selected proposals."""

    format: MeshFormat = "ply"
    """Mesh file format (``carvi_torch.mesh.MESH_FORMATS``)."""
    largest_component: bool = False
    """Keep only the largest connected component of the selected occupancy."""
    mesher: Mesher = "auto"
    """Marching cubes: ``skimage`` (scikit-image, one object at a time in the writer processes), ``torch``
    (``carvi_torch.marching``: batched, in the run's process on its device; the same meshes within 1e-5 voxel),
    or ``auto``: ``torch`` on CUDA, ``skimage`` elsewhere."""

    def validate(self) -> None:
        pass


@dataclass
class StudyConfig:
    """Settings for studies and benchmarks (``tools/``), not for producing a dataset."""

    cameras: CameraSource = "estimate"
    """``estimate`` (SfM + refinement) or ``gt``: take the true cameras of ``gt.json`` (oracle study)."""
    keep_all_scores: bool = False
    """Write the score of every proposal to ``<class>/proposal_scores.json`` (ranking studies)."""
    save_proposals: bool = False
    """Also write every proposal's occupancy (``<class>/proposals/<id>.npz``, bit-packed)."""

    def validate(self) -> None:
        pass


#: The sections of :class:`Config`, in order.
SECTIONS = ("input", "viewpoints", "surrogates", "carve", "select", "mesh", "study")


@dataclass
class Config:
    """Every knob of a reconstruction run: run-wide fields, then one section per stage."""

    data: Optional[str] = None
    """COCO keypoint JSON to reconstruct. ``None``: the embedded procedural collection."""
    gt: Optional[str] = None
    """Ground-truth ``gt.json`` (synthetic data). Default: ``gt.json`` beside ``data`` when present."""
    out: str = "outputs/default"
    """Output directory (``config.yaml``, ``summary.json``, per class ``cameras.json``, meshes, voxels)."""
    classes: Optional[list] = None
    """Restrict the run to these class names (``None``: all classes in the data)."""
    references: str = "all"
    """Objects to reconstruct: ``all``, or only those of one split (e.g. ``test``); every object still
    takes part in SfM and may serve as a surrogate."""
    overwrite: bool = False
    """Recompute objects whose outputs already exist (default: a rerun skips finished work)."""
    seed: int = 0
    """Seed of every random choice (surrogate sampling, synthetic data). Same seed, same outputs."""
    device: str = "cpu"
    """Torch device for all stages: ``cpu``, ``cuda``, ``cuda:1`` or ``auto`` (CUDA when available)."""
    stage: Stage = "all"
    """``all`` runs the whole pipeline; ``cameras`` stops after viewpoint estimation."""
    progress: bool = True
    """Show progress bars."""
    preview: bool = True
    """Write ``preview.png`` with a few results."""
    report: bool = True
    """Write the HTML report (``report/index.html``: every object's overlay and 3D mesh, per-class plots;
    ``python -m carvi_torch.report`` makes it for any finished run)."""
    executor: Executor = "local"
    """Who runs the classes: ``local`` (this process, meshes written by processes beside it) or ``ray``
    (each class's viewpoints one task, its objects tasks of ``ray_chunk_objects``, on a Ray cluster;
    ``pip install 'carvi_torch[ray]'``; docs/distributed.md). Same seed, same outputs on either."""
    ray_address: Optional[str] = None
    """``executor=ray``: the cluster to run on, ``auto`` (the one started on this machine by ``ray start``,
    or ``RAY_ADDRESS``) or ``host:port`` of its head; ``None``: start a Ray on this machine for the run."""
    ray_chunk_objects: int = 16
    """``executor=ray``: objects carved, meshed and written per task (each task reads its class plan,
    about 0.22 MB per object of the class at the default canvas, from the object store: larger classes
    want larger chunks)."""
    pipeline_classes: bool = True
    """``executor=local`` on the CPU: make the next class's viewpoints (SfM, the mixture of shapes, refinement,
    the surrogate plan) on a background thread while this class carves, selects and writes, so that the
    second core works during those single-threaded stages (one class's viewpoints more in memory; the
    same outputs; docs/benchmarks.md, *Many classes*). A CUDA run keeps its classes one after the other (the
    pipeline is unmeasured on a GPU), but for ``viewpoint_processes``. ``False``: each class's stages one after
    the other. ``viewpoint_processes`` above 0 takes its place."""
    viewpoint_processes: int = 0
    """``executor=local``: worker processes that make the classes' viewpoint stages (SfM, the mixture of shapes,
    refinement) ahead, several classes at once, on the CPU (as ``viewpoints.device=cpu``), each with the run's
    torch thread count; the run takes them in class order, moves them to its device and goes on with carving.
    At most this many classes wait beyond the one in progress; each process imports torch (a few hundred MB)
    and uses the run's thread count, beside the run's own threads. 0: none (the stage in the run's process; on the
    CPU one class ahead on a thread, ``pipeline_classes``). For machines with many cores and many classes,
    above all CUDA runs: a small class's viewpoint stage is slower on a GPU than on one CPU core
    (docs/benchmarks.md, *Many classes*). The same cameras as the run's own process on the CPU; on CUDA those of
    ``viewpoints.device=cpu``. ``executor=ray`` runs each class's viewpoints as a task already."""
    input: InputConfig = field(default_factory=InputConfig)
    viewpoints: ViewpointConfig = field(default_factory=ViewpointConfig)
    surrogates: SurrogateConfig = field(default_factory=SurrogateConfig)
    carve: CarveConfig = field(default_factory=CarveConfig)
    select: SelectConfig = field(default_factory=SelectConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    study: StudyConfig = field(default_factory=StudyConfig)

    # ------------------------------------------------------------------ helpers
    def override(self, items: list[str] | dict[str, Any]) -> "Config":
        """Return a copy with ``key=value`` strings (or a mapping, flat or nested by section) applied. A string's
        value is read by its setting's type (:func:`_typed`; of two strings for one setting the last wins); a
        mapping's values are YAML's or Python's, and a mapping that names one setting twice is refused."""
        values, named = self.flat(), {}
        typed = not isinstance(items, dict)
        for key, value in _pairs(items):
            _not_a_section(key, value)
            dotted = resolve_key(key)
            if not typed and dotted in named:
                raise ConfigError(f"{dotted} is given twice ({named[dotted]!r} and {key!r}); keep one")
            named[dotted] = key
            annotation = _ANNOTATIONS[dotted]
            values[dotted] = _coerce(dotted, _typed(dotted, value, annotation) if typed else value, annotation)
        cfg = _from_flat(values)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Raise :class:`ConfigError` for values out of range."""
        _positive(self, "ray_chunk_objects")
        _within(self.viewpoint_processes, 0, 256, "viewpoint_processes")
        _within(self.seed, 0, 2 ** 63 - 1, "seed", note=" (a 64-bit integer, not negative)")
        for name in SECTIONS:
            getattr(self, name).validate()

    def flat(self) -> dict[str, Any]:
        """``{dotted key: value}`` of every setting, in :func:`all_keys` order."""
        return {key: _get(self, key) for key in all_keys()}

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        """The configuration as YAML, nested by section, with each field's docstring as a comment."""
        lines = ["# carvi_torch resolved configuration"]
        for key in all_keys():
            section, _, name = key.rpartition(".")
            if section and name == _section_fields(section)[0]:
                lines.append(f"{section}:")
            indent = "  " if section else ""
            lines.append(f"{indent}# {FIELD_DOCS[key]}")
            value = yaml.safe_dump({name: _get(self, key)}, default_flow_style=True).strip()[1:-1]
            lines.append(indent + value)
        return "\n".join(lines) + "\n"

    def viewpoint_device(self, device, objects: int):
        """The torch device on which a class of ``objects`` makes its viewpoints, in a run on ``device``: the CPU
        with ``viewpoints.device=cpu``, with ``viewpoint_processes`` or with ``auto`` on a GPU below
        ``viewpoints.gpu_min_objects``; else ``device``.

        >>> import torch
        >>> Config().viewpoint_device(torch.device("cuda"), 48), Config().viewpoint_device(torch.device("cuda"), 9087)
        (device(type='cpu'), device(type='cuda'))
        """
        import torch

        v = self.viewpoints
        small = v.device == "auto" and device.type != "cpu" and objects < v.gpu_min_objects
        return torch.device("cpu") if v.device == "cpu" or self.viewpoint_processes > 0 or small else device

    def resolve_device(self):
        import torch

        if self.device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        try:
            dev = torch.device(self.device)
        except RuntimeError as e:
            raise ConfigError(f"device: {e}") from None
        if dev.type not in ("cpu", "cuda"):
            raise ConfigError(f"device must be cpu, cuda, cuda:N or auto, got {self.device!r}")
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError("device=cuda but no CUDA device is available (use device=cpu or device=auto)")
        return dev


# --------------------------------------------------------------------------- keys


def _section_fields(section: str) -> list[str]:
    return [f.name for f in fields(_SECTION_TYPES[section])]


_SECTION_TYPES = {f.name: f.default_factory for f in fields(Config) if f.name in SECTIONS}


def all_keys() -> list[str]:
    """Every setting's dotted key: the run-wide fields, then ``<section>.<field>`` per section."""
    top = [f.name for f in fields(Config) if f.name not in SECTIONS]
    return top + [f"{s}.{name}" for s in SECTIONS for name in _section_fields(s)]


def _aliases() -> dict[str, str]:
    """Short spellings: a field's bare name where one section has it, and ``<section>_<field>``."""
    out: dict[str, str] = {}
    bare: dict[str, list[str]] = {}
    for key in all_keys():
        section, _, name = key.rpartition(".")
        if section:
            bare.setdefault(name, []).append(key)
            out.setdefault(f"{section}_{name}", key)
    for name, keys in bare.items():
        if len(keys) == 1 and name not in out:
            out[name] = keys[0]
    top = set(all_keys())
    return {k: v for k, v in out.items() if k not in top}


def resolve_key(key: str) -> str:
    """The dotted key a command-line key names; :class:`ConfigError` (with suggestions) when it names none.

    Example:
        >>> resolve_key("carve.resolution"), resolve_key("resolution"), resolve_key("carve_backend")
        ('carve.resolution', 'carve.resolution', 'carve.backend')
    """
    key = key.strip()
    if key in _ANNOTATIONS:
        return key
    if key in _ALIASES:
        return _ALIASES[key]
    close = difflib.get_close_matches(key, list(_ANNOTATIONS) + list(_ALIASES) + list(SECTIONS), n=3, cutoff=0.6)
    hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    raise ConfigError(f"unknown config key {key!r}{hint} (reconstruct --help lists every key)")


def _get(cfg: Config, key: str) -> Any:
    obj = cfg
    for part in key.split("."):
        obj = getattr(obj, part)
    return obj


def _from_flat(values: dict[str, Any]) -> Config:
    top = {k: v for k, v in values.items() if "." not in k}
    sections = {s: _SECTION_TYPES[s](**{k.split(".", 1)[1]: v for k, v in values.items() if k.startswith(s + ".")})
                for s in SECTIONS}
    return Config(**top, **sections)


def _not_a_section(key: str, value: Any) -> None:
    """:class:`ConfigError` when ``key`` names a section (``carve``) given something other than a mapping of
    its settings: a known name used the wrong way, which an unknown key's message would misreport.

    Example:
        >>> _not_a_section("carve", 5)
        Traceback (most recent call last):
        ...
        carvi_torch.config.ConfigError: 'carve' is a section of settings, not a setting: give it a mapping of them \
(carve: {resolution: ...}, or carve.resolution=... on the command line), not 5
    """
    name = key.strip()
    if name in SECTIONS:
        first = next(iter(_section_fields(name)))
        raise ConfigError(f"{name!r} is a section of settings, not a setting: give it a mapping of them "
                          f"({name}: {{{first}: ...}}, or {name}.{first}=... on the command line), not {value!r}")


def _pairs(items: list[str] | dict[str, Any]) -> list[tuple[str, Any]]:
    """``(key, value)`` pairs of ``key=value`` strings (the value the text after ``=``, for :func:`_typed`) or
    of a mapping (sections flattened; an empty section, YAML's ``carve:`` with nothing under it, has none; a
    key that is not text is a :class:`ConfigError`)."""
    if isinstance(items, dict):
        pairs = []
        for k, v in items.items():
            if k in SECTIONS and (isinstance(v, dict) or v is None):  # None: a section with every key commented out
                pairs.extend((f"{k}.{_name(name)}", val) for name, val in (v or {}).items())
            else:
                pairs.append((_name(k), v))
        return pairs
    pairs = []
    for item in items:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form key=value")
        k, v = item.split("=", 1)
        pairs.append((k.strip(), v))
    return pairs


def _name(key: Any) -> str:
    """A key of a mapping of settings, which must be text (YAML reads ``on:`` as True, ``123:`` as a number).

    Example:
        >>> _name(123)
        Traceback (most recent call last):
        ...
        carvi_torch.config.ConfigError: config key 123 is not a setting name (reconstruct --help lists every key)
    """
    if not isinstance(key, str):
        raise ConfigError(f"config key {key!r} is not a setting name (reconstruct --help lists every key)")
    return key


def flatten_settings(data: dict, written: bool = False) -> dict[str, Any]:
    """``{dotted key: value}`` of a saved configuration (nested, or flat with short keys); unknown
    keys are kept as they are (a file written by another version), a key that is not text is a
    :class:`ConfigError`. Numbers are plain ``int`` and ``float``, or with ``written`` as :func:`read_yaml`
    gives them (with the text they were written as, for :meth:`Config.override`)."""
    out = {}
    for k, v in _pairs(data):
        v = v if written else _plain(v)
        try:
            out[resolve_key(k)] = v
        except ConfigError:
            out[k] = v
    return out


def _plain(value: Any) -> Any:
    """``value`` with :func:`read_yaml`'s numbers as plain ``int`` and ``float`` (in lists and mappings too); an
    integer as its decimal text reads (``040`` is 40, as :func:`read_run_config` takes it, not YAML 1.1's 32)."""
    if isinstance(value, _WrittenInt):
        text = value.text.replace("_", "").strip()
        return int(text, 10) if text.lstrip("+-").isdigit() else int(value)
    if isinstance(value, _WrittenFloat):
        return float(value)
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {_plain(k): _plain(v) for k, v in value.items()}
    return value


# --------------------------------------------------------------------------- docs and types


def _class_field_docs(cls, classes: dict) -> dict[str, str]:
    """Field docstrings of a dataclass, read from its source (the string under each field). ``classes``: the class
    definitions of this module's source by name (:func:`_field_docs` parses the file once); a class defined
    elsewhere is read with ``inspect``."""
    import ast
    import inspect

    node = classes.get(cls.__qualname__) if cls.__module__ == __name__ else None
    if node is None:
        try:
            node = ast.parse(inspect.getsource(cls)).body[0]
        except (OSError, TypeError):  # pragma: no cover - source unavailable
            return {}
    body = node.body
    docs = {}
    for node, nxt in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None), ast.Constant):
                docs[node.target.id] = " ".join(str(nxt.value.value).split())
    return docs


def _field_docs() -> dict[str, str]:
    """Every setting's docstring by dotted key, from this module's source, parsed once (``inspect.getsource`` of
    each class parsed the whole file again: 0.18 s of every command's start)."""
    import ast

    try:
        tree = ast.parse(Path(__file__).read_text(encoding="utf-8"))
        classes = {n.name: n for n in tree.body if isinstance(n, ast.ClassDef)}
    except (OSError, SyntaxError):  # pragma: no cover - source unavailable
        classes = {}
    docs = {k: v for k, v in _class_field_docs(Config, classes).items() if k not in SECTIONS}
    for s in SECTIONS:
        docs.update({f"{s}.{k}": v for k, v in _class_field_docs(_SECTION_TYPES[s], classes).items()})
    return docs


def _annotations() -> dict[str, Any]:
    mod = sys.modules[__name__].__dict__
    out = {k: v for k, v in typing.get_type_hints(Config, mod).items() if k not in SECTIONS}
    for s in SECTIONS:
        out.update({f"{s}.{k}": v for k, v in typing.get_type_hints(_SECTION_TYPES[s], mod).items()})
    return out


#: Each setting's docstring, by dotted key.
FIELD_DOCS: dict[str, str] = _field_docs()
_ANNOTATIONS: dict[str, Any] = _annotations()
_ALIASES: dict[str, str] = _aliases()


#: What ``key=value`` gives to unset a setting that may be unset: nothing, or YAML's spellings of null.
NULL_WORDS = ("", "null", "Null", "NULL", "~")
_BOOLS = {"true": True, "yes": True, "on": True, "1": True, "false": False, "no": False, "off": False, "0": False}


def _base(annotation: Any) -> Any:
    """The type of ``Optional[T]``: ``T``; any other annotation as it is."""
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is typing.Union and type(None) in args:
        return next(a for a in args if a is not type(None))
    return annotation


def _is_text(annotation: Any) -> bool:
    """Whether a setting of this type (not ``Optional``) holds text: ``str`` or a path."""
    return annotation is str or (isinstance(annotation, type) and issubclass(annotation, PurePath))


def _quoted(word: str) -> str | None:
    """What ``word`` holds when it is one YAML quoted string from end to end (``'007'``: ``007``); else ``None``."""
    if len(word) < 2 or word[0] != word[-1] or word[0] not in "'\"":
        return None
    try:
        value = yaml.safe_load(word)
    except yaml.YAMLError:
        return None
    return value if isinstance(value, str) else None


def _typed(key: str, text: str, annotation: Any) -> Any:
    """The value ``key=text`` on the command line gives a setting of type ``annotation``, for :func:`_coerce`:
    ``None`` for nothing or ``null`` (:data:`NULL_WORDS`); what a quoted value holds (``data='null'``); a text
    setting's text as typed, the blanks around it dropped (``out=007`` is the folder ``007``, not YAML's 7;
    ``device=cpu `` is ``cpu``); a list's ``[a, b]`` (YAML, a number's text kept) or ``a,b``; any other setting's
    text without the blanks around it.

    Example:
        >>> _typed("out", "007", str), _typed("data", "null", Optional[str]), _typed("seed", " 010", int)
        ('007', None, '010')
    """
    word = text.strip()
    if word in NULL_WORDS:
        return None
    quoted = _quoted(word)
    if quoted is not None:
        return quoted
    base = _base(annotation)
    if _is_text(base):
        return word  # blanks around a value are the shell's, not the setting's (quote them to keep them)
    if base is list and word.startswith("["):
        try:
            return yaml.load(word, Loader=_ConfigLoader)
        except yaml.YAMLError as e:
            raise ConfigError(f"{key}: malformed list {word}{_yaml_where(e)}") from None
    return word


def _coerce(key: str, value: Any, annotation: Any) -> Any:
    """Check/convert ``value`` (YAML's, Python's or :func:`_typed`'s) against the field's type (``Optional``,
    ``Literal``, bool, int, float, text, a list of names)."""
    base = _base(annotation)
    if value is None:
        if base is not annotation:
            return None
        raise ConfigError(f"{key} cannot be empty or null")
    if typing.get_origin(base) is Literal:
        choices = typing.get_args(base)
        if value not in choices:
            raise ConfigError(f"{key} must be one of {', '.join(map(str, choices))}; got {value!r}")
        return value
    if _is_text(base):
        return base(_text(key, value))
    if base is list:
        if isinstance(value, (str, _WrittenInt, _WrittenFloat)):  # a,b; a number of a file as written
            return [v.strip() for v in _text(key, value).split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list of names (a,b or [a, b]), got {value!r}")
        return [_text(key, v) for v in value]
    try:
        return _coerce_plain(value, base)
    except (TypeError, ValueError, OverflowError):
        name = "bool (true/false, yes/no, on/off or 1/0)" if base is bool else getattr(base, "__name__", str(base))
        shown = value.text if isinstance(value, (_WrittenInt, _WrittenFloat)) else repr(value)
        raise ConfigError(f"{key}: expected {name}, got {shown}") from None


def _text(key: str, value: Any) -> str:
    """A text setting's value: text as it is, a path as its text, a number of a config file as it was written
    (``out: 007`` is ``007``); :class:`ConfigError` for anything else (YAML's booleans, lists, mappings)."""
    if isinstance(value, str):
        return value
    if isinstance(value, (_WrittenInt, _WrittenFloat)):
        return value.text
    if isinstance(value, os.PathLike):
        return str(os.fspath(value))
    kind = ("the boolean" if isinstance(value, bool) else "a list" if isinstance(value, (list, tuple))
            else "a mapping" if isinstance(value, dict) else "the number" if isinstance(value, (int, float))
            else type(value).__name__)
    why = " (YAML reads yes/no, on/off and true/false so)" if isinstance(value, bool) else ""
    raise ConfigError(f"{key}: expected text, got {kind} {value!r}{why}; quote it to mean text: "
                      f"{key.rpartition('.')[2]}: \"...\"")


def _coerce_plain(value: Any, annotation: Any) -> Any:
    """A bool (also ``1``/``0``, ``"yes"``, ...), an int (text, a YAML number's included, read in decimal: ``010``
    is 10) or a finite float; ``ValueError`` when ``value`` is none."""
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        if isinstance(value, str) and value.strip().lower() in _BOOLS:
            return _BOOLS[value.strip().lower()]
        raise ValueError
    if annotation is int:
        if isinstance(value, bool):
            raise ValueError
        value = value.text if isinstance(value, (_WrittenInt, _WrittenFloat)) else value
        if isinstance(value, str):
            try:
                return int(value)
            except ValueError:
                value = float(value)
        if isinstance(value, float) and not value.is_integer():
            raise ValueError
        return int(value)
    if annotation is float:
        if isinstance(value, bool) or not math.isfinite(float(value)):
            raise ValueError
        return float(value)
    return value


def override_text(value: Any) -> str:
    """``value`` as a ``key=value`` override spells it (``reconstruct --help`` shows the defaults so): ``null``,
    ``true``/``false``, a list's names joined by commas, a number or text as it is (quoted where it would read as
    something else).

    Example:
        >>> override_text(None), override_text(False), override_text(["car", "chair"]), override_text(1e-07)
        ('null', 'false', 'car,chair', '1e-07')
        >>> override_text("outputs/default"), override_text("null"), override_text([])
        ('outputs/default', "'null'", '[]')
    """
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        names = [str(v) for v in value]
        if names and all(n.strip() == n and n and "," not in n and n[0] not in "['\"" for n in names):
            return ",".join(names)
        return yaml.safe_dump(names, default_flow_style=True, width=10 ** 6).strip()
    if isinstance(value, str) and (value.strip() in NULL_WORDS or _quoted(value.strip()) is not None
                                   or value.strip() != value):  # blanks around it are kept only when quoted
        return "'" + value.replace("'", "''") + "'"
    return str(value)


#: Settings that do not change how an object is reconstructed (a rerun may differ in them freely;
#: the input files are the user's choice: an object is resumed only when the fingerprint of its own inputs,
#: recorded in its voxels file, matches, whatever file they come from).
NEUTRAL_SETTINGS = {"out", "data", "gt", "progress", "preview", "report", "overwrite", "classes", "stage", "device",
                    "executor", "ray_address", "ray_chunk_objects", "pipeline_classes",  # where the work runs
                    "viewpoints.sfm_group_threads",  # the mixture fit's result is the same on any number of threads
                    # where the viewpoint stage runs, like `device`: another device rounds differently, no more
                    "viewpoints.device", "viewpoints.gpu_min_objects", "viewpoint_processes",
                    "carve.backend",  # every carving backend gives the same labels voxel for voxel
                    "study.keep_all_scores", "study.save_proposals"}  # files written beside the objects


def object_settings(cfg: Config) -> dict[str, Any]:
    """``{dotted key: value}`` of the settings that can change how an object is made: every setting but those of
    :data:`NEUTRAL_SETTINGS`, in :func:`all_keys` order. What :func:`settings_changed` compares, and what each
    object's voxels file records (:data:`~carvi_torch.io.layout.SETTINGS_MEMBER`).

    Example:
        >>> made = object_settings(Config())
        >>> made["carve.resolution"], "out" in made, "carve.backend" in made
        (60, False, False)
    """
    return {k: v for k, v in cfg.flat().items() if k not in NEUTRAL_SETTINGS}


def settings_changed(previous: Path, cfg: Config, summary: dict) -> dict:
    """``{key: (made, ..., now)}``: the settings in which finished objects in the run folder of ``previous`` (its
    ``config.yaml``) may have been made otherwise than ``cfg`` says (``now``), with the values they were made with
    (``made``, oldest first, ``now`` among them where objects were made with it too). Those values are the ones
    its ``summary.json`` records (``summary``: that file's content, ``{}`` without one; its
    ``resumed_from_other_settings``, the same form: a record is carried from run to run, so that a rerun with the
    same settings still says how its resumed objects were made), else that run's.
    A key the old file lacks (a setting added since) counts, as ``None``; settings of :data:`NEUTRAL_SETTINGS` do
    not, nor files the studies write besides the objects (``keep_all_scores``, ``save_proposals``). Empty for
    ``stage=cameras``, or without a readable ``config.yaml``. ``overwrite`` is the caller's to weigh: it redoes
    the classes it runs, not those it leaves (:func:`carvi_torch.executors.common.announce`).

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> _ = (d / "config.yaml").write_text(Config().to_yaml())
        >>> settings_changed(d / "config.yaml", Config().override(["resolution=24"]), {})
        {'carve.resolution': (60, 24)}
        >>> record = {"resumed_from_other_settings": {"carve.resolution": [16, 60]}}
        >>> settings_changed(d / "config.yaml", Config(), record)
        {'carve.resolution': (16, 60)}
        >>> settings_changed(d / "config.yaml", Config(overwrite=True), record)
        {'carve.resolution': (16, 60)}
    """
    if cfg.stage != "all" or not previous.is_file():
        return {}
    try:
        old = flatten_settings(read_yaml(previous))
    except (ConfigError, AttributeError):
        return {}
    record = summary.get("resumed_from_other_settings") or {}
    out = {}
    for k, now in object_settings(cfg).items():
        held = record.get(k) if isinstance(record, dict) else None
        made = list(held[:-1]) if isinstance(held, list) and len(held) > 1 else []
        if not made or old.get(k) != held[-1]:  # no record of it, or a config.yaml other than the record's run's
            made.append(old.get(k))
        made = [v for i, v in enumerate(made) if v not in made[:i]]
        if any(v != now for v in made):
            out[k] = (*made, now)
    return out



def read_yaml(path: str | Path) -> Any:
    """A YAML file's content (UTF-8, a byte order mark allowed; empty: ``{}``), read as a config file
    (:class:`_ConfigLoader`). Raises :class:`ConfigError` with one line naming the file (and the line and column
    of malformed YAML): missing, not UTF-8, malformed, a key that is not text or is given twice.

    Example:
        >>> import tempfile
        >>> p = Path(tempfile.mkdtemp()) / "c.yaml"
        >>> _ = p.write_text("carve:\\n  resolution: [16\\n x: :\\n")
        >>> try:
        ...     read_yaml(p)
        ... except ConfigError as e:
        ...     print(str(e).replace(str(p), "c.yaml"))
        c.yaml: malformed YAML at line 3, column 3: expected ',' or ']', but got ':' (in a flow sequence)
    """
    p = Path(path)
    try:
        return yaml.load(read_text(p), Loader=_ConfigLoader) or {}
    except (OSError, ValueError) as e:
        raise ConfigError(str(e) if str(p) in str(e) else f"{p}: {e}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: malformed YAML{_yaml_where(e)}") from None
    except RecursionError:
        raise ConfigError(f"{p}: YAML nested too deeply to read") from None


def _yaml_where(e: yaml.YAMLError) -> str:
    """`` at line L, column C: problem (in context)`` of a YAML error, on one line."""
    mark, problem = getattr(e, "problem_mark", None), getattr(e, "problem", None)
    if problem is None:
        return ": " + " ".join(str(e).split())
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    context = getattr(e, "context", None)
    return f"{where}: {problem}" + (f" ({context.replace('while parsing', 'in')})" if context else "")


class _WrittenInt(int):
    """An integer of a config file, with ``text``: how it was written (``010``, which YAML 1.1 reads as 8)."""

    text = ""


class _WrittenFloat(float):
    """A float of a config file, with ``text``: how it was written (``1.50``)."""

    text = ""


class _ConfigLoader(yaml.SafeLoader):
    """YAML read as a config file: a number keeps the text it was written as (:class:`_WrittenInt`,
    :class:`_WrittenFloat`: ``out: 007`` is the folder ``007``, ``seed: 010`` is ten), a date stays text, and a
    mapping's keys must be text, each once (:class:`ConfigError` naming the key and its line)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            lines: dict[str, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # <<: an anchor's keys, which this mapping may override
                    continue
                line = key_node.start_mark.line + 1
                if not isinstance(key_node, yaml.ScalarNode):
                    raise ConfigError(f"config key at line {line} is a {key_node.id}, not a setting name")
                key = self.construct_object(key_node, deep=deep)
                if not isinstance(key, str):
                    raise ConfigError(f"config key {key_node.value!r} at line {line} is not a setting name (YAML "
                                      f"reads it as {key!r}; reconstruct --help lists every key)")
                if key in lines:
                    raise ConfigError(f"config key {key!r} is given twice (lines {lines[key]} and {line}); keep one")
                lines[key] = line
        return super().construct_mapping(node, deep)


def _keep_text(cls: type, construct: Any) -> Any:
    """A YAML constructor: ``construct``'s number as ``cls``, with ``text`` the scalar as written."""

    def build(loader, node):
        value = cls(construct(loader, node))
        value.text = node.value
        return value
    return build


_ConfigLoader.add_constructor("tag:yaml.org,2002:int", _keep_text(_WrittenInt, yaml.SafeLoader.construct_yaml_int))
_ConfigLoader.add_constructor("tag:yaml.org,2002:float",
                              _keep_text(_WrittenFloat, yaml.SafeLoader.construct_yaml_float))
_ConfigLoader.add_constructor("tag:yaml.org,2002:timestamp", yaml.SafeLoader.construct_scalar)


def read_run_config(path: str | Path) -> Config:
    """The configuration a run saved (its ``config.yaml``, nested or flat); settings this version does
    not know are ignored, so outputs of other versions stay readable."""
    p = Path(path)
    data = read_yaml(p)
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping of key: value")
    known = {k: v for k, v in flatten_settings(data, written=True).items() if k in _ANNOTATIONS}
    return Config().override(known)


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults <- YAML file (if given) <- ``key=value`` overrides. Unknown keys are errors."""
    cfg = Config()
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"config file {p} not found")
        data = read_yaml(p)
        if not isinstance(data, dict):
            raise ConfigError(f"{p}: expected a mapping of key: value")
        cfg = cfg.override(data)
    if overrides:
        cfg = cfg.override(overrides)
    cfg.validate()
    return cfg
