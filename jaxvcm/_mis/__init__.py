"""Multiple importance sampling: the full-path explicit sums (`mis_weight`, the oracle),
the recursive full-path form (`mis_weight_recursive`, a second oracle), and the two forms
the renderer weights its techniques with at their joins, implementations of
`AbstractMIS`: `ExplicitMIS` (partial sums in log space) and `RecursiveMIS` (dVCM / dVC /
dVM carried along the subpaths). `mis_form(cfg)` is the one place that chooses."""

from .._config import RenderConfig
from ._base import AbstractMIS as AbstractMIS
from ._explicit import ExplicitMIS as ExplicitMIS
from ._explicit import Partials
from ._full import mis_weight as mis_weight
from ._recursive import Carried
from ._recursive import RecursiveMIS as RecursiveMIS
from ._recursive import mis_weight_recursive as mis_weight_recursive

SubpathMIS = Partials | Carried  # a form's per-subpath state (`AbstractMIS.subpaths`)


def mis_form(cfg: RenderConfig) -> AbstractMIS:
    """The MIS form `cfg.mis_form` names."""
    return RecursiveMIS() if cfg.mis_form == "recursive" else ExplicitMIS()
