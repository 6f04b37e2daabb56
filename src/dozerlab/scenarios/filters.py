"""The thesis's height-field smoothing filters (docs/physics.md, path step 3).

Two moving-average filters on a 1-D height profile sampled at equally spaced points:

* a narrow moving average, applied with widths 1, 2 and 4 points, that removes the
  point-to-point roughness of a height field built from discrete particles;
* a moving average applied only where the moving standard deviation is below a threshold
  (width 8 / threshold 0.1 m, then width 64 / threshold 0.01 m), which flattens near-flat
  stretches and leaves slopes and edges alone.

Windows are centred so the filters do not shift features: an odd width ``w`` averages ``w``
points with equal weights; an even width averages ``w + 1`` points with half weights on the two
end points (the centred ``2×w`` moving average of time-series analysis). The signal is padded by
repeating its end values, so a flat signal stays exactly flat up to its ends.
"""

from __future__ import annotations

import numpy as np

#: Widths (points) of the three narrow moving averages.
NARROW_WIDTHS: tuple[int, ...] = (1, 2, 4)
#: (width in points, standard-deviation threshold in m) of the two gated moving averages.
GATED_PASSES: tuple[tuple[int, float], ...] = ((8, 0.1), (64, 0.01))


def _kernel(width: int) -> np.ndarray:
    """Centred averaging weights for ``width`` points (sum 1; see the module docstring)."""
    if width < 1:
        raise ValueError(f"filter width must be >= 1 point, got {width}")
    if width % 2:
        return np.full(width, 1.0 / width)
    k = np.ones(width + 1)
    k[0] = k[-1] = 0.5
    return k / width


def _convolve(signal: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    half = len(kernel) // 2
    padded = np.pad(signal, half, mode="edge")
    return np.convolve(padded, kernel, mode="valid")


def _as_profile(signal: np.ndarray) -> np.ndarray:
    h = np.ascontiguousarray(signal, dtype=np.float64)
    if h.ndim != 1 or h.size == 0:
        raise ValueError(f"height profile must be a non-empty 1-D array, got shape {h.shape}")
    return h


def moving_average(signal: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average of a 1-D profile (shape (n,)) over ``width`` points."""
    return _convolve(_as_profile(signal), _kernel(width))


def moving_std(signal: np.ndarray, width: int) -> np.ndarray:
    """Centred moving standard deviation (same windows as :func:`moving_average`)."""
    h = _as_profile(signal)
    k = _kernel(width)
    var = _convolve(h * h, k) - _convolve(h, k) ** 2
    return np.sqrt(np.maximum(var, 0.0))


def gated_average(signal: np.ndarray, width: int, threshold: float) -> np.ndarray:
    """Moving average over ``width`` points applied only where the moving std < ``threshold`` (m)."""
    if threshold <= 0:
        raise ValueError(f"standard-deviation threshold must be > 0, got {threshold}")
    h = _as_profile(signal)
    return np.where(moving_std(h, width) < threshold, moving_average(h, width), h)


def smooth_height(signal: np.ndarray) -> np.ndarray:
    """The thesis's full filter chain: narrow averages 1, 2, 4, then gated 8/0.1 and 64/0.01."""
    h = _as_profile(signal)
    for width in NARROW_WIDTHS:
        h = moving_average(h, width)
    for width, threshold in GATED_PASSES:
        h = gated_average(h, width, threshold)
    return h
