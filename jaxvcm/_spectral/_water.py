"""Water optics from shipped data: pure water, plus a small parametric model of real water.

Units throughout: wavelength lambda in nm (vacuum), coefficients in 1/m.

Pure water (tables in `jaxvcm/data/`, each file cites its source):

* absorption a_w(lambda): Pope & Fry 1997, 380-725 nm every 5 nm, linearly interpolated
  (`pure_water_absorption`; clamped to the end values outside the table);
* scattering b_w(lambda): Zhang, Hu & He 2009 (S = 0, 20 C) through a power-law fit to them,
  b_w = 0.00196 (lambda / 500)^-4.18, which passes within 1.2% of every tabulated value from
  400 to 700 nm and is smooth beyond (`pure_water_scattering`); its phase function is
  3 (1 + p cos^2) / (4 pi (3 + p)) with p = 0.925 (`PURE_WATER_PHASE_B`);
* refractive index n(lambda): Daimon & Masumura 2007 four-term Sellmeier formula at 20 C
  (`water_ior`).

Real water (`WaterModel`): pure water plus the smallest set of terms that pool and sea
scenes need, each one a leaf a fit can adjust (all >= 0; fits should parameterise them in
log space):

* a_cdom exp(-S (lambda - 440)): dissolved organic matter ("yellow substance"), the
  standard single-exponential CDOM spectrum (Bricaud, Morel & Prieur 1981); it absorbs the
  blue, which is what turns clear blue water green. a_cdom in 1/m at 440 nm, S in 1/nm
  (0.014-0.018 typical).
* a_flat: wavelength-independent extra absorption (a crude stand-in for non-algal particles
  and chlorophyll's broad bands); it darkens without shifting hue, the one degree of
  freedom the exponential cannot supply.
* b_p (lambda / 550)^-n: particle scattering, b_p in 1/m at 550 nm, Angstrom-like exponent
  n (0-2; ~1 for small particles, ~0 for large ones), with a Henyey-Greenstein phase of
  asymmetry g (~0.9 in natural waters). Pure-water scattering is ~0.002 /m, so any visible
  haze in a scene comes from this term.
* a_w_scale (default 1): a factor on the Pope & Fry term, for fits that must be free to
  get pure water wrong (e.g. fits/literature_pure_water); leave it at 1 otherwise.

Why not more: the target observables are colours of a few regions at known depths, i.e.
a smooth spectrum of extinction; two absorption shapes (exponential in the blue, flat) on
top of the fixed pure-water spectrum and one power-law scattering term are the fewest
shapes that can move hue, brightness and haze independently; how far they span the Jerlov
types' K_d spectra is what the Jerlov fits (fits/jerlov_types) show. Chlorophyll's 440 and
675 nm bands would be the next term if a fit needed them.

Phase function of the mixture: the core has one phase function per water body, so a
spectral scene uses the HG phase of the particles when b_p > 0 (particle scattering then
dominates pure-water scattering by an order of magnitude or more) and the pure-water phase
otherwise (see `_spectral.spectral_scene`). The exact mixture (b_w p_w + b_p p_HG) / b is
not representable without changing the kernels.

Everything here is pure JAX (jit/grad-able in the wavelengths and the model's leaves); the
tables are loaded once with NumPy.
"""

from __future__ import annotations

import functools
import importlib.resources

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

PURE_WATER_PHASE_B = 0.925  # Zhang et al. 2009: p(theta) ~ 1 + 0.925 cos^2 theta
B_W_500 = 0.00196  # 1/m, Zhang et al. 2009 power-law fit at 500 nm
B_W_EXPONENT = 4.18  # b_w ~ lambda^-4.18


def _read_csv(name: str) -> tuple[list[str], np.ndarray]:
    """(column names, float64 rows) of a '#'-commented CSV file in jaxvcm/data."""
    text = importlib.resources.files("jaxvcm").joinpath("data", name).read_text()
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    header = lines[0].split(",")
    rows = np.array([[float(x) for x in ln.split(",")] for ln in lines[1:]], np.float64)
    return header, rows


@functools.cache
def pope_fry_table() -> tuple[np.ndarray, np.ndarray]:
    """Pure water's absorption as measured by Pope & Fry (1997): the shipped table.

    Returns (wavelengths nm, a_w 1/m), 380-725 nm every 5 nm."""
    _, r = _read_csv("water_absorption_pope_fry_1997.csv")
    return r[:, 0], r[:, 1]


@functools.cache
def sellmeier_coefficients() -> tuple[np.ndarray, np.ndarray]:
    """(B [4], C [4] um^2) of Daimon & Masumura 2007 (20 C)."""
    _, r = _read_csv("water_ior_daimon_masumura_2007.csv")
    return r[:, 1], r[:, 2]


@functools.cache
def jerlov_table() -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """The diffuse attenuation K_d of Jerlov's (1976) water types: the shipped table.

    Returns (water type names, wavelengths nm [7], K_d 1/m [7, types])."""
    h, r = _read_csv("jerlov_1976_kd.csv")
    return tuple(h[1:]), r[:, 0], r[:, 1:]


def _dtype(lam):
    lam = jnp.asarray(lam)
    return lam.dtype if jnp.issubdtype(lam.dtype, jnp.floating) else jnp.float32


def pure_water_absorption(lam: ArrayLike) -> Array:
    """a_w(lambda) in 1/m (Pope & Fry 1997), linear interpolation, any shape of lambda (nm)."""
    dt = _dtype(lam)
    wl, a = pope_fry_table()
    return jnp.interp(jnp.asarray(lam, dt), jnp.asarray(wl, dt), jnp.asarray(a, dt))


def pure_water_scattering(lam: ArrayLike) -> Array:
    """b_w(lambda) in 1/m: Zhang et al. 2009 power law 0.00196 (lambda / 500)^-4.18."""
    lam = jnp.asarray(lam, _dtype(lam))
    return B_W_500 * (lam / 500.0) ** (-B_W_EXPONENT)


def water_ior(lam: ArrayLike) -> Array:
    """Refractive index of pure water at 20 C (Daimon & Masumura 2007), lambda in nm."""
    dt = _dtype(lam)
    B, C = sellmeier_coefficients()
    l2 = (jnp.asarray(lam, dt) / 1000.0)[..., None] ** 2
    n2 = 1.0 + jnp.sum(jnp.asarray(B, dt) * l2 / (l2 - jnp.asarray(C, dt)), axis=-1)
    return jnp.sqrt(n2)


class WaterModel(eqx.Module):
    """Pure water + CDOM-like and flat extra absorption + power-law particle scattering.

        sigma_a(lambda) = a_w_scale a_w(lambda) + a_cdom exp(-S (lambda - 440)) + a_flat
        sigma_s(lambda) = b_w(lambda) + b_p (lambda / 550)^-n_p
        phase of the particles: Henyey-Greenstein, asymmetry g

    Leaves (differentiable): a_cdom [1/m at 440 nm], S [1/nm], a_flat [1/m],
    b_p [1/m at 550 nm], n_p [-], g [-], a_w_scale [-]. a_w_scale multiplies the Pope &
    Fry pure-water term (default 1: the data as published); it exists so that a fit can
    be *wrong* about pure water and show that region colours bring it back to 1
    (fits/literature_pure_water), not as a physical parameter of real water. The static
    flags switch the pure-water terms off (tests that need an exactly grey or purely
    absorbing medium; a_w_scale is then unused). The default instance is pure water.
    """

    a_cdom: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    S: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.015)
    a_flat: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    b_p: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    n_p: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.0)
    g: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.9)
    a_w_scale: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.0)
    pure_absorption: bool = eqx.field(static=True, default=True)
    pure_scattering: bool = eqx.field(static=True, default=True)

    def extra_absorption(self, lam: ArrayLike) -> Array:
        """a_x(lambda) = a_cdom exp(-S (lambda - 440)) + a_flat, 1/m."""
        lam = jnp.asarray(lam, _dtype(lam))
        dt = lam.dtype
        return (self.a_cdom.astype(dt) * jnp.exp(-self.S.astype(dt) * (lam - 440.0))
                + self.a_flat.astype(dt))

    def particle_scattering(self, lam: ArrayLike) -> Array:
        """b_p (lambda / 550)^-n_p, 1/m."""
        lam = jnp.asarray(lam, _dtype(lam))
        dt = lam.dtype
        return self.b_p.astype(dt) * (lam / 550.0) ** (-self.n_p.astype(dt))

    def sigma_a(self, lam: ArrayLike) -> Array:
        a = self.extra_absorption(lam)
        if not self.pure_absorption:
            return a
        a_w = pure_water_absorption(lam)
        return a + self.a_w_scale.astype(a_w.dtype) * a_w

    def sigma_s(self, lam: ArrayLike) -> Array:
        b = self.particle_scattering(lam)
        return b + pure_water_scattering(lam) if self.pure_scattering else b
