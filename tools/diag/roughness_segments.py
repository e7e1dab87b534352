"""Where a run's roughness went, per true roughness: eval's `test_*_roughness.png` against the
dataset's `roughness.png` (both linear, 8-bit) over the GT mask, pixels grouped by the true value
quantised to 0.05; per group with at least 300 pixels the median of ours and its 10th / 90th
percentiles.
usage: roughness_segments.py DATA RUN/eval [VIEWS]

Throw-away diagnostics (numpy, PIL); not part of the build or tests. Session 69, the synthetic
spheres (white 0.05, red 0.10, blue 0.30, floor stripes 0.35 / 0.75, green 0.60) at the
defaults: every group ends at 0.38–0.50 from the 0.3 start, the two glossy spheres at 0.41–0.42."""
import numpy as np
from diag_common import args, load

data, ev, views = args('roughness_segments.py DATA RUN/eval [VIEWS]', 16)
groups = {}
for k in range(views):
    gt = load(f'{data}/test_{k:03d}/roughness.png') / 255.0
    ours = load(f'{ev}/test_{k:03d}_roughness.png') / 255.0
    if gt.shape != ours.shape:
        raise SystemExit(f'{ev}/test_{k:03d}_roughness.png: {ours.shape[1]}x{ours.shape[0]}, '
                         f'the dataset\'s is {gt.shape[1]}x{gt.shape[0]}')
    mask = gt[..., 3] > 0.5
    true = np.round(gt[..., 0][mask] / 0.05) * 0.05
    for v in np.unique(true):
        groups.setdefault(round(float(v), 2), []).append(ours[..., 0][mask][true == v])
print(f'{ev}: our roughness per true roughness ({views} views)')
for v in sorted(groups):
    a = np.concatenate(groups[v])
    if len(a) >= 300:
        p10, p50, p90 = np.percentile(a, [10, 50, 90])
        print(f'  true {v:.2f}: {len(a):7d} px, ours median {p50:.3f} (p10 {p10:.3f}, p90 {p90:.3f})')
