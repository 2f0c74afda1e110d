"""The planar-tracking benchmarks' datasets and metrics, and `evaluate` over them.

`read` loads a dataset in one of `LAYOUTS` (POT-210, PlanarTrack, UCSB, TMT, or the plain
layout for one's own data) as `Sequence`s whose frames stream from disk; `write` writes a
sequence in any layout.  `evaluate` (also `jaxpso.evaluate` and the `jaxpso evaluate` command)
runs trackers over a dataset and scores them as the POT-210 and PlanarTrack toolkits do:
`alignment_errors`, `homography_discrepancies`, `curve`.  `track_features` is the feature
peer (SIFT + RANSAC) used as method "sift".
"""

from jaxpso._src.datasets import LAYOUTS
from jaxpso._src.datasets import PLANARTRACK_ATTRIBUTES
from jaxpso._src.datasets import POT_ATTRIBUTES
from jaxpso._src.datasets import Sequence
from jaxpso._src.datasets import frame_homographies
from jaxpso._src.datasets import read
from jaxpso._src.datasets import write
from jaxpso._src.evaluation import FEATURE_PEER
from jaxpso._src.evaluation import PRECISION_PX
from jaxpso._src.evaluation import PRECISION_RANK_PX
from jaxpso._src.evaluation import SUCCESS_RANK
from jaxpso._src.evaluation import SUCCESS_THRESHOLDS
from jaxpso._src.evaluation import Method
from jaxpso._src.evaluation import Report
from jaxpso._src.evaluation import alignment_errors
from jaxpso._src.evaluation import curve
from jaxpso._src.evaluation import evaluate
from jaxpso._src.evaluation import homography_discrepancies
from jaxpso._src.evaluation import method
from jaxpso._src.evaluation import track_features
from jaxpso._src.evaluation import used_frames

__all__ = ("FEATURE_PEER", "LAYOUTS", "PLANARTRACK_ATTRIBUTES", "POT_ATTRIBUTES", "PRECISION_PX",
           "PRECISION_RANK_PX", "SUCCESS_RANK", "SUCCESS_THRESHOLDS", "Method", "Report",
           "Sequence", "alignment_errors", "curve", "evaluate", "frame_homographies",
           "homography_discrepancies", "method", "read", "track_features", "used_frames",
           "write")
