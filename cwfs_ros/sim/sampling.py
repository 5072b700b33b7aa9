"""Points on the pupil annulus (and arrival times) for the ray-traced and paraxial renderers.

``"random"``: independent uniform draws, the photon shot noise of as many photons.
``"quasi"``: a scrambled Sobol sequence (scipy.stats.qmc), whose integration error falls
almost as 1 / n instead of 1 / sqrt(n): with no Poisson draw, an (almost) noise-free image,
as the paper's ZEMAX test images, without the moire of a regular grid.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SAMPLINGS", "annulus_samples"]

SAMPLINGS = ("random", "quasi")


def annulus_samples(rng: np.random.Generator, n: int, eps: float, sampling: str = "random",
                    with_time: bool = False) -> tuple[np.ndarray, ...]:
    """``(rho, phi)`` uniform over the area of the annulus ``eps <= rho <= 1``, plus a
    uniform ``u`` in [0, 1) (an arrival time in units of the exposure) if ``with_time``.

    The random draws come in the order rho, phi, u, so a caller keeps its random stream.
    """
    if sampling == "random":
        rho = np.sqrt(rng.uniform(eps * eps, 1.0, n))
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        u = rng.uniform(0.0, 1.0, n) if with_time else None
    elif sampling == "quasi":
        from scipy.stats import qmc

        q = qmc.Sobol(d=3 if with_time else 2, scramble=True, seed=rng).random(n)
        rho = np.sqrt(eps * eps + (1.0 - eps * eps) * q[:, 0])
        phi = 2.0 * np.pi * q[:, 1]
        u = q[:, 2] if with_time else None
    else:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    return (rho, phi) if u is None else (rho, phi, u)
