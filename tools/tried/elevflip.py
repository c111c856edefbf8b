import json, sys
from pathlib import Path
import numpy as np, torch
ROOT = Path(__file__).resolve().parents[2]
(ROOT / 'outputs' / 'tried').mkdir(parents=True, exist_ok=True)
sys.path.insert(0, str(ROOT))
from carvi_torch.io.coco import load_coco
from carvi_torch.config import ViewpointConfig
from carvi_torch.sdf import distance_to_mask
from carvi_torch.cameras import ScaledOrthographic, align_rotations, geodesic_errors
from carvi_torch.viewpoints import camera_fit, estimate_viewpoints, ground_truth_cameras
from carvi_torch.viewpoints.choice import class_up
from carvi_torch.viewpoints.refine import refine_with_shape, rows as take
torch.set_num_threads(1)
seed = int(sys.argv[1]); views = int(sys.argv[2]) if len(sys.argv) > 2 else 8
rd = Path(f'{ROOT}/outputs/viewpoints_cad/renders_v{views}_s{seed}')
gt = json.loads((rd / 'gt.json').read_text())
def flip(R, u):
    H = torch.eye(3, dtype=R.dtype) - 2 * torch.outer(u, u)
    x = R[:, 0] @ H; d = R[:, 2] @ H  # rows: H is symmetric, row vectors reflected
    x = x - (x * d).sum(-1, keepdim=True) * d; x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(d, x)
    return torch.stack([x, y, d], 1)
def med(R, Rg):
    return float(np.median(geodesic_errors(R, Rg, align_rotations(R, Rg)).numpy()))
out = {}
for cls, coll in sorted(load_coco(rd / 'annotations.json').collections.items()):
    cfg = ViewpointConfig()
    vp = estimate_viewpoints(coll, cfg, seed=seed)
    n = len(coll); both = vp.both
    up = class_up(vp.sfm_cameras.R[vp.sfm_valid].cpu())
    gtc, _ = ground_truth_cameras(gt, coll)
    ok = (vp.sfm_valid[:n].cpu() & torch.isfinite(gtc.R).flatten(1).all(1))
    if up is None:
        print(cls, 'no up'); continue
    up = up.to(vp.cameras.R.dtype)
    dist = camera_fit._finite_maps(distance_to_mask(both.masks))
    mix = vp.groups
    E0 = torch.zeros(len(both)); E1 = torch.zeros(len(both)); R1 = vp.cameras.R.clone()
    for g in range(mix.k):
        idx = torch.arange(len(both)) if mix.k == 1 else mix.groups[g][0]
        sub = take(both, idx)
        cams = ScaledOrthographic(vp.cameras.R[idx], vp.cameras.s[idx], vp.cameras.t[idx])
        r0 = refine_with_shape(mix.shape(g), cams, sub, dist[idx], cfg)  # energy at the final camera (a no-op restart)
        fc = ScaledOrthographic(flip(vp.cameras.R[idx], up), vp.cameras.s[idx], vp.cameras.t[idx])
        r1 = refine_with_shape(mix.shape(g), fc, sub, dist[idx], cfg)
        E0[idx] = r0.energy_after.float(); E1[idx] = r1.energy_after.float(); R1[idx] = r1.cameras.R
    el = lambda R: torch.rad2deg(torch.asin((-(R[:, 2] @ up)).clamp(-1, 1)))
    e0, e1 = el(vp.cameras.R[:n]), el(R1[:n])
    Rg = gtc.R.double()[ok]
    res = {'final': med(vp.cameras.R[:n].double()[ok], Rg)}
    for m in (0.0, 0.05, 0.2, 0.5):
        take_flip = (E1[:n] <= (1 + m) * E0[:n]) & (e1 > e0)
        Rm = torch.where(take_flip[:, None, None], R1[:n], vp.cameras.R[:n]).double()
        res[f'm{m}'] = (med(Rm[ok], Rg), int(take_flip[ok].sum()))
    out[cls] = res
    print(cls, res, flush=True)
Path(f'{ROOT}/outputs/tried/elevflip_v{views}_s{seed}.json').write_text(json.dumps(out))
