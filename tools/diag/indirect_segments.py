"""Where a run's indirect-light error lies: eval's indirect PSNR from its pictures
(`eval/test_*_indirect.png` against `test_*_indirect_gt.png`, both sRGB, over the GT mask, mean
over views), then per GT material (the GT `albedo.png` sRGB colour quantised to 0.05, which
parts spheres' white glossy sphere, 0.93, from its checker's light squares, 0.91), its share of the
squared error and our mean sRGB bias there, and last the PSNR our indirect light would score
multiplied by eval's albedo scale (`RUN/eval/metrics.json`, `pbr_protocol.albedo_scale`): how
much of the error is the albedo's absolute level rather than where the light goes.
usage: indirect_segments.py DATA RUN/eval [VIEWS]

Throw-away diagnostics (numpy, PIL) for the shared scenes; not part of the build or tests.
Session 61, seed 0 at the defaults: spheres 30 % on the checker's light squares (ours too dark),
36 % on the red and blue glossy spheres (too bright), 8 % on the white glossy one (too dark);
cornell 86 % on the white faces (too dark); the albedo scale is worth +0.19 / +0.29 dB."""
import sys, json, numpy as np
from diag_common import args, lin, load

def srgb(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)

def psnr(se, n):
    return -10 * np.log10(se / n)

data, ev, views = args('indirect_segments.py DATA RUN/eval [VIEWS]', 16)
try:
    scale = np.array(json.load(open(f'{ev}/metrics.json'))['pbr_protocol']['albedo_scale'])
except (OSError, KeyError, ValueError) as e:
    sys.exit(f'{ev}/metrics.json: no pbr_protocol.albedo_scale ({e})')
acc, ours, scaled = {}, [], []
tot = 0.0
for k in range(views):
    o = load(f'{ev}/test_{k:03d}_indirect.png', 'RGB') / 255
    g = load(f'{ev}/test_{k:03d}_indirect_gt.png') / 255
    a = load(f'{data}/test_{k:03d}/albedo.png') / 255
    if not (o.shape[:2] == g.shape[:2] == a.shape[:2]):
        sys.exit(f'{ev}/test_{k:03d}_indirect.png: not the size of the GT (evaluate at the dataset\'s size)')
    m = g[..., 3] > 0.5
    d = o - g[..., :3]
    se = (d ** 2).sum(-1)
    ours.append(psnr(se[m].sum(), 3 * m.sum()))
    ds = srgb(lin(o * 255) * scale) - g[..., :3]
    scaled.append(psnr((ds[m] ** 2).sum(), 3 * m.sum()))
    key = np.round(a[..., :3] * 20) / 20
    for c in np.unique(key[m], axis=0):
        s = m & (key == c).all(-1)
        e = acc.setdefault(tuple(c), [0.0, 0, 0.0])
        e[0] += se[s].sum(); e[1] += s.sum(); e[2] += d[s].mean(-1).sum()
    tot += se[m].sum()
print(f'{ev}: indirect PSNR {np.mean(ours):.2f}; × the albedo scale {np.round(scale, 3)}: {np.mean(scaled):.2f}')
for c, (s, n, b) in sorted(acc.items(), key=lambda x: -x[1][0])[:8]:
    print(f'  GT albedo ~{np.array(c)} (sRGB) {n:7d} px: share of squared error {s / tot:.3f}, '
          f'mean bias ours − GT {b / n:+.4f}')
