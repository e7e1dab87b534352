"""How sharp a learned light's sun is, against the truth's: power, peak and how much of the power
sits in the brightest texels.

    python3 tools/diag/env_peak.py TRUTH.hdr|TRUTH.exr RUN/envmap.exr

Reads Radiance .hdr (RGBE, run-length encoded or flat) and OpenEXR (an `RGB` or `RGBA` layer;
needs `pip install openexr`) lat-long maps. The truth is also box-filtered to the learned map's
size (its sides must divide the truth's). Per map: its power ∫ L dω (channel mean; solid angle
per texel sin θ Δθ Δφ), its peak texel and the peak over the map's mean, and the share of the
power in the brightest 0.1 / 1 / 5 % of texels.

Throw-away diagnostics (numpy); not part of the build or tests. Session 71, synthetic spheres
under `sky`: the truth at 128 × 64 peaks at 531 × its mean with 22 % of its power in the top
0.1 % of texels; the default run's learned sun 25 × and 3 %, and started at the true light it
decays to 38 × (45 × without the env TV) unless a quarter of the cached directions sample it
(779 ×)."""
import os, sys
import numpy as np

def read_hdr(path):
    try:
        data = open(path, 'rb').read()
    except OSError as e:
        sys.exit(f'{path}: cannot read ({e.strerror or e})')
    if not data.startswith(b'#?'):
        sys.exit(f'{path}: not a Radiance .hdr file (no #? signature)')
    i, line = 0, b''
    while True:
        j = data.find(b'\n', i)
        if j < 0:
            sys.exit(f'{path}: the header never gives the size (-Y H +X W)')
        line, i = data[i:j], j + 1
        if line.startswith(b'-Y '):
            break
    parts = line.split()
    if len(parts) != 4 or parts[2] != b'+X':
        sys.exit(f'{path}: size line {line!r} is not "-Y H +X W"')
    h, w = int(parts[1]), int(parts[3])
    rgbe = np.zeros((h, w, 4), np.uint8)
    try:
        for y in range(h):
            if w >= 8 and data[i] == 2 and data[i + 1] == 2:  # new-style run-length scanline
                i += 4
                for c in range(4):
                    x = 0
                    while x < w:
                        n = data[i]
                        i += 1
                        if n > 128:
                            rgbe[y, x:x + n - 128, c] = data[i]
                            i += 1
                            x += n - 128
                        else:
                            rgbe[y, x:x + n, c] = np.frombuffer(data[i:i + n], np.uint8)
                            i += n
                            x += n
            else:
                rgbe[y] = np.frombuffer(data[i:i + 4 * w], np.uint8).reshape(w, 4)
                i += 4 * w
    except (IndexError, ValueError):
        sys.exit(f'{path}: the pixel data ends early (truncated?)')
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return rgbe[..., :3] * scale[..., None]

def read_exr(path):
    try:
        import OpenEXR
    except ImportError:
        sys.exit('env_peak.py needs the OpenEXR module for .exr files: pip install openexr')
    try:
        channels = OpenEXR.File(path).parts[0].channels
    except Exception as e:  # the module raises its own types for unreadable files
        sys.exit(f'{path}: cannot read as OpenEXR ({e})')
    for name in ('RGB', 'RGBA'):
        if name in channels:
            return np.asarray(channels[name].pixels, dtype=np.float64)[..., :3]
    sys.exit(f'{path}: no RGB or RGBA layer (found {", ".join(channels)})')

def read_map(path):
    ext = os.path.splitext(path)[1].lower()
    if ext == '.hdr':
        return read_hdr(path)
    if ext == '.exr':
        return read_exr(path)
    sys.exit(f'{path}: not a .hdr or .exr file')

def stats(name, env):
    h, w = env.shape[:2]
    theta = (np.arange(h) + 0.5) / h * np.pi
    solid_angle = np.sin(theta)[:, None] * (np.pi / h) * (2 * np.pi / w)
    lum = env.mean(-1)
    power = lum * solid_angle
    total = power.sum()
    peak = np.unravel_index(np.argmax(lum), lum.shape)
    order = np.argsort(-lum.ravel())
    cumulative = np.cumsum(power.ravel()[order]) / max(total, 1e-12)
    top = [cumulative[max(int(q * lum.size) - 1, 0)] for q in (0.001, 0.01, 0.05)]
    print(f'{name}: {w}×{h}, power {total:.3f}, peak {lum.max():.1f} (row {peak[0]}, column {peak[1]}) = '
          f'{lum.max() / lum.mean():.0f} × the mean; power in the top 0.1 / 1 / 5 % of texels '
          f'{top[0]:.2f} / {top[1]:.2f} / {top[2]:.2f}')

def main():
    if len(sys.argv) != 3:
        sys.exit('usage: env_peak.py TRUTH.hdr|TRUTH.exr RUN/envmap.exr')
    truth, ours = read_map(sys.argv[1]), read_map(sys.argv[2])
    (H, W), (h, w) = truth.shape[:2], ours.shape[:2]
    stats('truth', truth)
    if H % h or W % w:
        print(f'(the truth\'s {W}×{H} does not divide into the learned {w}×{h}: no box-filtered line)')
    else:
        stats('truth box-filtered', truth.reshape(h, H // h, w, W // w, 3).mean((1, 3)))
    stats('learned', ours)

if __name__ == '__main__':
    main()
