"""95% intervals of what test episodes measure: a success rate and a mean return."""

import math

import numpy as np


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (centre - half, centre + half)


def mean_interval(values: np.ndarray, z: float = 1.96) -> tuple[float, float]:
    """The normal-approximation 95% interval of the mean of ``values`` (the test episodes'
    returns: independent episodes, many of them)."""
    values = np.asarray(values, dtype=np.float64)
    half = z * values.std(ddof=1) / math.sqrt(len(values)) if len(values) > 1 else 0.0
    return float(values.mean() - half), float(values.mean() + half)
