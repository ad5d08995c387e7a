"""Spectral mode: hero wavelengths on the unchanged RGB core, water optics from measured
data (`_water`), albedo and light spectra upsampled at scene load (`_scene`), the spectral
pass and progressive render (`_pass`)."""

from ._pass import SpectralDiagnostics as SpectralDiagnostics
from ._pass import render_pass_spectral as render_pass_spectral
from ._pass import render_pass_spectral_jit as render_pass_spectral_jit
from ._pass import render_spectral as render_spectral
from ._pass import sample_wavelengths as sample_wavelengths
from ._pass import split_pass_key as split_pass_key
from ._pass import xyz_to_srgb as xyz_to_srgb
from ._scene import LAMBDA_MAX as LAMBDA_MAX
from ._scene import LAMBDA_MIN as LAMBDA_MIN
from ._scene import LAMBDA_RANGE as LAMBDA_RANGE
from ._scene import SpectralScene as SpectralScene
from ._scene import cmf_table as cmf_table
from ._scene import spectral_scene as spectral_scene
from ._scene import upsample_emission as upsample_emission
from ._scene import upsample_reflectance as upsample_reflectance
from ._water import WaterModel as WaterModel
from ._water import jerlov_table as jerlov_table
from ._water import pope_fry_table as pope_fry_table
from ._water import pure_water_absorption as pure_water_absorption
from ._water import pure_water_scattering as pure_water_scattering
from ._water import water_ior as water_ior
