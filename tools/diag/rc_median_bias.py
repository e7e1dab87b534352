"""How far below its mean the radiometric consistency's target lies where the L1 loss looks for it.
The consistency compares each sampled surfel's SH colour with its rendering equation estimated from
`--rc-rays` directions (a Fibonacci cap above 10°, turned by a random angle each iteration); an L1
loss fits the median of that noisy target, not its mean. Under a learned sun the median estimate
of an unoccluded surfel's irradiance is the one whose few rays miss the sun.
Prints, per env map, normal and ray count, the median / mean of the estimate over 3000 rotations,
the share of rotations under the mean, and the coefficient of variation.
usage: rc_median_bias.py MAP.exr|MAP.hdr [...]   (env RAYS=16,32,64 sets the ray counts)

Throw-away diagnostics (numpy; OpenEXR for .exr; reads maps with env_peak.py and draws the spiral
with lobe_sampling_bias.py, both beside it); not part of the build or tests. Session 74, learned maps
of the synthetic scenes (sun ≈ 26–28 × the map's mean, 2.7 % of the cap holding 30 % of an
up-facing surfel's light): at 16 rays the up-facing median is 0.92 (spheres) / 0.95 (cornell) of
the mean, cv 0.30–0.33; at 32 rays 0.99–1.005, at 64 rays 1.00 (cv 0.02–0.03). The shared scenes'
learned lights have no texel over 10.4 × their mean: up-facing 0.99 (spheres, cv 0.09) and 0.95
(cornell, cv 0.15) at 16 rays.
"""
import os, sys
import numpy as np
from env_peak import read_map                 # .hdr / .exr with clear errors
from lobe_sampling_bias import Z_MIN, fibonacci_cap  # the cache's spiral about +z, its 10° floor


def load_luminance(path):
    return read_map(path).mean(-1)


def lookup(env, d):
    """Bilinear lookup in radiogs' (Blender's) lat-long convention: u = 0.5 − atan2(y, x)/2π,
    row 0 = zenith, texel centres at +0.5 (src/envmap.rs)."""
    h, w = env.shape
    u = (0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi)) % 1.0
    x = u * w - 0.5
    y = np.arccos(np.clip(d[..., 2], -1, 1)) / np.pi * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    at = lambda yy, xx: env[np.clip(yy, 0, h - 1), xx % w]
    return (at(y0, x0) * (1 - fx) * (1 - fy) + at(y0, x0 + 1) * fx * (1 - fy)
            + at(y0 + 1, x0) * (1 - fx) * fy + at(y0 + 1, x0 + 1) * fx * fy)


def spiral(n, count, rotation):
    """The spiral about +z turned onto the normal n, and its weight Ω_cap/S."""
    local = fibonacci_cap(count, rotation)
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    t = np.cross(n, a)
    t /= np.linalg.norm(t)
    b = np.cross(n, t)
    dirs = local[:, :1] * t + local[:, 1:2] * b + local[:, 2:] * n
    return dirs, 2 * np.pi * (1 - Z_MIN) / count


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__.split('\n\n')[0])
    try:
        counts = [int(c) for c in os.environ.get('RAYS', '16,32,64').split(',')]
    except ValueError:
        sys.exit(f"RAYS={os.environ['RAYS']}: expected ray counts separated by commas, e.g. 16,32,64")
    rng = np.random.default_rng(0)
    for path in sys.argv[1:]:
        env = load_luminance(path)
        for normal in ([0, 0, 1.0], [0.7, 0, 0.714], [0, 0.7, 0.714], [-0.7, 0, 0.714], [0, -0.7, 0.714]):
            n = np.array(normal) / np.linalg.norm(normal)
            cells = []
            for count in counts:
                est = np.empty(3000)
                for k in range(est.size):
                    dirs, weight = spiral(n, count, rng.uniform(0, 2 * np.pi))
                    est[k] = (lookup(env, dirs) * (dirs @ n)).sum() * weight
                mean = est.mean()
                cells.append(f'{count} rays: median/mean {np.median(est) / mean:.3f}, '
                             f'under the mean {np.mean(est < mean):.2f}, cv {est.std() / mean:.2f}')
            print(path, np.round(n, 2), ' | '.join(cells))


if __name__ == '__main__':
    main()
