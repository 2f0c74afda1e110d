"""Video and image-folder input, tracking overlays, result files and plots.

`read_frames` yields the frames of a video file or of a folder of images as
uint8 RGB (or grey) arrays; `draw_overlay` draws a tracked quadrilateral
coloured by its status; `write_video` writes frames to .mp4 or .avi;
`write_results` writes a `jaxpso.track` result as results.csv and
results.json and returns its summary (`summarize`, with `corner_errors` if
the true corners are known); `plot_results` writes a PNG of the error or
score per frame and the template centre's trajectory.  OpenCV and matplotlib
are imported only when these functions run.
"""

from jaxpso._src.results import WITHIN_PX
from jaxpso._src.results import corner_errors
from jaxpso._src.results import plot_results
from jaxpso._src.results import summarize
from jaxpso._src.results import write_results
from jaxpso._src.video import IMAGE_EXTENSIONS
from jaxpso._src.video import STATUS_COLORS
from jaxpso._src.video import VIDEO_CODECS
from jaxpso._src.video import draw_overlay
from jaxpso._src.video import read_frames
from jaxpso._src.video import write_video

__all__ = ("IMAGE_EXTENSIONS", "STATUS_COLORS", "VIDEO_CODECS", "WITHIN_PX", "corner_errors",
           "draw_overlay", "plot_results", "read_frames", "summarize", "write_results",
           "write_video")
