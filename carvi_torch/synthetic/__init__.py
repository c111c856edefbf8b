"""Synthetic data: meshes with keypoints rendered into masks + keypoints, and embedded procedural classes.

* :mod:`.meshes` — :class:`Model`, loaders (PASCAL3D+ ``.npz``; any trimesh mesh with a
  ``.json`` of keypoints), :func:`infer_flip_pairs`.
* :mod:`.render` — exact rasteriser, keypoint visibility, photographic camera sampling,
  :func:`render_view`, :func:`render_dataset` (COCO keypoint JSON + ``gt.json``).
* :mod:`.procedural` — car, aeroplane, chair and bottle classes built from parts, and the
  default collection the package reconstructs when given no data.
* :mod:`.cache` — the default collection's files, kept in the user's cache once generated.
"""
from .meshes import Model, infer_flip_pairs, load_cad_npz, load_mesh_with_keypoints, load_model, load_models
from .render import (keypoint_visibility, rasterize_depth, rasterize_triangles, render_dataset, render_view,
                     sample_cameras)

__all__ = [
    "Model", "infer_flip_pairs", "load_cad_npz", "load_mesh_with_keypoints", "load_model", "load_models",
    "keypoint_visibility", "rasterize_depth", "rasterize_triangles", "render_dataset", "render_view",
    "sample_cameras", "make_instance", "write_default_collection", "CATEGORIES",
]


def __getattr__(name):  # procedural classes load lazily (skimage import)
    if name in ("make_instance", "write_default_collection", "CATEGORIES"):
        from . import procedural

        return getattr(procedural, name)
    raise AttributeError(name)
