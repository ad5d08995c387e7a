"""Fitting water coefficients to target colours of image regions (re-exports only).

`_colour` colour conversions, `_model` regions and the forward model (residuals),
`_solver` the Levenberg-Marquardt driver, `_rgb` / `_spectral` the two fits, `_config` the
TOML fit config, `_plot` figures and fit.json / fit.png.
"""

from ._colour import SPACES as SPACES
from ._colour import delta_e2000 as delta_e2000
from ._colour import srgb_to_xyz as srgb_to_xyz
from ._colour import to_lab_host as to_lab_host
from ._colour import to_space as to_space
from ._colour import to_srgb_host as to_srgb_host
from ._colour import xyz_to_lab as xyz_to_lab
from ._colour import xyz_to_space as xyz_to_space
from ._config import CONFIG_DOC as CONFIG_DOC
from ._config import FREE as FREE
from ._config import WATER_FIELDS as WATER_FIELDS
from ._config import WATER_FLAGS as WATER_FLAGS
from ._config import FitConfigError as FitConfigError
from ._config import load_fit_config as load_fit_config
from ._model import Region as Region
from ._model import default_uncertainty as default_uncertainty
from ._model import region_colours as region_colours
from ._model import region_colours_fn as region_colours_fn
from ._model import residuals as residuals
from ._model import spectral_region_colours_fn as spectral_region_colours_fn
from ._plot import plot_fit as plot_fit
from ._plot import plot_fit_spectral as plot_fit_spectral
from ._plot import plot_swatches_and_loss as plot_swatches_and_loss
from ._plot import write_outputs as write_outputs
from ._plot import write_outputs_spectral as write_outputs_spectral
from ._rgb import FitResult as FitResult
from ._rgb import fit as fit
from ._solver import Solution as Solution
from ._solver import levenberg_marquardt as levenberg_marquardt
from ._spectral import SpectralFitResult as SpectralFitResult
from ._spectral import absorption_band as absorption_band
from ._spectral import fit_spectral as fit_spectral
