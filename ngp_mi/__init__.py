"""ngp-mi: the Neural Graphics Pipeline (Chen et al., EG 2021) on Mitsuba 3 / Dr.Jit and PyTorch.

Importing the package is cheap: Mitsuba, Dr.Jit and torch load only when a module needs them
(Mitsuba and Dr.Jit always through :mod:`ngp_mi.backend`).
"""

__version__ = "0.1.0"
