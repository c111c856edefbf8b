import json, sys
from pathlib import Path
import numpy as np, torch
ROOT = Path(__file__).resolve().parents[2]
(ROOT / 'outputs' / 'tried').mkdir(parents=True, exist_ok=True)
sys.path.insert(0, str(ROOT))
from carvi_torch.cameras import align_rotations, geodesic_errors
def med(R, Rg):
    R, Rg = torch.tensor(R), torch.tensor(Rg)
    return float(np.median(geodesic_errors(R, Rg, align_rotations(R, Rg)).numpy()))
views = sys.argv[1]; seeds = [0, 1, 2]
D = {s: json.load(open(f'{ROOT}/outputs/tried/wsweep_v{views}_s{s}.json')) for s in seeds}
ws = ['0.0', '0.1', '0.3', '1.0']
rules = {f'w{w}': (lambda nv, th, w=w: [w] * len(nv)) for w in ws}
for T in (4, 5, 6, 7):
    for lo in ('0.0', '0.1', '0.3'):
        rules[f'nvis<={T}:1 else {lo}'] = (lambda nv, th, T=T, lo=lo: ['1.0' if v <= T else lo for v in nv])
res = {}
for cls in D[0]:
    for s in seeds:
        r = D[s][cls]; gt = np.array(r['gt']); ok = np.array(r['1.0']['sfm_valid']) & np.isfinite(gt).reshape(len(gt), -1).all(1)
        sfm = med(np.array(r['1.0']['sfm'])[ok], gt[ok])
        nv = np.array(r['1.0']['nvis'])[ok]; th = np.array(r['1.0']['thick'])[ok]
        for name, f in rules.items():
            pick = f(nv, th)
            R = np.stack([np.array(r[w]['R'])[ok][i] for i, w in enumerate(pick)])
            res.setdefault(name, {}).setdefault(cls, []).append((sfm, med(R, gt[ok])))
for name, pc in res.items():
    notworse = [c for c, v in pc.items() if all(b <= a + 1e-9 for a, b in v)]
    tot = sum(b for c, v in pc.items() if c != 'bottle' for a, b in v)
    cells = ' '.join(f"{c[:5]}:" + '/'.join(f'{b:.1f}' for a, b in v) for c, v in pc.items())
    print(f'{name:22s} notworse {len(notworse):2d} sum {tot:6.1f} | {cells}')
print('sfm', ' '.join(f"{c[:5]}:" + '/'.join(f'{a:.1f}' for a, b in v) for c, v in res['w1.0'].items()))
