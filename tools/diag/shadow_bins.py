"""Are the floor's shadows right? From `oracle_split`'s DUMP pictures (`DUMP=DIR cargo run --release
--example oracle_split -- RUN DATA VIEWS`, best on an `oracle_materials` copy: true materials and
light), our direct light / Cycles' direct light on the floor's interior pixels (grey GT albedo, one
GT colour over the 3 × 3 neighbourhood, neither picture clipped), both divided by the GT albedo and
averaged over R G B, binned by Cycles' direct light in quantiles: 0–5 % is the deepest shadow,
50–100 % the lit floor. The pictures are 8-bit sRGB, so expect a few % of error.
usage: shadow_bins.py DATA DUMP_DIR [VIEWS]

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests.
Session 53, true geometry (`oracle_normals SNAP=0.5`): 1.55 in the deepest shadow with the env
box-filtered to 8 × 16 (the default), 1.08 at full resolution."""
import sys, numpy as np
from diag_common import args, lin, load

data, dump, views = args('shadow_bins.py DATA DUMP_DIR [VIEWS]', 8)
gt_direct, ours_direct = [], []
for k in range(views):
    pic = load(f'{dump}/test_{k:03d}_direct.png', 'RGB')
    albedo = load(f'{data}/test_{k:03d}/albedo.png', 'RGBA')
    h, w = albedo.shape[:2]
    if pic.shape[:2] != (2 * h, 3 * w):
        sys.exit(f'{dump}/test_{k:03d}_direct.png: not a DUMP picture of this dataset\'s {w}×{h} views')
    g, o = lin(pic[:h, :w]), lin(pic[:h, w:2 * w])
    a = lin(albedo[..., :3])
    grey = (albedo[..., 3] > 250) & (np.abs(a - a.mean(-1, keepdims=True)).max(-1) < 0.03)
    interior = np.ones_like(grey)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            interior &= np.abs(np.roll(np.roll(a, dy, 0), dx, 1) - a).max(-1) < 0.02
    sel = grey & interior & (g.mean(-1) < 0.99) & (o.mean(-1) < 0.99)
    gt_direct.append((g[sel] / a[sel]).mean(-1))
    ours_direct.append((o[sel] / a[sel]).mean(-1))
G, O = np.concatenate(gt_direct), np.concatenate(ours_direct)
if G.size == 0:
    sys.exit('no floor pixels found: is DATA the spheres scene?')
edges = np.quantile(G, [0, 0.05, 0.1, 0.25, 0.5, 1])
labels = ['0-5 %', '5-10 %', '10-25 %', '25-50 %', '50-100 %']
print(f'{dump}: {G.size} floor pixels; ours / Cycles direct light by Cycles\' quantile')
for name, lo, hi in zip(labels, edges[:-1], edges[1:]):
    s = (G >= lo) & ((G < hi) if hi < edges[-1] else (G <= hi))
    print(f'  {name:>8}: {O[s].mean() / G[s].mean():.3f}')
