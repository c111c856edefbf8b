"""Evaluation: shape metrics against ground-truth meshes, viewpoint metrics, baselines and study helpers.

* :mod:`~carvi_torch.evaluation.metrics`: the paper's symmetric RMS surface distance, voxel IoU;
* :mod:`~carvi_torch.evaluation.scoring`: every object's shape error in an evaluation, in worker processes;
* :mod:`~carvi_torch.evaluation.viewpoint_metrics`: rotation errors after one global alignment;
* :mod:`~carvi_torch.evaluation.baselines`: Puffball and the SfM convex hull;
* :mod:`~carvi_torch.evaluation.studies`: ranking curves and shape clusters for the studies in ``tools/``;
* :mod:`~carvi_torch.evaluation.reliability`: how well the objects' ``quality`` ranks their true errors
  (Spearman's rho; ``evaluate``'s ``quality.md``).
"""
