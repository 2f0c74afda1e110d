"""Similarity measures for direct image alignment: SSD, ZNCC and mutual information.

`ssd` is an error (lower is better); `ncc`, `mi` and `nmi` are similarities
(higher is better).  All take `a, b` of shape (..., h, w) with broadcasting
over the leading axes and an optional validity mask, so a swarm of warped
patches is scored as `mi(template[None], patches, mask)`.
"""

from jaxpso._src.similarity import SoftBins
from jaxpso._src.similarity import entropy
from jaxpso._src.similarity import joint_histogram
from jaxpso._src.similarity import mi
from jaxpso._src.similarity import ncc
from jaxpso._src.similarity import nmi
from jaxpso._src.similarity import soft_bins
from jaxpso._src.similarity import ssd

__all__ = (
    "SoftBins",
    "entropy",
    "joint_histogram",
    "mi",
    "ncc",
    "nmi",
    "soft_bins",
    "ssd",
)
