"""jaxvcm: a differentiable Vertex Connection and Merging renderer for analytic water scenes.

The public API, in the order of the pipeline: scenes and configuration, the pure pass and
its parts, the progressive drivers, spectral mode and water optics, fitting, input/output.
Everything else is private (`jaxvcm._*`) and may change.
"""

from ._version import __version__ as __version__

# ---- scenes and configuration
from ._config import ALGORITHMS as ALGORITHMS
from ._config import TECHNIQUES as TECHNIQUES
from ._config import RenderConfig as RenderConfig
from ._config import Techniques as Techniques
from ._scene import Scene as Scene
from ._aim import ViewGuide as ViewGuide
from ._aim import aim_at_view as aim_at_view
from ._aim import view_guide as view_guide

# ---- the pure pass, its techniques and MIS weights
from ._integrator import PassStats as PassStats
from ._integrator import Technique as Technique
from ._integrator import TechniqueImages as TechniqueImages
from ._integrator import profile_stages as profile_stages
from ._integrator import technique_images as technique_images
from ._mis import mis_weight as mis_weight
from ._mis import mis_weight_recursive as mis_weight_recursive
from ._render import Diagnostics as Diagnostics
from ._render import pass_key as pass_key
from ._render import render_pass as render_pass

# ---- host-side drivers
from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._host_memory import reuse_host_buffers as reuse_host_buffers
from ._render import render as render
from ._hosts import initialize as initialize_processes
from ._render import render_pass_host as render_pass_host

# ---- spectral mode and water optics
from ._spectral import SpectralDiagnostics as SpectralDiagnostics
from ._spectral import SpectralScene as SpectralScene
from ._spectral import WaterModel as WaterModel
from ._spectral import cmf_table as cmf_table
from ._spectral import jerlov_table as jerlov_table
from ._spectral import pope_fry_table as pope_fry_table
from ._spectral import pure_water_absorption as pure_water_absorption
from ._spectral import pure_water_scattering as pure_water_scattering
from ._spectral import render_pass_spectral as render_pass_spectral
from ._spectral import render_pass_spectral_jit as render_pass_spectral_jit
from ._spectral import render_spectral as render_spectral
from ._spectral import spectral_scene as spectral_scene
from ._spectral import upsample_emission as upsample_emission
from ._spectral import upsample_reflectance as upsample_reflectance
from ._spectral import water_ior as water_ior

# ---- fitting water optics to colours
from ._fit import FitConfigError as FitConfigError
from ._fit import FitResult as FitResult
from ._fit import Region as Region
from ._fit import SpectralFitResult as SpectralFitResult
from ._fit import delta_e2000 as delta_e2000
from ._fit import fit as fit
from ._fit import fit_spectral as fit_spectral
from ._fit import load_fit_config as load_fit_config
from ._fit import region_colours_fn as region_colours_fn
from ._fit import spectral_region_colours_fn as spectral_region_colours_fn
from ._fit import to_space as to_space
from ._fit import write_outputs as write_fit_outputs
from ._fit import write_outputs_spectral as write_spectral_fit_outputs
from ._reference import fresnel_unpolarised as fresnel_unpolarised
from ._reference import sky_floor_radiance as sky_floor_radiance
from ._reference import sun_floor_radiance as sun_floor_radiance

# ---- input / output
from ._io import SceneError as SceneError
from ._io import atomic_path as atomic_path
from ._io import check_outputs as check_outputs
from ._io import load_scene as load_scene
from ._io import read_exr as read_exr
from ._io import recover_outputs as recover_outputs
from ._io import scene_from_dict as scene_from_dict
from ._io import to_srgb8 as to_srgb8
from ._io import water_grid as water_grid
from ._io import write_outputs as write_outputs

# ---- the sorted hash grid (for the grid benchmark)
from ._hashgrid import build as hashgrid_build
from ._hashgrid import query_reduce as hashgrid_query_reduce
from ._hashgrid import sort_order as hashgrid_sort_order
