"""UWB ranging error model by propagation class (LOS / NLOS), shaped after Table I of the grid paper.

An error `e` is added to the true distance: `range = distance + e`. Each class is a three-part mixture:

1. a Gaussian core `bias + sigma * N(0, 1)` (LOS: small positive bias of the two-way ranging;
   NLOS: larger bias from the excess delay through or around an obstacle),
2. with probability `tail_prob` an extra positive exponential excess delay of mean `tail_scale`
   (multipath: the first path is attenuated and a later one is detected),
3. with probability `outlier_prob` a gross outlier drawn uniformly in `[outlier_min, outlier_max]`
   (Table I: the NLOS 2-sigma and 3-sigma quantiles of |error| lie at 23.2 and 24.2 m, so about 5 %
   of NLOS errors sit in that narrow band, which needs a concentrated outlier interval of 20-25 m;
   the LOS variance of 1.59 m^2 against a 0.73 m 3-sigma quantile implies ~0.2 % such outliers).

The defaults reproduce Table I's |error| statistics in shape (LOS mean 0.28 m, median 0.21 m; NLOS
mean 3.78 m, median 0.69 m, 2-sigma quantile 23 m) to within about 15 % when sampled i.i.d.
(sampled: LOS 0.26 / 0.21 m, NLOS 3.65 / 0.67 m, NLOS 2-sigma quantile 22.9 m); see
`tests/test_sim.py`. Host-side NumPy: simulation happens once, outside traced code.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np

__all__ = ["ChannelModel", "sample_range_errors"]


class ChannelModel(eqx.Module):
    """Parameters of the LOS / NLOS ranging error mixture. Distances in metres, the rest probabilities.

    Attributes:
        los_bias, los_sigma: mean and standard deviation of the LOS Gaussian core [m].
        los_tail_prob, los_tail_scale: probability and mean [m] of an extra exponential LOS excess delay.
        los_outlier_prob: probability of a gross LOS outlier.
        nlos_bias, nlos_sigma: mean and standard deviation of the NLOS Gaussian core [m].
        nlos_tail_prob, nlos_tail_scale: probability and mean [m] of the NLOS exponential excess delay.
        nlos_outlier_prob: probability of a gross NLOS outlier.
        outlier_min, outlier_max: gross outliers are uniform in this interval [m] (both classes).
    """

    los_bias: float = 0.20
    los_sigma: float = 0.08
    los_tail_prob: float = 0.15
    los_tail_scale: float = 0.12
    los_outlier_prob: float = 0.002
    nlos_bias: float = 0.58
    nlos_sigma: float = 0.12
    nlos_tail_prob: float = 0.30
    nlos_tail_scale: float = 2.5
    nlos_outlier_prob: float = 0.11
    outlier_min: float = 20.0
    outlier_max: float = 25.0


def sample_range_errors(rng: np.random.Generator, los: np.ndarray, model: ChannelModel | None = None) -> np.ndarray:
    """Ranging errors [m] (same shape as `los`, a bool array: True = LOS) to add to true distances.

    Args:
        rng: NumPy random generator (the only source of randomness: same seed, same errors).
        los: bool array of any shape, True where the link is line of sight.
        model: channel parameters; `ChannelModel()` when None.

    Returns:
        float64 array shaped like `los`: core + tail, or a gross outlier, per element. Errors can be
        slightly negative (LOS core); callers clip `distance + error` at zero.
    """
    m = ChannelModel() if model is None else model
    los = np.asarray(los, dtype=bool)
    shape = los.shape

    def pick(a, b):
        return np.where(los, float(a), float(b))

    # Draw every variate for every element (fixed draw order) so the stream does not depend on `los`.
    core = rng.standard_normal(shape)
    u_tail = rng.random(shape)
    expo = rng.standard_exponential(shape)
    u_out = rng.random(shape)
    out_val = rng.uniform(float(m.outlier_min), float(m.outlier_max), shape)

    err = pick(m.los_bias, m.nlos_bias) + pick(m.los_sigma, m.nlos_sigma) * core
    err = err + np.where(u_tail < pick(m.los_tail_prob, m.nlos_tail_prob), expo, 0.0) * pick(
        m.los_tail_scale, m.nlos_tail_scale
    )
    return np.where(u_out < pick(m.los_outlier_prob, m.nlos_outlier_prob), out_val, err)
