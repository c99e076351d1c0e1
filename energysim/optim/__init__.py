"""Deprecated alias of `energysim.solvers`, kept so that existing imports keep working."""

import warnings

from energysim.solvers import *  # noqa: F403
from energysim.solvers import __all__  # noqa: F401

warnings.warn(
    "energysim.optim is now energysim.solvers; import from there (or use es.NewtonCG, es.LBFGS, es.Adam)",
    DeprecationWarning,
    stacklevel=2,
)
