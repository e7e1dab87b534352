"""Why a fixed set of uniform directions pushes a glossy roughness up: the derivative, with
respect to roughness r, of an N-direction estimate of the GGX specular integral (a Fibonacci cap
above 10°, turned by a random angle about the normal: one row of the inverse stage's incident
cache), against the true derivative (200 000 directions), under a uniform white env, for a view
30° off the normal. Prints per r the share of 2000 rotations whose derivative is positive
("rougher gathers more") and its median, beside the truth.
usage: lobe_sampling_bias.py [N]   (default 64, the cache's S; the consistency traces 16)

Throw-away diagnostics (numpy); not part of the build or tests. Session 69: at r = 0.1 / 0.2 /
0.3 the 64-direction derivative is positive in 99 / 82 / 60 % of rotations while the true one is
≤ 0; at 0.5 the lobe is resolved (0 %); at views 10°, 50° and 70° off the normal the shares at
r ≤ 0.2 are 80–100 % too (the truth's sign varies). A cache row keeps its rotation until it is
re-traced (at most `--cache-every` 200 iterations later), and meanwhile the optimiser follows
that rotation's sign, so under the cache's lobe a roughness below ≈ 0.4 is pushed up. With the
consistency's 16 directions (fresh each iteration): 99 / 78 / 58 / 18 / 0 % at r = 0.1 / 0.3 /
0.4 / 0.5 / 0.6.
Session 70: a lobe with the true sign (lobe_normalized_sign.py), built into the inverse stage,
left the glossy spheres where this one does, so this sign is not what holds roughness there."""
import sys
import numpy as np

Z_MIN = np.sin(np.radians(10))  # the cache's 10° floor

def fibonacci_cap(n, rotation, z_min=Z_MIN):
    """src/shade/sampling.rs's `fibonacci_cap_jittered` without jitter: uniform in cos θ over the
    cap above the floor, the golden-angle spiral turned by `rotation` about the normal."""
    i = np.arange(n) + 0.5
    z = 1 - (1 - z_min) * i / n
    phi = np.pi * (3 - 5 ** 0.5) * np.arange(n) + rotation
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], 1)

def specular_cos(wi, wo, r):
    """f_s · cos θ_i of radiogs' lobe (GGX D, α = r², height-correlated Smith G, Schlick F with
    f0 0.04), normal +z."""
    a2 = (r * r) ** 2
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    noh, nol, nov = h[:, 2], np.clip(wi[:, 2], 1e-6, 1), np.clip(wo[2], 1e-6, 1)
    d = a2 / (np.pi * (noh * noh * (a2 - 1) + 1) ** 2)
    lam = lambda c: (-1 + np.sqrt(1 + a2 * (1 - c * c) / (c * c))) / 2
    g = 1 / (1 + lam(nol) + lam(nov))
    f = 0.04 + 0.96 * (1 - (wi * h).sum(-1)) ** 5
    return d * g * f / (4 * nov)

def d_estimate(dirs, wo, r, eps=1e-3):
    """d/dr of the uniform-pdf estimate (cap solid angle / N) Σ f_s cos, central difference."""
    e = lambda rr: specular_cos(dirs, wo, rr).sum() * 2 * np.pi * (1 - Z_MIN) / len(dirs)
    return (e(r + eps) - e(r - eps)) / (2 * eps)

def directions_argument():
    """The optional first argument N (directions per estimate, default 64), checked."""
    try:
        n_dirs = int(sys.argv[1]) if len(sys.argv) > 1 else 64
    except ValueError:
        sys.exit(f'N: {sys.argv[1]!r} is not a number of directions')
    if n_dirs < 1:
        sys.exit(f'N: {n_dirs} directions; at least 1')
    return n_dirs

def main():
    n_dirs = directions_argument()
    rng = np.random.default_rng(0)
    wo = np.array([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
    dense = fibonacci_cap(200_000, 0.0)
    for r in (0.1, 0.2, 0.3, 0.4, 0.5, 0.6):
        truth = d_estimate(dense, wo, r)
        per_rotation = []
        for _ in range(2000):
            per_rotation.append(d_estimate(fibonacci_cap(n_dirs, rng.uniform(0, 2 * np.pi)), wo, r))
        per_rotation = np.array(per_rotation)
        print(f'r {r}: true dE/dr {truth:+.4f}; {n_dirs} directions: positive in {100 * (per_rotation > 0).mean():.0f} % '
              f'of rotations, median {np.median(per_rotation):+.4f}')

if __name__ == '__main__':
    main()
