"""Shared by albedo_segments.py, indirect_segments.py, roughness_segments.py and shadow_bins.py: sRGB decoding, picture loading and the
DATA DIR [VIEWS] arguments, each bad input said by name."""
import sys, numpy as np
from PIL import Image

def lin(x):
    """8-bit sRGB values → linear."""
    x = x / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)

def load(path, mode='RGBA'):
    try:
        return np.asarray(Image.open(path).convert(mode)).astype(np.float64)
    except OSError as e:
        sys.exit(f'{path}: cannot read ({e.strerror or e})')

def args(usage, default_views):
    """(DATA, DIR, VIEWS) from the command line."""
    if len(sys.argv) not in (3, 4):
        sys.exit(f'usage: {usage}')
    try:
        views = int(sys.argv[3]) if len(sys.argv) > 3 else default_views
    except ValueError:
        sys.exit(f'VIEWS: {sys.argv[3]!r} is not a number of views')
    if views < 1:
        sys.exit(f'VIEWS: {views} must be at least 1')
    return sys.argv[1], sys.argv[2], views
