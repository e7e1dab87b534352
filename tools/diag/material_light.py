"""Per GT material and channel: is an albedo level wrong because the light we shade it with is?
Our PBR render fits the photos, so where our albedo is k × the truth's, our incident light there
is ≈ 1/k × the truth's. This splits that light into its direct and indirect parts.

    python3 tools/diag/material_light.py DATA RUN/eval [VIEWS]

For a `radiogs synth` dataset (its test views carry `direct.exr`, `indirect.exr`, `normal.exr`
and `albedo.png`; needs `pip install openexr`); on a Cycles dataset, which has no direct pass,
the truth's direct part is the photo (clipped, denoised) minus its indirect pass. Over the fully
covered pixels, per GT material (GT albedo quantised to 0.05) and face (the GT normal's axis, or
curved), sums per channel of: our median-scaled albedo (`test_NNN_albedo.png`) and the truth's;
our direct radiance (`test_NNN_pbr.png` − `test_NNN_indirect.png`) and the truth's; our indirect
radiance and the truth's. Printed: the albedo ratio a, and the incident light that the direct and
indirect radiance ratios imply, D / a and I / a (ours / truth; the specular part of the radiance
is counted as diffuse, so glossy materials read less clean), and the truth's direct share (faces
whose true indirect light is near zero, e.g. the walls' outer faces, print huge I / a: ignore it). The
albedo is median-scaled by eval, so only the ratios *between* materials mean anything: a
material whose D / a sits below the white faces' is shaded with too little direct light,
relative to them.

Session 80 (default runs): on both cornells the green wall's inner face has D / a 0.50–0.76
against the white faces' 1.02–1.19 (its albedo 1.2–1.5 × the truth's).

Throw-away diagnostics (numpy, PIL, OpenEXR); not part of the build or tests."""
import os, sys
import numpy as np
from diag_common import args, lin, load
from direct_share import read_exr

def read_normal(path):
    """The GT normal pass: RGB(A) from `radiogs synth`, X Y Z channels from Cycles."""
    import OpenEXR
    try:
        channels = OpenEXR.File(path).parts[0].channels
    except Exception as e:
        sys.exit(f'{path}: cannot read as OpenEXR ({e})')
    if 'RGBA' in channels:
        return np.asarray(channels['RGBA'].pixels, dtype=np.float64)[..., :3]
    if all(c in channels for c in 'XYZ'):
        return np.stack([np.asarray(channels[c].pixels, dtype=np.float64) for c in 'XYZ'], -1)
    sys.exit(f'{path}: neither RGBA nor X Y Z channels (found {", ".join(channels)})')

def main():
    data, evaldir, views = args('material_light.py DATA RUN/eval [VIEWS]', 16)
    keys_all, rows = [], []
    for v in range(views):
        folder = os.path.join(data, f'test_{v:03d}')
        indirect = read_exr(os.path.join(folder, 'indirect.exr'))
        if os.path.exists(os.path.join(folder, 'direct.exr')):
            direct = read_exr(os.path.join(folder, 'direct.exr'))
        else:
            # A Cycles dataset (no direct pass): the photo minus its indirect pass, its alpha kept.
            photo = load(os.path.join(folder, 'rgba.png'))
            direct = np.concatenate([lin(photo[..., :3]) - indirect[..., :3], photo[..., 3:] / 255], -1)
        gt_albedo = load(os.path.join(folder, 'albedo.png'))
        ours = {name: lin(load(os.path.join(evaldir, f'test_{v:03d}_{name}.png'))[..., :3])
                for name in ('albedo', 'pbr', 'indirect')}
        for name, image in ours.items():
            if image.shape[:2] != direct.shape[:2]:
                sys.exit(f'{evaldir}/test_{v:03d}_{name}.png: {image.shape[1]}×{image.shape[0]}, the GT is '
                         f'{direct.shape[1]}×{direct.shape[0]} (evaluate at the dataset\'s size)')
        # Fully covered pixels only: edges mix materials and the background.
        mask = (direct[..., 3] > 0.99) & (gt_albedo[..., 3] > 250)
        truth_albedo = lin(gt_albedo[..., :3])[mask]
        # Split each material by the face it is on: the GT normal's axis (±x ±y ±z), 6 = curved.
        normal = read_normal(os.path.join(folder, 'normal.exr'))[mask]
        axis = np.argmax(np.abs(normal), 1)
        face = np.where(np.abs(normal).max(1) > 0.95, 2 * axis + (np.take_along_axis(normal, axis[:, None], 1)[:, 0] < 0), 6)
        keys_all.append(np.concatenate([np.round(truth_albedo * 20) / 20, face[:, None]], 1))
        rows.append(np.stack([ours['albedo'][mask], truth_albedo,
                              ours['pbr'][mask] - ours['indirect'][mask], direct[..., :3][mask],
                              ours['indirect'][mask], indirect[..., :3][mask]], 1))
    keys = np.concatenate(keys_all)
    rows = np.concatenate(rows)  # pixels × 6 quantities × 3 channels
    uniq, label, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    label = label.ravel()
    print(f'{evaldir}: ours / truth per GT material and channel (R G B), {views} views')
    print('GT albedo, face               pixels  albedo a            D / a               I / a               '
          'truth direct share')
    for t in np.argsort(-count)[:12]:
        s = rows[label == t].sum(0)
        a = s[0] / np.maximum(s[1], 1e-9)
        d = s[2] / np.maximum(s[3], 1e-9) / a
        i = s[4] / np.maximum(s[5], 1e-9) / a
        share = s[3] / np.maximum(s[3] + s[5], 1e-9)
        fmt = lambda x: ' '.join(f'{c:5.2f}' for c in x)
        face = ('+x', '-x', '+y', '-y', '+z', '-z', 'curved')[int(uniq[t][3])]
        print(f'{str(uniq[t][:3]):18s} {face:6s} {count[t]:7d}  {fmt(a)}   {fmt(d)}   {fmt(i)}   {fmt(share)}')

if __name__ == '__main__':
    main()
