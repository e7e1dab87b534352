"""How much of a run's albedo error is spatial variation within a material, and how much is each
material's level: eval's masked albedo PSNR (`albedo_psnr_masked`, eval's `albedo_psnr` until
session 60: the per-channel median-scaled `eval/test_*_albedo.png` against the GT `albedo.png`
over the GT mask, mean over views), then the same with our albedo replaced, per GT
material, by its median over all the views (an oracle segmentation: GT colours quantised to
0.05, which parts spheres' white glossy sphere, 0.85, from its checker's light squares, 0.8;
session 53–60 used 0.1), then with each material's level set to the truth's median and its
variation kept (session 79), then per material the mean ours / GT and the coefficient of
variation.
usage: albedo_segments.py DATA RUN/eval [VIEWS]

Throw-away diagnostics (numpy, PIL) for the shared scenes (flat-coloured materials); not part
of the build or tests. Session 53: spheres 19.93 → 25.25 dB, cornell 15.64 → 19.97 dB."""
import sys, numpy as np
from diag_common import args, lin, load

def psnr(a, b):
    return -10 * np.log10(((np.clip(a, 0, 1) - b) ** 2).mean())

data, ev, views = args('albedo_segments.py DATA RUN/eval [VIEWS]', 16)
pairs = []
for k in range(views):
    g = load(f'{data}/test_{k:03d}/albedo.png')
    o = load(f'{ev}/test_{k:03d}_albedo.png')
    if g.shape != o.shape:
        sys.exit(f'{ev}/test_{k:03d}_albedo.png: {o.shape[1]}×{o.shape[0]}, the GT is {g.shape[1]}×{g.shape[0]} '
                 '(evaluate at the dataset\'s size)')
    m = g[..., 3] > 127
    pairs.append((lin(g[..., :3])[m], lin(o[..., :3])[m]))
G = np.concatenate([p[0] for p in pairs])
O = np.concatenate([p[1] for p in pairs])
keys, label, count = np.unique(np.round(G * 20) / 20, axis=0, return_inverse=True, return_counts=True)
label = label.ravel()
median = np.array([np.median(O[label == t], 0) for t in range(len(keys))])
# Each material's level set to the truth's, its variation kept: which of level and variation to fix.
gain = np.array([np.median(G[label == t], 0) for t in range(len(keys))]) / np.maximum(median, 1e-4)
ours, seg, lev, off = [], [], [], 0
for g, o in pairs:
    lab = label[off:off + len(g)]
    off += len(g)
    ours.append(psnr(o, g))
    seg.append(psnr(median[lab], g))
    lev.append(psnr(o * gain[lab], g))
print(f'{ev}: masked albedo PSNR {np.mean(ours):.2f}, with per-material medians {np.mean(seg):.2f}, '
      f'with per-material levels set to the truth\'s {np.mean(lev):.2f}')
for t in np.argsort(-count)[:10]:
    s = label == t
    ratio = O[s].mean(0) / np.maximum(G[s].mean(0), 1e-4)
    cv = O[s].std(0) / np.maximum(O[s].mean(0), 1e-4)
    share = ((O[s] - G[s]) ** 2).sum() / ((O - G) ** 2).sum()
    print(f'  GT ~{keys[t]} {count[t]:7d} px: ours/GT {np.round(ratio, 3)}, CV {np.round(cv, 3)}, '
          f'share of squared error {share:.3f}')
