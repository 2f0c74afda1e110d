"""Synthetic sequences of a textured plane seen by a moving camera, with exact truth.

`make_sequence(seed, ...)` renders frames from an embedded CC0 image laid on
the plane n · X = d, with a smooth 6-DOF trajectory, optional sudden jumps,
gain drift, an intensity change part-way, an occlusion of the region, blur
and noise, and returns the true template → frame homographies, corners and
poses and whether the region is visible; `lazy=True` renders the frames one
at a time as they are asked for, for long sequences.
"""

from jaxpso._src.synthetic import INTENSITY_CHANGES
from jaxpso._src.synthetic import Sequence
from jaxpso._src.synthetic import make_sequence

__all__ = ("INTENSITY_CHANGES", "Sequence", "make_sequence")
