"""The sign of the roughness derivative of an N-direction cache row's specular estimate, point-
sampled (Σ g L, `--specular mc`) against normalised (E · Σ g L / Σ g; E the lobe's directional
albedo, g = f_s cos · weight; session 70's `--specular mc-normalized`, commit 9621f08, reverted:
in runs it did not make roughness learn, BENCHMARKS.md), beside the true
derivative (200 000 directions), under five lights: white, a sky 1 + z, a spot of 15° and of 5°
at the mirror direction, a 15° spot 40° away from it. View 30° off the normal, 300 random
rotations of the Fibonacci cap per roughness. Prints the share of rotations whose derivative is
positive ("rougher gathers more") and the median, for both estimators.
usage: lobe_normalized_sign.py [N]   (default 64, the cache's S)

Throw-away diagnostics (numpy, reuses lobe_sampling_bias.py's lobe and spiral); not part of the
build or tests. Session 70: the normalised estimate has the true sign in every rotation (the sky
at r = 0.1: 90 %; its truth there is −0.0018), its size
smaller than the truth's for lobes narrower than the spacing (r = 0.1 under the 5° spot:
median −0.32 against −26.3); the point-sampled one is positive in 80–99 % of rotations at
r ≤ 0.2 whatever the truth."""
import numpy as np
from lobe_sampling_bias import Z_MIN, directions_argument, fibonacci_cap, specular_cos

n_dirs = directions_argument()
wo = np.array([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
mirror = np.array([-wo[0], 0.0, wo[2]])
away = np.array([np.sin(np.radians(10)), 0.0, np.cos(np.radians(10))])  # 40° from the mirror

def spot(centre, width_deg, peak):
    return lambda d: 1 + peak * np.exp(-(1 - d @ centre) / (1 - np.cos(np.radians(width_deg))))

lights = [('white', lambda d: np.ones(len(d))), ('sky 1 + z', lambda d: 1 + d[:, 2]),
          ('15° spot, mirror', spot(mirror, 15, 20)), ('5° spot, mirror', spot(mirror, 5, 200)),
          ('15° spot, 40° off', spot(away, 15, 20))]
cap = 2 * np.pi * (1 - Z_MIN)
dense = fibonacci_cap(200_000, 0.0)
albedo = lambda r: specular_cos(dense, wo, r).sum() * cap / len(dense)  # E over the cap
rng = np.random.default_rng(0)
eps = 1e-3
derivative = lambda f, r: (f(r + eps) - f(r - eps)) / (2 * eps)
for name, light in lights:
    l_dense = light(dense)
    for r in (0.1, 0.2, 0.3, 0.45, 0.6):
        truth = derivative(lambda rr: (specular_cos(dense, wo, rr) * l_dense).sum() * cap / len(dense), r)
        point, normalised = [], []
        for _ in range(300):
            d = fibonacci_cap(n_dirs, rng.uniform(0, 2 * np.pi))
            l = light(d)
            point.append(derivative(lambda rr: (specular_cos(d, wo, rr) * l).sum() * cap / n_dirs, r))
            normalised.append(derivative(
                lambda rr: albedo(rr) * (specular_cos(d, wo, rr) * l).sum() / specular_cos(d, wo, rr).sum(), r))
        point, normalised = np.array(point), np.array(normalised)
        print(f'{name:18s} r {r:4.2f}: true {truth:+9.4f} | point-sampled: positive {100 * (point > 0).mean():3.0f} %, '
              f'median {np.median(point):+9.4f} | normalised: positive {100 * (normalised > 0).mean():3.0f} %, '
              f'median {np.median(normalised):+9.4f}')
