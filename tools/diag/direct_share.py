"""Where a run's light is wrong, split into its direct and indirect parts, binned by how much of
the truth's light at each pixel is direct (deep shadow … full light).

    python3 tools/diag/direct_share.py DATA RUN/eval [VIEWS]

For a `radiogs synth` dataset (its test views carry `direct.exr` and `indirect.exr`, linear RGBA;
needs `pip install openexr`). Per pixel over the GT alpha: the truth's direct and indirect
radiance, ours from eval's `test_NNN_pbr.png` (the whole PBR render) and `test_NNN_indirect.png`
(its L_ind part), both decoded from sRGB; ours direct = PBR − indirect. Printed per bin of the
truth's direct share: pixels, ours / truth for the whole radiance, the indirect and the direct
part (sums over the bin's pixels, channel means). Our PBR render fits the photos, so a direct
part above 1 in the shadow bins says our shading puts too much light there and the albedo
is fitted too dark to make up for it. Last, the truth's own direct light blurred by a Gaussian of
σ = 1 … 4 px (within the mask) over the truth, per bin: the excess a shading that is right but
smeared over a surfel's footprint would show.

Throw-away diagnostics (numpy, PIL, OpenEXR); not part of the build or tests. Session 71,
synthetic spheres at the defaults: direct 3.27 / 1.57 / 1.16 / 1.00 × the truth from deep shadow
to full light, indirect 0.69–0.73 × in the shadows; started from the true light and kept sharp
by sampling its sun (`--env-importance-inverse 0.25`), the shadows' direct excess stays
(3.26 / 1.53); the truth blurred at σ = 3 px shows 3.45 / 1.60 / 1.11 / 0.99. That match is not the cause:
surfels 40 % smaller leave the excess as it was, and `examples/probe_shadow_blur` (session 72)
splits it into the normals at the objects' feet, the traced visibility's leaks and the learned
light; shading once per surfel costs little of it."""
import os, sys
import numpy as np
from diag_common import args, lin, load

BINS = ((0.0, 0.2), (0.2, 0.5), (0.5, 0.8), (0.8, 1.01))
SIGMAS = (1, 2, 3, 4)

def blur(image, mask, sigma):
    """Gaussian blur of an H × W × 3 image within the mask (normalised by the blurred mask)."""
    r = int(3 * sigma)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    num, den = image * mask[..., None], mask.astype(np.float64)
    for axis in (0, 1):
        num = np.apply_along_axis(lambda x: np.convolve(x, k, 'same'), axis, num)
        den = np.apply_along_axis(lambda x: np.convolve(x, k, 'same'), axis, den)
    return num / np.maximum(den, 1e-6)[..., None]

def read_exr(path):
    try:
        import OpenEXR
    except ImportError:
        sys.exit('direct_share.py needs the OpenEXR module: pip install openexr')
    if not os.path.exists(path):
        sys.exit(f'{path}: not found (is this a `radiogs synth` dataset with direct.exr and indirect.exr?)')
    try:
        channels = OpenEXR.File(path).parts[0].channels
    except Exception as e:  # the module raises its own types for unreadable files
        sys.exit(f'{path}: cannot read as OpenEXR ({e})')
    if 'RGBA' not in channels:
        sys.exit(f'{path}: no RGBA channels (found {", ".join(channels)})')
    return np.asarray(channels['RGBA'].pixels, dtype=np.float64)

def main():
    data, evaldir, views = args('direct_share.py DATA RUN/eval [VIEWS]', 16)
    # Per bin: pixels, ours PBR, truth total, ours indirect, truth indirect (channel means, summed).
    sums = np.zeros((len(BINS), 5))
    blurred = np.zeros((len(SIGMAS), len(BINS), 2))  # blurred truth, truth (direct)
    for v in range(views):
        folder = os.path.join(data, f'test_{v:03d}')
        direct, indirect = read_exr(os.path.join(folder, 'direct.exr')), read_exr(os.path.join(folder, 'indirect.exr'))
        pbr = lin(load(os.path.join(evaldir, f'test_{v:03d}_pbr.png'))[..., :3])
        ours_indirect = lin(load(os.path.join(evaldir, f'test_{v:03d}_indirect.png'))[..., :3])
        if pbr.shape[:2] != direct.shape[:2] or ours_indirect.shape[:2] != direct.shape[:2]:
            sys.exit(f'{evaldir}/test_{v:03d}_*.png: {pbr.shape[1]}×{pbr.shape[0]}, the GT is '
                     f'{direct.shape[1]}×{direct.shape[0]} (evaluate at the dataset\'s size)')
        mask = direct[..., 3] > 0.5
        total = direct[..., :3] + indirect[..., :3]
        share = direct[..., :3].mean(-1) / np.maximum(total.mean(-1), 1e-4)
        for b, (lo, hi) in enumerate(BINS):
            sel = mask & (share >= lo) & (share < hi)
            sums[b] += [sel.sum(), pbr[sel].mean(-1).sum(), total[sel].mean(-1).sum(),
                        ours_indirect[sel].mean(-1).sum(), indirect[..., :3][sel].mean(-1).sum()]
        for j, sigma in enumerate(SIGMAS):
            smeared = blur(direct[..., :3], mask, sigma)
            for b, (lo, hi) in enumerate(BINS):
                sel = mask & (share >= lo) & (share < hi)
                blurred[j, b] += [smeared[sel].mean(-1).sum(), direct[..., :3][sel].mean(-1).sum()]
    print(f'{evaldir}: ours / truth per bin of the truth\'s direct share ({views} views)')
    print('direct share     pixels   whole   indirect   direct')
    for (lo, hi), (n, ours, truth, ours_ind, truth_ind) in zip(BINS, sums):
        if n == 0:
            print(f'  {lo:.1f}–{min(hi, 1.0):.1f}  {0:9d}       –          –        –')
            continue
        ratio = lambda a, b: f'{a / b:.3f}' if b > 0 else '–'
        print(f'  {lo:.1f}–{min(hi, 1.0):.1f}  {int(n):9d}   {ratio(ours, truth)}     {ratio(ours_ind, truth_ind)}    '
              f'{ratio(ours - ours_ind, truth - truth_ind)}')
    print('the truth\'s direct light blurred / unblurred, per bin:')
    for sigma, rows in zip(SIGMAS, blurred):
        print(f'  σ = {sigma} px: ' + '  '.join(f'{a / b:.3f}' if b > 0 else '–' for a, b in rows))

if __name__ == '__main__':
    main()
