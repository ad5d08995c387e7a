"""Fitting water coefficients to target colours of image regions (re-exports only)."""

from ._rgb import CONFIG_DOC as CONFIG_DOC
from ._rgb import WATER_FIELDS as WATER_FIELDS
from ._rgb import FitConfigError as FitConfigError
from ._rgb import FitResult as FitResult
from ._rgb import Region as Region
from ._rgb import delta_e2000 as delta_e2000
from ._rgb import fit as fit
from ._rgb import load_fit_config as load_fit_config
from ._rgb import region_colours_fn as region_colours_fn
from ._rgb import to_space as to_space
from ._rgb import write_outputs as write_outputs
from ._spectral import SpectralFitResult as SpectralFitResult
from ._spectral import fit_spectral as fit_spectral
from ._spectral import spectral_region_colours_fn as spectral_region_colours_fn
from ._spectral import write_outputs_spectral as write_outputs_spectral
