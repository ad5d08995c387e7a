"""Colour conversions of the fit: linear sRGB / CIE XYZ / CIELAB, and Delta E 2000.

The JAX conversions (`srgb_to_xyz`, `xyz_to_lab`, `to_space`, `xyz_to_space`) are
differentiable: the residuals of a fit are taken through them. The constants (the sRGB
matrix, the D65 white with Y = 1) come from colour-science, which also does the host-side
work (Lab <-> XYZ for swatches, Delta E 2000 for reports); `xyz_to_lab` is tested against it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

SPACES = ("srgb", "xyz", "lab")  # colour spaces of targets and residuals
_SPACE_NAMES = {"srgb": "linear sRGB", "xyz": "CIE XYZ", "lab": "CIELAB"}

# CIE constants of CIELAB (CIE 15:2004): epsilon = (6/29)^3, kappa = (29/3)^3.
_LAB_EPS = 216.0 / 24389.0
_LAB_KAPPA = 24389.0 / 27.0


def _colour_constants() -> tuple[np.ndarray, np.ndarray]:
    """(linear sRGB -> XYZ matrix [3, 3], D65 white XYZ with Y = 1), from colour-science."""
    import colour

    M = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ, np.float64)
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    white = np.asarray(colour.xyY_to_XYZ([xy[0], xy[1], 1.0]), np.float64)
    return M, white


def target_problem(target, space: str) -> str | None:
    """Why `target` (3 numbers in `space`) cannot be a region's colour, or None.

    Refused: non-finite numbers; in the linear spaces ("srgb", "xyz") a component <= 0 (a
    region's mean colour reaches 0 only through infinitely dark water, so a fit towards it
    runs its coefficients to a bound); in "lab" an L outside (0, 100] (0 is black, 100 the
    white of Y = 1). There is no upper bound on brightness: the brightest a region can be
    has no cheap honest bound (waves focus a sun or a point light into caustics of
    unbounded radiance), so a target brighter than the scene can show is not refused here;
    its fit ends with a coefficient at its bound or fits badly, and says so."""
    t = np.asarray(target, np.float64)
    shown = "[" + ", ".join(f"{x:g}" for x in t) + "]"
    if not np.all(np.isfinite(t)):
        return f"must be finite, got {shown}"
    if space in ("srgb", "xyz") and not np.all(t > 0):
        return (f"must be > 0 in every component in {_SPACE_NAMES[space]} (a region's colour "
                f"is 0 only behind infinitely dark water), got {shown}")
    if space == "lab" and not 0 < t[0] <= 100:
        return f"L must lie in (0, 100] in CIELAB, got {shown}"
    return None


def srgb_to_xyz(rgb, M=None):
    """Linear sRGB [..., 3] -> CIE XYZ [..., 3] (JAX; differentiable)."""
    if M is None:
        M = _colour_constants()[0]
    M = jnp.asarray(M, rgb.dtype)
    return rgb @ M.T


def xyz_to_lab(xyz, white=None):
    """CIE XYZ [..., 3] -> CIELAB [..., 3] (JAX; differentiable), CIE 1976 formula:
    f(t) = t^(1/3) for t > eps, (kappa t + 16) / 116 otherwise, t = X / X_n etc.;
    L = 116 f(Y) - 16, a = 500 (f(X) - f(Y)), b = 200 (f(Y) - f(Z))."""
    if white is None:
        white = _colour_constants()[1]
    t = xyz / jnp.asarray(white, xyz.dtype)
    f = jnp.where(t > _LAB_EPS, jnp.cbrt(jnp.maximum(t, _LAB_EPS)), (_LAB_KAPPA * t + 16.0) / 116.0)
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    return jnp.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)], axis=-1)


def to_space(rgb, space: str):
    """Linear sRGB (JAX) -> `space` ("srgb", "xyz", "lab")."""
    if space == "srgb":
        return rgb
    M, white = _colour_constants()
    xyz = srgb_to_xyz(rgb, M)
    return xyz if space == "xyz" else xyz_to_lab(xyz, white)


def to_lab_host(c, space: str) -> np.ndarray:
    """Colours in `space` -> CIELAB (D65) with colour-science (host, float64)."""
    import colour

    c = np.asarray(c, np.float64)
    if space == "lab":
        return c
    M, white = _colour_constants()
    xyz = c @ M.T if space == "srgb" else c
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    return np.asarray(colour.XYZ_to_Lab(xyz, xy), np.float64)


def to_srgb_host(c, space: str) -> np.ndarray:
    """Colours in `space` -> linear sRGB (host, float64; for swatches)."""
    import colour

    c = np.asarray(c, np.float64)
    if space == "srgb":
        return c
    M, white = _colour_constants()
    if space == "lab":
        xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
        c = np.asarray(colour.Lab_to_XYZ(c, xy), np.float64)
    return c @ np.linalg.inv(M).T


def delta_e2000(a, b, space: str) -> np.ndarray:
    """Delta E 2000 between colours a and b [..., 3] given in `space` (colour-science)."""
    import colour

    return np.asarray(colour.delta_E(to_lab_host(a, space), to_lab_host(b, space),
                                     method="CIE 2000"), np.float64)


def xyz_to_space(xyz, space: str, M=None, white=None):
    """CIE XYZ (JAX) -> `space` ("xyz", "srgb" = linear sRGB, "lab"); the film of a spectral
    render is XYZ."""
    if space == "xyz":
        return xyz
    if M is None or white is None:
        M, white = _colour_constants()
    if space == "srgb":
        return xyz @ jnp.asarray(np.linalg.inv(M), xyz.dtype).T
    return xyz_to_lab(xyz, white)
