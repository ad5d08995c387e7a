"""jaxvcm: a differentiable Vertex Connection and Merging renderer for analytic water scenes."""

__version__ = "0.1.0"

from ._config import RenderConfig as RenderConfig
from ._fit import FitResult as FitResult
from ._fit import Region as Region
from ._fit import fit as fit
from ._fit import load_fit_config as load_fit_config
from ._fit_spectral import SpectralFitResult as SpectralFitResult
from ._fit_spectral import fit_spectral as fit_spectral
from ._loader import SceneError as SceneError
from ._loader import load_scene as load_scene
from ._loader import scene_from_dict as scene_from_dict
from ._integrator import PassStats as PassStats
from ._integrator import Technique as Technique
from ._integrator import TechniqueImages as TechniqueImages
from ._integrator import technique_images as technique_images
from ._mis import mis_weight as mis_weight
from ._mis_recursive import mis_weight_recursive as mis_weight_recursive
from ._render import Diagnostics as Diagnostics
from ._render import pass_key as pass_key
from ._render import render as render
from ._render import render_pass as render_pass
from ._render import render_pass_host as render_pass_host
from ._scene import Scene as Scene
from ._spectral import SpectralScene as SpectralScene
from ._spectral import SpectralDiagnostics as SpectralDiagnostics
from ._spectral import render_pass_spectral as render_pass_spectral
from ._spectral import render_pass_spectral_jit as render_pass_spectral_jit
from ._spectral import render_spectral as render_spectral
from ._spectral import spectral_scene as spectral_scene
from ._spectral import WaterModel as WaterModel
from ._reference import fresnel_unpolarised as fresnel_unpolarised
from ._reference import sky_floor_radiance as sky_floor_radiance
from ._spectral import cmf_table as cmf_table
from ._spectral import upsample_emission as upsample_emission
from ._spectral import upsample_reflectance as upsample_reflectance
from ._spectral import jerlov_table as jerlov_table
from ._spectral import pope_fry_table as pope_fry_table
from ._spectral import pure_water_absorption as pure_water_absorption
from ._spectral import pure_water_scattering as pure_water_scattering
from ._spectral import water_ior as water_ior
