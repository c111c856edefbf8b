"""Leave-one-keypoint-out test of refinement per class: does the silhouette term predict held-out keypoints better?"""
import json, sys, time
from pathlib import Path
import numpy as np, torch
ROOT = Path(__file__).resolve().parents[2]
(ROOT / 'outputs' / 'tried').mkdir(parents=True, exist_ok=True)
sys.path.insert(0, str(ROOT / 'tools')); sys.path.insert(0, str(ROOT))
from viewpoints_cad import _aligned_errors
from carvi_torch.io.coco import load_coco
from carvi_torch.config import ViewpointConfig
from carvi_torch.sdf import distance_to_mask
from carvi_torch.viewpoints import camera_fit, estimate_viewpoints, ground_truth_cameras
from carvi_torch.viewpoints.choice import box_diagonal
from carvi_torch.viewpoints.refine import rows as take
from carvi_torch.cameras import ScaledOrthographic
torch.set_num_threads(1)

def sub(c, r):
    return ScaledOrthographic(c.R[r], c.s[r], c.t[r])

def loo(vp, cfg, n):
    both = vp.both
    dist = camera_fit._finite_maps(distance_to_mask(both.masks))
    diag = box_diagonal(both.masks).double()
    out = []  # (row, k, err_kp, err_ref)
    mix = vp.groups
    for g in range(mix.k):
        idx = torch.arange(len(both)) if mix.k == 1 else mix.groups[g][0].cpu()
        sb = take(both, idx if mix.k > 1 else None)
        S = camera_fit.supported_shape(mix.shape(g), sb.visible, cfg.refine_min_support)
        sfm = sub(vp.sfm_cameras, idx)
        valid = vp.sfm_valid[idx]
        for k in torch.isfinite(S).all(-1).nonzero().squeeze(1).tolist():
            r = (sb.visible[:, k] & valid & (idx < n)).nonzero().squeeze(1)
            vis = sb.visible[r].clone(); vis[:, k] = False
            r = r[vis.sum(1) >= 2]; vis = vis[vis.sum(1) >= 2]
            if len(r) == 0: continue
            Sk = S.clone(); Sk[k] = float('nan')
            kp = sb.keypoints[r]
            c0 = camera_fit.refine_cameras(Sk, sub(sfm, r), kp, vis, None).cameras
            c1 = camera_fit.refine_cameras(Sk, c0, kp, vis, dist[idx][r], silhouette_weight=cfg.silhouette_weight,
                                           max_iters=cfg.refine_iters, silhouette_robust=cfg.silhouette_robust or None,
                                           twin_flatness=cfg.refine_twin_flatness).cameras
            w = kp[:, k].double()
            d = diag[idx][r]
            e = [((c.project(S[k:k+1])[:, 0].double() - w).norm(dim=-1) / d).numpy() for c in (c0, c1)]
            for i in range(len(r)):
                out.append((int(idx[r[i]]), k, float(e[0][i]), float(e[1][i])))
    return out

res = {}
for seed in [int(s) for s in sys.argv[1].split(',')]:
    rd = Path(f'{ROOT}/outputs/viewpoints_cad/renders_v8_s{seed}') if len(sys.argv) < 3 else Path(sys.argv[2].format(seed=seed))
    gt = json.loads((rd / 'gt.json').read_text())
    for cls, coll in sorted(load_coco(rd / 'annotations.json').collections.items()):
        t0 = time.time()
        cfg = ViewpointConfig(refine_keep='refined')
        vp = estimate_viewpoints(coll, cfg, seed=seed)
        n = len(coll)
        gtc, _ = ground_truth_cameras(gt, coll)
        ok = (vp.sfm_valid[:n].cpu() & torch.isfinite(gtc.R).flatten(1).all(1)).numpy()
        Rg = gtc.R.double()[ok]
        err = {k: _aligned_errors(c.R[:n].double().cpu()[ok], Rg) for k, c in (('sfm', vp.sfm_cameras), ('refined', vp.cameras))}
        pairs = loo(vp, cfg, n)
        a = np.array([(p[2], p[3]) for p in pairs])
        row = dict(seed=seed, sfm=float(np.median(err['sfm'])), refined=float(np.median(err['refined'])),
                   pairs=len(a), mean_kp=float(a[:, 0].mean()), mean_ref=float(a[:, 1].mean()),
                   med_kp=float(np.median(a[:, 0])), med_ref=float(np.median(a[:, 1])),
                   frac_better=float((a[:, 1] < a[:, 0]).mean()), per_row=pairs,
                   change=(err['refined'] - err['sfm']).tolist())
        res.setdefault(cls, []).append(row)
        print(f"{cls:12s} s{seed} true {row['sfm']:.2f}->{row['refined']:.2f}  loo mean {row['mean_kp']:.4f}->{row['mean_ref']:.4f} "
              f"med {row['med_kp']:.4f}->{row['med_ref']:.4f} better {row['frac_better']:.2f} n={len(a)} {time.time()-t0:.0f}s", flush=True)
Path(f'{ROOT}/outputs/tried/loo_{sys.argv[1].replace(",","_")}.json').write_text(json.dumps(res))
