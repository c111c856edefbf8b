"""Per object final cameras at several silhouette weights, with visible-keypoint counts and true errors."""
import json, sys
from pathlib import Path
import numpy as np, torch
ROOT = Path(__file__).resolve().parents[2]
(ROOT / 'outputs' / 'tried').mkdir(parents=True, exist_ok=True)
sys.path.insert(0, str(ROOT))
from carvi_torch.io.coco import load_coco
from carvi_torch.config import ViewpointConfig
from carvi_torch.viewpoints import camera_fit, estimate_viewpoints, ground_truth_cameras
torch.set_num_threads(1)
seed = int(sys.argv[1]); views = int(sys.argv[2]); ws = [float(x) for x in sys.argv[3].split(',')]
classes = sys.argv[4].split(',') if len(sys.argv) > 4 else None
rd = Path(f'{ROOT}/outputs/viewpoints_cad/renders_v{views}_s{seed}')
gt = json.loads((rd / 'gt.json').read_text())
out = {}
for cls, coll in sorted(load_coco(rd / 'annotations.json').collections.items()):
    if classes and cls not in classes: continue
    n = len(coll)
    gtc, _ = ground_truth_cameras(gt, coll)
    rec = {'gt': gtc.R.double().tolist()}
    for w in ws:
        vp = estimate_viewpoints(coll, ViewpointConfig(silhouette_weight=w), seed=seed)
        S = vp.shape
        nvis = (vp.both.visible[:n] & torch.isfinite(S).all(-1)).sum(-1)
        rec[str(w)] = {'R': vp.cameras.R[:n].double().tolist(), 'sfm': vp.sfm_cameras.R[:n].double().tolist(),
                       'sfm_valid': vp.sfm_valid[:n].tolist(), 'nvis': nvis.tolist(),
                       'thick': camera_fit.keypoint_thickness(S, vp.both.visible[:n]).tolist()}
    out[cls] = rec
    print(cls, flush=True)
Path(f'{ROOT}/outputs/tried/wsweep_v{views}_s{seed}.json').write_text(json.dumps(out))
