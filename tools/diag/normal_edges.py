"""Where a run's normal error lies relative to edges, and the metric's own floor.

    python3 tools/diag/normal_edges.py DATA RUN/eval [VIEWS]

Reads eval's `test_NNN_normal.png` (n·0.5 + 0.5) and the dataset's `normal.png` (alpha = mask),
as eval's normal MAE does (mean over all pixels, background 0). Prints
- the floor: the true geometry (README.json's boxes, UV spheres and z-axis cylinders, cast at
  each pixel centre) against `normal.png`, which Cycles renders pixel-filtered, so even the
  true surface sampled at pixel centres misses by this much;
- ours and that truth split by each pixel's distance (1..6 px, 7+) to the nearest jump in the
  ground-truth normal (over 20°) or mask: how much of the MAE is rounded creases and rims.
Session 64: cornell's default run 5.53°, half of it within 6 px of an edge; floor 1.03°.
On a `radiogs synth` dataset (its own object list) only ours is split (session 71)."""
import json, os, sys
import numpy as np
from diag_common import args, load

def hits(objects, o, d):
    """Nearest hit's world normal per ray (NaN where none)."""
    n = len(d)
    t_best, n_best = np.full(n, np.inf), np.full((n, 3), np.nan)
    def keep(t, nrm):
        ok = (t > 1e-6) & (t < t_best)
        t_best[ok] = t[ok]
        n_best[ok] = nrm[ok]
    for ob in objects:
        loc, kind, p = np.array(ob['location']), ob['type'], ob['params']
        if ob['rotation_euler'][0] or ob['rotation_euler'][1]:
            sys.exit(f"{ob['object']}: only rotations about z are supported")
        a = ob['rotation_euler'][2]
        rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        ol, dl = (o - loc) @ rz, d @ rz
        with np.errstate(divide='ignore', invalid='ignore'):
            if kind == 'box':
                he = np.array(p['half_extents'])
                t1, t2 = (-he - ol) / dl, (he - ol) / dl
                tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
                t = np.where(tn.max(1) <= tf.min(1), tn.max(1), np.inf)
                axis = tn.argmax(1)
                nl = np.zeros((n, 3))
                nl[np.arange(n), axis] = -np.sign(dl[np.arange(n), axis])
                keep(t, nl @ rz.T)
            elif kind == 'uv_sphere':
                r = p['radius']
                b, c = (ol * dl).sum(1), (ol * ol).sum(1) - r * r
                disc = b * b - c
                t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
                keep(t, ((ol + t[:, None] * dl) / r) @ rz.T)
            elif kind == 'cylinder':
                r, h = p['radius'], p['depth'] / 2
                for s in (-1.0, 1.0):  # caps
                    t = (s * h - ol[:, 2]) / dl[:, 2]
                    q = ol + t[:, None] * dl
                    t = np.where((q[:, 0] ** 2 + q[:, 1] ** 2 <= r * r) & (s * dl[:, 2] < 0), t, np.inf)
                    keep(t, np.tile([0.0, 0.0, s], (n, 1)) @ rz.T)
                a2 = dl[:, 0] ** 2 + dl[:, 1] ** 2
                b = ol[:, 0] * dl[:, 0] + ol[:, 1] * dl[:, 1]
                disc = b * b - a2 * (ol[:, 0] ** 2 + ol[:, 1] ** 2 - r * r)
                t = (-b - np.sqrt(np.maximum(disc, 0))) / a2
                q = ol + t[:, None] * dl
                t = np.where((disc > 0) & (np.abs(q[:, 2]) <= h), t, np.inf)
                nl = np.stack([q[:, 0] / r, q[:, 1] / r, np.zeros(n)], 1)
                keep(t, nl @ rz.T)
            else:
                sys.exit(f"{ob['object']}: object type {kind!r} is not supported")
    return n_best

def read_json(path):
    try:
        with open(path) as f:
            return json.load(f)
    except OSError as e:
        sys.exit(f'{path}: cannot read ({e.strerror or e})')
    except json.JSONDecodeError as e:
        sys.exit(f'{path}: not JSON ({e})')

def unit(v):
    return v / (np.linalg.norm(v, axis=-1, keepdims=True) + 1e-12)

def angle_error(p, g, mask):
    e = np.degrees(np.arccos(np.clip((unit(p) * g).sum(-1), -1, 1)))
    return np.where(mask & np.isfinite(e), e, np.where(mask, 90.0, 0.0))

def main():
    data, evaldir, views = args('normal_edges.py DATA RUN/eval [VIEWS]', 16)
    meta = read_json(os.path.join(data, 'README.json'))
    # `radiogs synth` writes its own object list (no Blender 'location'/'params'): there the
    # truth-at-pixel-centres column is left out and only ours is split by edge distance.
    blender = all('location' in ob and 'params' in ob for ob in meta.get('objects', []))
    if not blender:
        print(f'{data}/README.json: not a Blender object list (a `radiogs synth` dataset?): '
              'the truth-at-pixel-centres column is left out')
    bands = 7
    sums = {'ours': np.zeros(bands + 1), 'truth': np.zeros(bands + 1)}
    counts, pixels = np.zeros(bands + 1), 0
    for v in range(views):
        folder = os.path.join(data, f'test_{v:03d}')
        cam = read_json(os.path.join(folder, 'metadata.json'))
        c2w = np.array([float(x) for x in cam['cam_transform_mat'].split(',')]).reshape(4, 4)
        w, h = cam['imw'], cam['imh']
        f = w / (2 * np.tan(cam['cam_angle_x'] / 2))
        x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        # Blender camera: looks along −z, +y up.
        d = unit(np.stack([(x - w / 2) / f, -(y - h / 2) / f, -np.ones_like(x)], -1).reshape(-1, 3) @ c2w[:3, :3].T)
        truth = (hits(meta['objects'], np.broadcast_to(c2w[:3, 3], d.shape), d).reshape(h, w, 3)
                 if blender else None)
        gt = load(os.path.join(folder, 'normal.png')) / 255
        mask = gt[..., 3] >= 0.5
        gn = unit(gt[..., :3] * 2 - 1)
        ours = load(os.path.join(evaldir, f'test_{v:03d}_normal.png'), 'RGB') / 255 * 2 - 1
        # Distance band: the smallest square radius r holding a normal or mask jump.
        band = np.full((h, w), bands)
        for r in range(bands - 1, 0, -1):
            near = np.zeros((h, w), bool)
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    sn = np.roll(gn, (dy, dx), (0, 1))
                    sm = np.roll(mask, (dy, dx), (0, 1))
                    near |= ((gn * sn).sum(-1) < np.cos(np.radians(20))) | (sm != mask)
            band[near] = r
        for name, pred in (('ours', ours), ('truth', truth)):
            if pred is None:
                continue
            e = angle_error(pred, gn, mask)
            for b in range(1, bands + 1):
                sums[name][b] += e[(band == b) & mask].sum()
        for b in range(1, bands + 1):
            counts[b] += ((band == b) & mask).sum()
        pixels += w * h
    floor = (f'; the true geometry at pixel centres against normal.png (the floor) '
             f'{sums["truth"].sum() / pixels:.2f}°' if blender else '')
    print(f'{evaldir}: normal MAE {sums["ours"].sum() / pixels:.2f}°{floor} ({views} views)')
    print('px from an edge   pixels   ours: mean°  share°' + ('   truth: mean°  share°' if blender else ''))
    for b in range(1, bands + 1):
        n = max(counts[b], 1)
        label = f'{b}' if b < bands else f'{bands}+'
        truth = f'   {sums["truth"][b] / n:11.1f}  {sums["truth"][b] / pixels:6.2f}' if blender else ''
        print(f'{label:>15}  {counts[b] / pixels * 100:6.1f}%   {sums["ours"][b] / n:10.1f}  {sums["ours"][b] / pixels:6.2f}'
              + truth)

if __name__ == '__main__':
    main()
