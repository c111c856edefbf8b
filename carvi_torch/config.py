"""Run configuration: one dataclass, one docstring per field.

Resolution order (later wins): the dataclass defaults, ``configs/default.yaml``
shipped with the package (the same values, for users to copy), a ``--config FILE``,
then ``key=value`` overrides on the command line. The resolved configuration is
written next to the outputs as ``config.yaml``.

Example:
    >>> cfg = Config().override(["resolution=32", "imprint=false"])
    >>> cfg.resolution, cfg.imprint
    (32, False)
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Optional

import yaml

__all__ = ["Config", "ConfigError", "load_config"]


class ConfigError(ValueError):
    """A configuration file or override is invalid (names the key and the problem)."""


@dataclass
class Config:
    """Every knob of a reconstruction run."""

    # ---- input / output
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

    # ---- general
    seed: int = 0
    """Seed of every random choice (surrogate sampling, synthetic data). Same seed, same outputs."""
    device: str = "cpu"
    """Torch device for all stages: ``cpu``, ``cuda``, ``cuda:1`` or ``auto`` (CUDA when available)."""
    stage: str = "all"
    """``all`` runs the whole pipeline; ``cameras`` stops after viewpoint estimation."""
    cameras: str = "estimate"
    """``estimate`` (SfM + refinement) or ``gt``: take the true cameras of ``gt.json`` (oracle study)."""
    progress: bool = True
    """Show progress bars."""

    # ---- embedded default collection
    procedural_instances: int = 40
    """Instances per class of the embedded procedural collection (used when ``data`` is ``None``)."""

    # ---- canvas
    canvas_size: int = 128
    """Side (pixels) of the square canvas every instance is cropped and scaled into."""
    canvas_margin: float = 0.1
    """Fraction of the canvas left empty on each side of the object's bounding box."""
    min_instances: int = 3
    """Classes with fewer usable instances are reported and skipped."""

    # ---- viewpoints (SfM + refinement)
    mirrors: bool = True
    """Add left-right flipped copies (SfM data; mirrored silhouettes in carving unless articulated)."""
    sfm_max_outer: int = 200
    """Outer (fill) iterations of the missing-data factorisation at most."""
    sfm_inner: int = 10
    """Inner (camera / shape) alternations per outer iteration."""
    sfm_tol: float = 1e-7
    """Stop when the relative change of the visible-entry residual falls below this."""
    sfm_groups: int = 1
    """Most rigid shapes per class (``carvi_torch.sfm_mixture``): a class whose members differ in
    proportions is split into groups, each with its own SfM shape, in one class frame. 1 = one mean
    shape per class, as in the paper."""
    sfm_group_min: int = 15
    """Fewest objects per shape group (a class with fewer than twice this keeps one shape)."""
    sfm_group_gain: float = 0.3
    """A split into one more group is kept when it cuts the keypoint residual by more than this fraction."""
    sfm_group_agreement_deg: float = 60.0
    """A split is only considered when its groups' frames agree within this many degrees (median over
    the objects; no ground truth)."""
    sfm_group_rounds: int = 6
    """Most hard-EM rounds per candidate split."""
    sfm_group_threads: int = 2
    """Python threads that run the two initialisations of each candidate split side by side, for
    classes of at least ``sfm_mixture.THREADS_MIN_OBJECTS`` objects (1: one after the other; same
    result either way)."""
    refine: bool = True
    """Silhouette refinement of the SfM cameras (``False`` = the -CRef ablation)."""
    refine_iters: int = 150
    """Refinement steps at most."""
    silhouette_weight: float = 1.0
    """Weight of the distance-to-mask penalty against the keypoint reprojection error."""
    silhouette_robust: float = 0.2
    """Robust (Geman-McClure) scale of the distance-to-mask penalty, a fraction of each mask's larger side; 0 = the paper's squared distance."""
    refine_twin_flatness: float = 0.1
    """Also refine a camera from its planar twin (the other camera under which the plane of its visible keypoints looks the same) when those keypoints are this flat (thickness: smallest over middle spread; 1 = every camera, 0 = off); the twin's result is kept when its energy is at least 2% lower (``refine.TWIN_MARGIN``). The flat instances are refined twice."""

    refine_min_support: float = 0.1
    """Leave out of the refinement (and of the unseen-image path) every mean-shape keypoint shown by fewer than this fraction of the instances refined with that shape (the class, or its shape group): placed by SfM from too few views, it would pull every instance's camera through the silhouette term (``refine.supported_shape``; 0 = use every keypoint)."""

    # ---- surrogates
    cluster_threshold_deg: float = 15.0
    """An instance joins a principal direction's cluster within this angle (front or back)."""
    cluster_widen_step_deg: float = 5.0
    """Widen the threshold by this while the second-smallest cluster has too few members."""
    cluster_max_threshold_deg: float = 45.0
    """Never widen beyond this."""
    proposals: int = 20
    """Triplets (reconstruction proposals) sampled per reference instance."""
    symmetric_step_deg: float = 90.0
    """Rotationally symmetric classes: synthesise surrogate views every this many degrees."""
    symmetric_axis_in_image: bool = True
    """Rotationally symmetric classes: assume each photo sees the symmetry axis in its image plane."""

    # ---- carving
    resolution: int = 60
    """Voxel grid steps per axis."""
    imprint: bool = True
    """Imprint the reference silhouette (``False`` = the -SImp ablation)."""
    carve_interpolation: str = "bilinear"
    """How the carving reads the distance maps at a voxel's projection: ``bilinear`` (the paper's) or
    ``nearest`` (the pixel it falls in, an approximation: about 1.5-1.75x faster than the torch backend's
    bilinear carving, but it has no fused kernel, so on the CPU it is slower than the default;
    docs/benchmarks/README.md)."""
    carve_backend: str = "auto"
    """Who computes the carving's labels: ``auto`` (the compiled CPU kernel of ``carvi_torch.carve_fused``
    where it applies -- CPU, bilinear -- and builds, else torch), ``torch`` (batched ``grid_sample``) or
    ``fused`` (the kernel, an error where it cannot run). Every backend gives the same labels voxel for
    voxel; the kernel is about 2.3x faster on the CPU (docs/benchmarks/README.md)."""
    max_batch_voxels: int = 50_000_000
    """Upper bound on the voxels (of the reference's foreground columns) carved in one batched chunk (bounds memory); the carving never uses more than its per-device default (``carve.default_batch_voxels``: 2^19 per thread on CPU, at most 2^21, measured with 1 and 2 threads; 2^25 on CUDA), so only smaller values change anything."""

    # ---- selection and meshes
    plane_size: int = 64
    """Resolution of the average masks / proposal projections used for selection."""
    largest_component: bool = False
    """Keep only the largest connected component of the selected occupancy."""
    mesh_format: str = "ply"
    """Mesh file format: ``ply``, ``obj`` or ``glb``."""
    keep_all_scores: bool = True
    """Write the score of every proposal (ranking studies)."""
    save_proposals: bool = False
    """Also write every proposal's occupancy (``<class>/proposals/<id>.npz``, bit-packed) for studies."""
    preview: bool = True
    """Write ``preview.png`` with a few results."""

    # ------------------------------------------------------------------ helpers
    def override(self, items: list[str] | dict[str, Any]) -> "Config":
        """Return a copy with ``key=value`` strings (or a dict) applied, values parsed as YAML scalars."""
        if isinstance(items, dict):
            pairs = list(items.items())
        else:
            pairs = []
            for item in items:
                if "=" not in item:
                    raise ConfigError(f"override {item!r} is not of the form key=value")
                k, v = item.split("=", 1)
                pairs.append((k.strip(), yaml.safe_load(v) if v.strip() != "" else None))
        known = {f.name: f for f in fields(self)}
        values = dataclasses.asdict(self)
        for k, v in pairs:
            if k not in known:
                raise ConfigError(f"unknown config key {k!r}; known keys: {', '.join(sorted(known))}")
            values[k] = _coerce(k, v, known[k].type)
        cfg = Config(**values)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Raise :class:`ConfigError` for values out of range."""
        if self.stage not in ("all", "cameras"):
            raise ConfigError(f"stage must be 'all' or 'cameras', got {self.stage!r}")
        if self.cameras not in ("estimate", "gt"):
            raise ConfigError(f"cameras must be 'estimate' or 'gt', got {self.cameras!r}")
        if self.carve_interpolation not in ("bilinear", "nearest"):
            raise ConfigError(f"carve_interpolation must be 'bilinear' or 'nearest', got {self.carve_interpolation!r}")
        if self.carve_backend not in ("auto", "torch", "fused"):
            raise ConfigError(f"carve_backend must be 'auto', 'torch' or 'fused', got {self.carve_backend!r}")
        if self.mesh_format not in ("ply", "obj", "glb"):
            raise ConfigError(f"mesh_format must be ply, obj or glb, got {self.mesh_format!r}")
        for name in ("canvas_size", "resolution", "proposals", "plane_size", "refine_iters", "sfm_max_outer",
                     "sfm_inner", "procedural_instances", "min_instances", "sfm_groups", "sfm_group_min",
                     "sfm_group_rounds", "sfm_group_threads"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 4 <= self.resolution <= 2048:
            raise ConfigError(f"resolution must be in [4, 2048] (the carving's bound), got {self.resolution}")
        if not 0 <= self.canvas_margin < 0.5:
            raise ConfigError(f"canvas_margin must be in [0, 0.5), got {self.canvas_margin}")
        if not 0 < self.cluster_threshold_deg <= 90:
            raise ConfigError(f"cluster_threshold_deg must be in (0, 90], got {self.cluster_threshold_deg}")
        if not self.refine_twin_flatness >= 0:
            raise ConfigError(f"refine_twin_flatness must be >= 0 (0 = off), got {self.refine_twin_flatness}")
        if not 0 <= self.refine_min_support <= 1:
            raise ConfigError(f"refine_min_support must be in [0, 1] (0 = every keypoint), "
                              f"got {self.refine_min_support}")
        if self.silhouette_robust < 0:
            raise ConfigError(f"silhouette_robust must be >= 0 (0 = squared distance), got {self.silhouette_robust}")
        if not 0 <= self.sfm_group_gain < 1:
            raise ConfigError(f"sfm_group_gain must be in [0, 1), got {self.sfm_group_gain}")
        if not 0 < self.sfm_group_agreement_deg <= 180:
            raise ConfigError(f"sfm_group_agreement_deg must be in (0, 180], got {self.sfm_group_agreement_deg}")
        if not 0 < self.symmetric_step_deg < 360:
            raise ConfigError(f"symmetric_step_deg must be in (0, 360), got {self.symmetric_step_deg}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        lines = ["# carvi_torch resolved configuration"]
        for f in fields(self):
            doc = FIELD_DOCS.get(f.name, "")
            if doc:
                lines.append(f"# {doc}")
            lines.append(yaml.safe_dump({f.name: getattr(self, f.name)}, default_flow_style=True).strip()[1:-1])
        return "\n".join(lines) + "\n"

    def resolve_device(self):
        import torch

        if self.device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        dev = torch.device(self.device)
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError("device=cuda but no CUDA device is available (use device=cpu or device=auto)")
        return dev


def _field_docs() -> dict[str, str]:
    """Field docstrings, read from the source (the attribute docstrings under each field)."""
    import ast
    import inspect

    docs: dict[str, str] = {}
    try:
        tree = ast.parse(inspect.getsource(Config))
    except (OSError, TypeError):  # pragma: no cover - source unavailable
        return docs
    body = tree.body[0].body
    for node, nxt in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None), ast.Constant):
                docs[node.target.id] = " ".join(str(nxt.value.value).split())
    return docs


FIELD_DOCS = _field_docs()


def _coerce(key: str, value: Any, annotation: Any) -> Any:
    """Check/convert ``value`` against the field's annotation (a string under ``from __future__``)."""
    ann = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    optional = ann.startswith("Optional[")
    base = ann[len("Optional["):-1] if optional else ann
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{key} cannot be empty")
    try:
        if base == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.lower() in ("true", "yes", "1", "on", "false", "no", "0", "off"):
                return value.lower() in ("true", "yes", "1", "on")
            raise ValueError
        if base == "int":
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if base == "float":
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        if base == "str":
            return str(value)
        if base == "list":
            if isinstance(value, str):
                return [v.strip() for v in value.split(",") if v.strip()]
            return list(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key}: expected {base}, got {value!r}") from None
    return value


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults <- YAML file (if given) <- ``key=value`` overrides. Unknown keys are errors."""
    cfg = Config()
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"config file {p} not found")
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"{p}: malformed YAML: {e}") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{p}: expected a mapping of key: value")
        cfg = cfg.override(data)
    if overrides:
        cfg = cfg.override(overrides)
    cfg.validate()
    return cfg
