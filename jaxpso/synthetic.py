"""Synthetic sequences of a textured plane seen by a moving camera, with exact truth.

`make_sequence(seed, ...)` renders frames from an embedded CC0 image laid on
the plane n · X = d, with a smooth 6-DOF trajectory, optional sudden jumps,
gain drift, an intensity change part-way, blur and noise, and returns the
true template → frame homographies, corners and poses.
"""

from jaxpso._src.synthetic import INTENSITY_CHANGES
from jaxpso._src.synthetic import Sequence
from jaxpso._src.synthetic import make_sequence

__all__ = ("INTENSITY_CHANGES", "Sequence", "make_sequence")
