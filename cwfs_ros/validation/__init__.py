"""Validation against Xin et al. 2015 (Figs. 4-10) and beyond: ``cwfs-ros validate``.

The computations live in small modules, one concern each:

* :mod:`.common`: verdicts, sensor configurations (the paper's 1 mm single-field pair and
  the as-built split sensor), injection of a wavefront term through the primary mirror,
  ray-traced donuts with per-ray deflections (the atmosphere), the geometric limit.
* :mod:`.paper`: the paper's figures (orthogonality, convergence, perturbed telescope,
  linearity, atmosphere against algorithm noise).
* :mod:`.beyond`: the photon-noise floor and the optical-feedback solver's recovery.
* :mod:`.plots`: the figures (matplotlib on an Agg canvas, no pyplot state).
* :mod:`.readings`: the estimator's reading of a corner from a noise-free split pair, which
  the measurement model ``estimator`` is fitted to and checked against.

The entry point (argument parsing, report writing) is :mod:`cwfs_ros.cli.validate`.
"""

# The figures are computed by submodule (the CLI imports them on demand: batoid is heavy).
__all__ = ["beyond", "common", "loop_model", "paper", "plots", "readings"]
