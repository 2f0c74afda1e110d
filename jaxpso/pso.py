"""A vectorised particle swarm optimizer: one compiled step, one `lax.while_loop`.

`run(key, loss_fn, lower, upper, args, config=..., hparams=...)` minimises
`loss_fn(x, args)` over a box; `trace` is the fixed-length `lax.scan` form
with a per-iteration record; `init` and `step` are the pure pieces.  The
termination settings of `PSOConfig` reach the loop as `PSOLimits` arrays, so
changing them does not recompile `run`.
"""

from jaxpso._src.pso import init
from jaxpso._src.pso import run
from jaxpso._src.pso import step
from jaxpso._src.pso import trace
from jaxpso._src.pso_types import BOUNDARIES
from jaxpso._src.pso_types import RNGS
from jaxpso._src.pso_types import TOPOLOGIES
from jaxpso._src.pso_types import VARIANTS
from jaxpso._src.pso_types import PSOConfig
from jaxpso._src.pso_types import PSOHParams
from jaxpso._src.pso_types import PSOLimits
from jaxpso._src.pso_types import PSOResult
from jaxpso._src.pso_types import PSOState
from jaxpso._src.pso_types import PSOTrace
from jaxpso._src.pso_types import Status
from jaxpso._src.pso_types import default_hparams

__all__ = (
    "BOUNDARIES",
    "RNGS",
    "TOPOLOGIES",
    "VARIANTS",
    "PSOConfig",
    "PSOHParams",
    "PSOLimits",
    "PSOResult",
    "PSOState",
    "PSOTrace",
    "Status",
    "default_hparams",
    "init",
    "run",
    "step",
    "trace",
)
