"""Spectral mode: hero-wavelength rendering on the unchanged RGB core, film in CIE XYZ.

The core treats the last axis of every spectrum (albedos, light radiance, sigma_a,
sigma_s) as C independent channels and never assumes C = 3. A spectral pass therefore

1. draws one hero wavelength per pass from the pass key, uniform on [380, 720) nm, and
   C - 1 rotations of it by multiples of 340 / C nm (wrapping around the range;
   Wilkie, Nawaz, Droske, Weidlich & Hanika 2014, "Hero wavelength spectral sampling").
   Each lambda_c is marginally uniform, p(lambda_c) = 1 / 340 nm^-1, and together they
   stratify the range. One hero per pass means every pixel of a pass sees the same C
   wavelengths: colour noise is correlated across the image within a pass and averages
   out over passes (each pass is unbiased on its own);
2. instantiates the RGB scene with every spectral quantity evaluated at these C
   wavelengths (`SpectralScene.at_wavelengths`): albedo spectra and light spectra from
   tables precomputed at scene load, water sigma_a = a_w + a_x and sigma_s = b_w + b_p from
   `_water.WaterModel`, the CIE 1931 2 degree colour-matching functions;
3. renders with the unchanged `render_pass` (C channels = C wavelengths; paths are shared
   by all wavelengths, which is exact with one water index for all of them);
4. converts to CIE 1931 XYZ with the estimator
       XYZ = sum_c L(lambda_c) cmf(lambda_c) / (C p(lambda_c)) = (340 / C) sum_c L cmf,
   an unbiased estimate of integral_380^720 L(lambda) cmf(lambda) dlambda for every pass.
   Passes are averaged in XYZ and converted to linear sRGB (colour-science) at the end.

Upsampling at scene load (`spectral_scene`), all with colour-science:

* RGB albedos -> reflectance spectra with the Mallett & Yuksel 2019 sRGB basis
  (`colour.recovery.RGB_to_sd_Mallett2019`): linear in RGB, bounded in [0, 1] for albedos
  in [0, 1], grey stays exactly flat (up to 1e-5), and it round-trips to the same linear
  sRGB under D65 (to ~3e-4).
* Light colours -> emission spectra: the Mallett spectrum of the light's RGB colour times
  D65 (area lights, sky, and the sun by default) or times a blackbody (sun, optional), scaled
  so that the spectrum's luminance Y = integral Le ybar over [380, 720] nm equals the RGB
  light's luminance (sRGB Y row). A white RGB light of 1 is D65 with Y = 1, i.e. linear
  sRGB ~ (1, 1, 1) on the film.

Water: `WaterModel` (pure water + CDOM-like and flat absorption + power-law particle
scattering). One refractive index for the whole scene unless dispersion is on: by default the
Daimon & Masumura n(550 nm) = 1.33468; `ior="scene"` keeps the RGB scene's value and a
number sets it. Phase function: HG with the model's g when b_p > 0, the pure-water phase
(1 + 0.925 cos^2) otherwise (`phase="scene"` keeps the RGB scene's phase).

Dispersion (option, off by default): with one index per scene every wavelength of a path
takes the same refracted direction, so the C channels share one path. With dispersion on,
each wavelength has its own index n(lambda) (Daimon & Masumura, shifted to pass through the
scene's index at 550 nm). Two implementations:

* `dispersion="hero"` (`True`): the hero-wavelength literature's termination (Wilkie et
  al. 2014, sec. 4.3). The core gets one index per channel (`Materials.ior` [M, C]); at a
  refraction through the water surface the path follows the hero wavelength, the other
  channels are terminated and the hero is weighted C (once per full path, however many
  dispersive refractions its two subpaths made), which is the unbiased single-wavelength
  estimator of the hero. Reflections keep every channel (weight R_c / R_h). Paths that
  never refract keep all C wavelengths, so the cost is one pass and only refracted light
  loses the hero's variance reduction.
* `dispersion="exact"`: every wavelength is traced on its OWN path: the pass maps the
  unchanged `render_pass` (`lax.map`) over C single-wavelength scenes with the same core key. No
  wavelength ever follows a refraction computed for another, at C times the cost. It is
  the reference the hero form is tested against.

Light selection uses the RGB scene's power weights (any positive weights are unbiased;
they are detached).
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._scene import LIGHT_SUN, PHASE_HG, PHASE_WATER, Scene
from ._water import PURE_WATER_PHASE_B, WaterModel, water_ior

LAMBDA_MIN = 380.0  # nm
LAMBDA_MAX = 720.0  # nm (exclusive upper end of the hero range)
LAMBDA_RANGE = LAMBDA_MAX - LAMBDA_MIN
GRID_STEP = 1.0  # nm, spacing of the precomputed tables
MAX_WAVELENGTHS = 64  # per pass: each is a channel of every array of the pass
CMFS_NAME = "CIE 1931 2 Degree Standard Observer"


def _shape():
    import colour

    return colour.SpectralShape(LAMBDA_MIN, LAMBDA_MAX, GRID_STEP)


@functools.cache
def _tables() -> dict:
    """colour-science tables on the 1 nm grid 380..720: cmf [K, 3], D65 [K], Mallett basis
    [K, 3] (float64 NumPy)."""
    import colour

    sh = _shape()
    cmfs = colour.MSDS_CMFS[CMFS_NAME].copy().align(sh)
    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(sh)
    basis = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019.copy().align(sh)
    return {"grid": np.asarray(sh.wavelengths, np.float64), "cmf": np.asarray(cmfs.values),
            "d65": np.asarray(d65.values), "basis": basis}


def cmf_table() -> tuple[np.ndarray, np.ndarray]:
    """The CIE 1931 2 degree colour-matching functions of the spectral film.

    Returns (grid nm [K], xbar, ybar, zbar [K, 3]) on the 1 nm grid 380..720 nm."""
    t = _tables()
    return t["grid"], t["cmf"]


def upsample_reflectance(rgb) -> np.ndarray:
    """Linear-sRGB albedo [3] -> reflectance spectrum on the grid [K] (Mallett 2019)."""
    import colour

    sd = colour.recovery.RGB_to_sd_Mallett2019(np.asarray(rgb, np.float64), _tables()["basis"])
    return np.clip(np.asarray(sd.values, np.float64), 0.0, None)


def _srgb_luminance(rgb) -> float:
    import colour

    m = colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ
    return float(np.asarray(m)[1] @ np.asarray(rgb, np.float64))


def upsample_emission(rgb, illuminant: str = "D65", temperature: float = 5778.0) -> np.ndarray:
    """Linear-sRGB light colour [3] -> emission spectrum on the grid [K].

    Mallett(rgb) times D65 or a blackbody at `temperature` K, scaled to the RGB colour's
    luminance."""
    import colour

    t = _tables()
    if illuminant == "D65":
        base = t["d65"]
    elif illuminant == "blackbody":
        base = np.asarray(colour.sd_blackbody(temperature, _shape()).values, np.float64)
    else:
        raise ValueError(f"illuminant: unknown {illuminant!r}; 'D65' or 'blackbody'")
    spec = upsample_reflectance(rgb) * base
    y = np.trapezoid(spec * t["cmf"][:, 1], t["grid"])
    target = _srgb_luminance(rgb)
    return spec * (target / y) if y > 0 else np.zeros_like(spec)


def _interp_rows(lam: Array, table: Array) -> Array:
    """Linear interpolation on the uniform grid: table [..., K] at lam [C] -> [..., C]."""
    K = table.shape[-1]
    x = (lam - LAMBDA_MIN) / GRID_STEP
    i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, K - 2)
    f = jnp.clip(x - i.astype(x.dtype), 0.0, 1.0).astype(table.dtype)
    return table[..., i] * (1 - f) + table[..., i + 1] * f


class SpectralScene(eqx.Module):
    """A scene for spectral mode: an RGB `Scene` plus its spectra on a 1 nm grid.

    The RGB scene holds the geometry, camera and light positions (its spectral leaves are
    replaced per pass, `at_wavelengths`); the spectra are tabulated on the 1 nm grid
    380..720 nm (K = 341 points). Built by `spectral_scene`."""

    scene: Scene
    water: WaterModel
    albedo: Float[Array, "M K"]  # reflectance spectra of the materials
    emission: Float[Array, "L K"]  # Le (area lights, sky) or irradiance E (sun) spectra
    cmf: Float[Array, "K 3"]  # CIE 1931 2 degree xbar, ybar, zbar
    ior: Float[Array, ""]  # the water's (non-dispersive) index
    n_wavelengths: int = eqx.field(static=True, default=8)
    phase_kind: int = eqx.field(static=True, default=PHASE_WATER)
    phase_b: float = eqx.field(static=True, default=PURE_WATER_PHASE_B)
    dispersion: str = eqx.field(static=True, default="off")  # "off" | "hero" | "exact"
    phase_from_scene: bool = eqx.field(static=True, default=False)  # keep the scene's g, b
    glossy: Float[Array, "M K"] | None = None  # the glossy materials' k_s spectra

    def ior_at(self, lam: Array) -> Array:
        """The water's index at lam: `ior` without dispersion; with dispersion the
        Daimon & Masumura curve shifted so that it passes through `ior` at 550 nm."""
        dt = lam.dtype
        if self.dispersion == "off":
            return jnp.broadcast_to(self.ior.astype(dt), lam.shape)
        return water_ior(lam) + (self.ior.astype(dt) - water_ior(jnp.asarray(550.0, dt)))

    def at_wavelengths(self, lam: Float[Array, "C"], ior: Array | None = None) -> Scene:
        """The RGB scene with C = len(lam) channels, one per wavelength, and the water
        index `ior` (default: the non-dispersive `self.ior`)."""
        s = self.scene
        dt = s.bounds.dtype
        lam = lam.astype(dt)
        C = lam.shape[0]
        albedo = _interp_rows(lam, self.albedo.astype(dt))
        emission = _interp_rows(lam, self.emission.astype(dt))
        ior = (self.ior if ior is None else ior).astype(dt)
        # ior [C] (hero dispersion): one index per channel for the water's material
        # (`Materials.ior` [M, C]); the Water record keeps the hero's
        w = s.water
        if w.enabled:
            sig_a = jnp.maximum(self.water.sigma_a(lam).astype(dt), 0.0)
            sig_s = jnp.maximum(self.water.sigma_s(lam).astype(dt), 0.0)
            if self.phase_from_scene:
                g, b = w.g, w.b
            else:
                g = self.water.g.astype(dt) if self.phase_kind == PHASE_HG else w.g
                b = jnp.asarray(self.phase_b, dt) if self.phase_kind == PHASE_WATER else w.b
            if ior.ndim == 1:
                mat_ior = jnp.broadcast_to(s.materials.ior[:, None], (s.materials.ior.shape[0], C))
                mat_ior = mat_ior.astype(dt).at[w.mat].set(ior)
            else:
                mat_ior = s.materials.ior.at[w.mat].set(ior)
        else:
            sig_a = sig_s = jnp.zeros((C,), dt)
            g, b, mat_ior = w.g, w.b, s.materials.ior
        water = dataclasses.replace(w, phase_kind=self.phase_kind if w.enabled else w.phase_kind,
                                    sigma_a=sig_a, sigma_s=sig_s, g=g, b=b,
                                    ior=(ior.reshape(-1)[0] if w.enabled else w.ior))
        glossy = (jnp.zeros((albedo.shape[0], C), dt) if self.glossy is None
                  else _interp_rows(lam, self.glossy.astype(dt)))
        materials = dataclasses.replace(s.materials, albedo=albedo, ior=mat_ior, glossy=glossy)
        lights = dataclasses.replace(s.lights, radiance=emission)
        return dataclasses.replace(s, materials=materials, water=water, lights=lights)

    def xyz_weights(self, lam: Float[Array, "C"]) -> Float[Array, "C 3"]:
        """cmf(lambda_c) / (C p(lambda_c)) with p = 1 / 340 nm^-1."""
        C = lam.shape[0]
        cmf = _interp_rows(lam, self.cmf.T.astype(lam.dtype)).T
        return cmf * (LAMBDA_RANGE / C)


def spectral_scene(scene: Scene, water: WaterModel | None = None, n_wavelengths: int = 8,
                   sun: str = "D65", sun_temperature: float = 5778.0,
                   ior: str | float = "data", phase: str = "auto",
                   dispersion: bool | str = False) -> SpectralScene:
    """Upsample an RGB scene once (host side): albedo and light spectra, water model.

    water:  the `WaterModel` (default: pure water).
    ior:    "data" (Daimon & Masumura n(550 nm)), "scene" (the RGB scene's water index) or a
            number; one index for all wavelengths (no dispersion).
    phase:  "auto" (HG with water.g if b_p > 0, else the pure-water phase) or "scene".
    sun:    "D65" or "blackbody" (at `sun_temperature` K) for sun lights; other lights D65.
    dispersion: False / "off" (default): one index, every wavelength shares each path.
            True / "hero": per-wavelength index n(lambda) (Daimon & Masumura, shifted to
            pass through the chosen index at 550 nm); refractions follow the hero
            wavelength and terminate the others (one pass's cost). "exact": every
            wavelength traced on its own path with its own index (C times the cost).
    """
    modes = {False: "off", True: "hero", "off": "off", "hero": "hero", "exact": "exact"}
    if not isinstance(dispersion, (bool, str)) or dispersion not in modes:
        raise ValueError(f"dispersion: unknown {dispersion!r}; False/'off', True/'hero' or "
                         "'exact'")
    if not 1 <= n_wavelengths <= MAX_WAVELENGTHS:
        raise ValueError(f"n_wavelengths: must lie in [1, {MAX_WAVELENGTHS}], "
                         f"got {n_wavelengths}")
    water = WaterModel() if water is None else water
    dt = scene.bounds.dtype
    albedo = np.stack([upsample_reflectance(a) for a in np.asarray(scene.materials.albedo)])
    glossy = np.stack([upsample_reflectance(a) for a in np.asarray(scene.materials.glossy)])
    emission = np.stack([
        upsample_emission(r, sun if k == LIGHT_SUN else "D65", sun_temperature)
        for k, r in zip(scene.lights.kind, np.asarray(scene.lights.radiance))])
    if ior == "data":
        n = float(water_ior(np.float64(550.0)))
    elif ior == "scene":
        n = float(scene.water.ior)
    else:
        n = float(ior)
    if phase == "auto":
        kind = PHASE_HG if float(np.asarray(water.b_p)) > 0 else PHASE_WATER
        pb = PURE_WATER_PHASE_B
    elif phase == "scene":
        kind, pb = scene.water.phase_kind, float(scene.water.b)
    else:
        raise ValueError(f"phase: unknown {phase!r}; 'auto' or 'scene'")
    A = lambda x: jnp.asarray(np.asarray(x, np.float64), dtype=dt)  # noqa: E731
    water = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dt) if eqx.is_array(x) else x, water)
    return SpectralScene(scene, water, A(albedo), A(emission), A(_tables()["cmf"]), A(n),
                         n_wavelengths, kind, pb, modes[dispersion], phase == "scene",
                         A(glossy))
