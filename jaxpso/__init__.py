"""jaxpso: planar region tracking by direct image alignment, searched by a JAX particle swarm.

Public: `track` (a region through a sequence), `align` (one registration:
swarm + Gauss–Newton) with `TrackConfig`, and the modules `jaxpso.warp`
(homographies, the plane-induced motion model, image sampling),
`jaxpso.similarity` (SSD, ZNCC, mutual information), `jaxpso.baselines`
(the gradient methods, `TrackConfig(method=...)`),
`jaxpso.pso` (the swarm optimizer), `jaxpso.synthetic` (test sequences) and
`jaxpso.io` (videos, overlays, results files), `jaxpso.datasets` (the field's benchmarks:
readers, metrics, `evaluate`).
Compiled programs are kept on disk across processes (`cache_dir`, `set_cache_dir`) and the
last used in memory (`set_max_programs`).
Importing jaxpso does not import OpenCV or matplotlib.
"""

from jaxpso._src.align import AlignResult
from jaxpso._src.align import AlignStatus
from jaxpso._src.align import align
from jaxpso._src.config import TrackConfig
from jaxpso._src.detect import detect
from jaxpso._src.evaluation import evaluate
from jaxpso._src.baselines import METHODS
from jaxpso._src.programs import cache_dir
from jaxpso._src.programs import set_cache_dir
from jaxpso._src.programs import set_max_programs
from jaxpso._src.track import TrackResult
from jaxpso._src.track import TrackStatus
from jaxpso._src.track import track
from jaxpso import baselines
from jaxpso import data
from jaxpso import datasets
from jaxpso import io
from jaxpso import pso
from jaxpso import similarity
from jaxpso import synthetic
from jaxpso import warp

__version__ = "0.1.0"

__all__ = ("METHODS", "AlignResult", "AlignStatus", "TrackConfig", "TrackResult", "TrackStatus",
           "align", "baselines", "cache_dir", "data", "datasets", "detect", "evaluate", "io",
           "pso", "set_cache_dir", "set_max_programs", "similarity", "synthetic", "track", "warp",
           "__version__")
