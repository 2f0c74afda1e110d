"""jaxpso: planar region tracking by direct image alignment, searched by a JAX particle swarm.

Public modules: `jaxpso.warp` (homographies, the plane-induced motion model,
image sampling) and `jaxpso.similarity` (SSD, ZNCC, mutual information).
Importing jaxpso does not import OpenCV or matplotlib.
"""

from jaxpso import pso
from jaxpso import similarity
from jaxpso import synthetic
from jaxpso import warp

__version__ = "0.1.0"

__all__ = ("pso", "similarity", "synthetic", "warp", "__version__")
