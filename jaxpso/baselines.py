"""Gradient alignment methods behind the same `align`/`track` interface.

Select one with `jaxpso.TrackConfig(method=...)`: "fa" (Lucas–Kanade forward
additive), "fc" (forward compositional), "ic" (inverse compositional), "esm"
(efficient second-order minimisation), "ha" (hyperplane approximation),
"adam" and "lbfgs" (optax on the differentiable similarity) and "ecc"
(OpenCV's findTransformECC); "pso" is the swarm.  `SUPPORTED` says which
motion models and similarities each handles; `ecc` is the plain OpenCV call.
"""

from jaxpso._src.baselines import METHODS
from jaxpso._src.baselines import SUPPORTED
from jaxpso._src.baselines import check_supported
from jaxpso._src.baselines import ecc

__all__ = ("METHODS", "SUPPORTED", "check_supported", "ecc")
