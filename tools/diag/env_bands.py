"""Where a learned light puts its power, against the truth's: shares of ∫ L dω (channel mean) by
elevation band, by 45° of azimuth in the upper hemisphere and 90° in the lower, and each
hemisphere's colour. Both maps are normalised to their own power (the light's scale is free).

    python3 tools/diag/env_bands.py TRUTH.hdr|TRUTH.exr RUN/envmap.exr
    python3 tools/diag/env_bands.py --blur SIGMA_DEG TRUTH.hdr OUT.hdr

Blender lat-long: azimuth atan2(y, x) = (0.5 − u)·360°, +Z up. The truth is box-filtered to the
learned map's size. `--blur` writes the truth at 128 × 64, convolved on the sphere with a
Gaussian of SIGMA_DEG (a sun that our 64 cached directions can sample; the "true light, held"
oracle: `train --env-init-map OUT.hdr --lr-env 0`).

Throw-away diagnostics (numpy; .exr needs `pip install openexr`); not part of the build or tests.
Session 78, the default runs of the four scenes measured (synthetic and shared cornell and
spheres): the learned light puts 0.69–0.85 × the truth's share in the band 0–10° above the
horizon, 1.1–11.5 × at the zenith but on synthetic spheres, and 1.3–7.8 × far below the horizon."""
import os, sys
import numpy as np
from env_peak import read_map

def texel_dirs(h, w):
    """Unit directions and sin θ of an h × w lat-long map's texel centres."""
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (0.5 - (np.arange(w) + 0.5) / w) * 2 * np.pi
    t, p = np.meshgrid(theta, phi, indexing='ij')
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1), np.sin(t)

def box_down(m, h, w):
    H, W, _ = m.shape
    if H % h or W % w:
        sys.exit(f'the truth\'s {W}×{H} does not divide into {w}×{h}')
    return m.reshape(h, H // h, w, W // w, 3).mean(axis=(1, 3))

def write_hdr(path, m):
    """Flat (not run-length encoded) Radiance RGBE."""
    h, w, _ = m.shape
    peak = m.max(axis=2)
    e = np.where(peak > 1e-32, np.floor(np.log2(np.maximum(peak, 1e-32))) + 1, 0)
    scale = np.where(peak > 1e-32, 256.0 / np.exp2(e), 0)
    rgbe = np.zeros((h, w, 4), np.uint8)
    rgbe[..., :3] = np.clip(m * scale[..., None], 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(peak > 1e-32, e + 128, 0).astype(np.uint8)
    tmp = f'{path}.partial'
    try:
        with open(tmp, 'wb') as f:  # written aside, then renamed: never a half-written map
            f.write(b'#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n' % (h, w))
            f.write(rgbe.tobytes())
        os.replace(tmp, path)
    except OSError as e:
        sys.exit(f'{path}: cannot write ({e.strerror or e})')

def blur(truth, sigma_deg, out):
    src = box_down(truth, 128, 256)
    d_src, sin_src = texel_dirs(128, 256)
    d_src, L, sin_src = d_src.reshape(-1, 3), src.reshape(-1, 3), sin_src.reshape(-1)
    d_out = texel_dirs(64, 128)[0].reshape(-1, 3)
    kappa = 1.0 / np.radians(sigma_deg) ** 2
    res = np.zeros((len(d_out), 3))
    for i in range(0, len(d_out), 256):
        wgt = np.exp(kappa * (d_out[i:i + 256] @ d_src.T - 1.0)) * sin_src[None, :]
        res[i:i + 256] = (wgt @ L) / wgt.sum(1, keepdims=True)
    res = res.reshape(64, 128, 3)
    write_hdr(out, res)
    print(f'{out}: 128×64, peak {res.max() / res.mean():.0f} × the mean')

def bands(truth, ours):
    h, w, _ = ours.shape
    t = box_down(truth, h, w)
    _, sin_t = texel_dirs(h, w)
    elevation = 90 - np.degrees((np.arange(h) + 0.5) / h * np.pi)
    azimuth = (0.5 - (np.arange(w) + 0.5) / w) * 360
    power = lambda m, rows, cols: (m.mean(-1) * sin_t)[np.ix_(rows, cols)].sum()
    all_rows, all_cols = np.arange(h), np.arange(w)
    total_o, total_t = power(ours, all_rows, all_cols), power(t, all_rows, all_cols)
    print(f'power ours / truth {total_o / total_t:.3f}; shares below are of each map\'s own power')
    def line(name, rows, cols):
        o, g = power(ours, rows, cols) / total_o, power(t, rows, cols) / total_t
        ratio = f'{o / g:.2f}' if g > 0 else '—'
        print(f'  {name:28} ours {o:.3f}  truth {g:.3f}  ratio {ratio}')
    for lo, hi in ((60, 90), (30, 60), (10, 30), (0, 10), (-30, 0), (-90, -30)):
        line(f'elevation [{lo}, {hi})°', np.where((elevation >= lo) & (elevation < hi))[0], all_cols)
    upper, lower = np.where(elevation >= 0)[0], np.where(elevation < 0)[0]
    for rows, step, name in ((upper, 45, 'upper'), (lower, 90, 'lower')):
        for a in range(-180, 180, step):
            line(f'{name}, azimuth [{a}, {a + step})°', rows, np.where((azimuth >= a) & (azimuth < a + step))[0])
    for rows, name in ((upper, 'upper'), (lower, 'lower')):
        o = (ours[rows] * sin_t[rows][..., None]).sum(axis=(0, 1))
        g = (t[rows] * sin_t[rows][..., None]).sum(axis=(0, 1))
        print(f'  {name} hemisphere rgb shares: ours {np.round(o / o.sum(), 3)}, truth {np.round(g / g.sum(), 3)}')

def main():
    if len(sys.argv) == 5 and sys.argv[1] == '--blur':
        try:
            sigma = float(sys.argv[2])
        except ValueError:
            sys.exit(f'--blur {sys.argv[2]!r}: not a number (degrees)')
        if not 0 < sigma < 90:
            sys.exit(f'--blur {sigma}: must be in (0, 90) degrees')
        blur(read_map(sys.argv[3]), sigma, sys.argv[4])
    elif len(sys.argv) == 3:
        bands(read_map(sys.argv[1]), read_map(sys.argv[2]))
    else:
        sys.exit(__doc__.split('\n\n')[1])

if __name__ == '__main__':
    main()
