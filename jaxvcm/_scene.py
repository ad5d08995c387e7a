"""Scene pytree: static structure (kinds, counts, sizes) vs differentiable parameters.

Following MJX's `Model`: a field is a pytree leaf iff it is a `jax.Array`; kinds, counts
and image sizes are `eqx.field(static=True)` so that changing them recompiles while
changing a coefficient does not. Shapes are written in the field comments:
R rectangles, S spheres, M materials, W waves, L lights, C spectral channels.

Units: metres, y up. Spectra are arrays of C channels (C = 3, linear RGB, in an RGB
scene; one channel per wavelength in spectral mode); no kernel assumes C = 3.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

# ---- static enumerations ----
MAT_DIFFUSE = 0  # Lambertian, two-sided
MAT_DIELECTRIC = 1  # smooth dielectric with exact Fresnel (the water surface)
MAT_MIRROR = 2  # ideal specular reflector
MAT_GLOSSY = 3  # Lambertian + normalised Phong lobe (SmallVCM's glossy model), two-sided

PHASE_ISOTROPIC = 0
PHASE_HG = 1
PHASE_WATER = 2  # p(mu) = 3 (1 + b mu^2) / (4 pi (3 + b)), b = 0.835 (Morel 1974)

LIGHT_RECT = 0  # one-sided rectangular area light, emits on the side its normal faces
LIGHT_SPHERE = 1  # spherical area light, emits on both sides of its surface
LIGHT_SUN = 2  # directional (delta) light, irradiance on a plane normal to it
LIGHT_SKY = 3  # constant radiance from the upper hemisphere (directions with y > 0)
LIGHT_BACKGROUND = 4  # constant radiance from every direction (SmallVCM's background light)
LIGHT_POINT = 5  # isotropic point light (delta position), intensity I in W/sr
DELTA_LIGHTS = (LIGHT_SUN, LIGHT_POINT)  # no emitter hit: y_0 cannot be reached by a path

LIGHT_NAMES = {LIGHT_RECT: "rect", LIGHT_SPHERE: "sphere", LIGHT_SUN: "sun", LIGHT_SKY: "sky",
               LIGHT_BACKGROUND: "background", LIGHT_POINT: "point"}
MAT_NAMES = {MAT_DIFFUSE: "diffuse", MAT_DIELECTRIC: "dielectric", MAT_MIRROR: "mirror",
             MAT_GLOSSY: "glossy"}
PHASE_NAMES = {PHASE_ISOTROPIC: "isotropic", PHASE_HG: "hg", PHASE_WATER: "water"}

# Shape classes reported by the intersector (static ids).
SHAPE_NONE = -1
SHAPE_RECT = 0
SHAPE_SPHERE = 1
SHAPE_WATER = 2


class Camera(eqx.Module):
    origin: Float[Array, "3"]
    forward: Float[Array, "3"]  # unit view direction
    right: Float[Array, "3"]  # unit, image +x
    up: Float[Array, "3"]  # unit, image +y
    tan_half_fov: Float[Array, ""]  # tan(vertical fov / 2)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)


class Materials(eqx.Module):
    kind: tuple[int, ...] = eqx.field(static=True)  # [M] MAT_*
    albedo: Float[Array, "M C"]  # diffuse reflectance / mirror tint
    # relative IOR inside/outside for dielectrics, 1 otherwise. [M]: one index for every
    # channel. [M C]: a dispersive index per channel (spectral mode, channel 0 = the hero
    # wavelength): refractions follow the hero and terminate the other channels
    # (`_materials.sample_bsdf`).
    ior: Float[Array, "M"] | Float[Array, "M C"]
    # MAT_GLOSSY: the Phong lobe's reflectance k_s [M C] and exponent n [M] (k_s = 0, n = 1
    # for the other kinds); `albedo` is then the Lambertian part k_d
    glossy: Float[Array, "M C"]
    exponent: Float[Array, "M"]
    # [M] or (): True where the material is one-sided (a shape's `two_sided = false`): it
    # scatters only on the side its shape's normal faces and is black from behind, like
    # SmallVCM's and Mitsuba's diffuse; () or all False: every material two-sided (the
    # check is then not in the compiled program)
    one_sided: tuple[bool, ...] = eqx.field(static=True, default=())

    @property
    def dispersive(self) -> bool:
        return self.ior.ndim == 2


class Rects(eqx.Module):
    """Parallelograms p0 + u e1 + v e2, u, v in [0, 1]; normal n = normalize(e1 x e2)."""

    p0: Float[Array, "R 3"]
    e1: Float[Array, "R 3"]
    e2: Float[Array, "R 3"]
    mat: Int[Array, "R"]
    light: Int[Array, "R"]  # index into Lights, -1 if not emissive

    @property
    def count(self) -> int:
        return self.p0.shape[0]


class Spheres(eqx.Module):
    center: Float[Array, "S 3"]
    radius: Float[Array, "S"]
    mat: Int[Array, "S"]
    light: Int[Array, "S"]

    @property
    def count(self) -> int:
        return self.center.shape[0]


class Water(eqx.Module):
    """The pool's water: heightfield surface and the homogeneous medium below it.

    Surface: y = level + sum_i amp_i sin(kx_i x + kz_i z + phase_i) over the footprint
    x in [xmin, xmax], z in [zmin, zmax]. The water body is {footprint, floor < y < surface};
    membership follows from position, so no medium stack is needed.
    """

    enabled: bool = eqx.field(static=True)
    phase_kind: int = eqx.field(static=True)
    level: Float[Array, ""]
    amp: Float[Array, "W"]
    kx: Float[Array, "W"]
    kz: Float[Array, "W"]
    phase0: Float[Array, "W"]
    footprint: Float[Array, "4"]  # xmin, xmax, zmin, zmax
    floor: Float[Array, ""]  # bottom of the water body
    sigma_a: Float[Array, "C"]  # absorption, 1/m
    sigma_s: Float[Array, "C"]  # scattering, 1/m
    g: Float[Array, ""]  # Henyey-Greenstein asymmetry (PHASE_HG)
    b: Float[Array, ""]  # 1 + b cos^2 coefficient (PHASE_WATER)
    ior: Float[Array, ""]  # water / air
    mat: int = eqx.field(static=True)  # material id of the surface (a MAT_DIELECTRIC)

    @property
    def n_waves(self) -> int:
        return self.amp.shape[0]


class Lights(eqx.Module):
    kind: tuple[int, ...] = eqx.field(static=True)  # [L] LIGHT_*
    shape: tuple[int, ...] = eqx.field(static=True)  # [L] rect / sphere index, -1 otherwise
    radiance: Float[Array, "L C"]  # Le for area lights and sky; irradiance E for the sun;
    #                                intensity I (W/sr) for point lights
    direction: Float[Array, "L 3"]  # sun: unit direction light travels; zeros otherwise
    power_weight: Float[Array, "L"]  # unnormalised light-selection weights (see _lights)
    position: Float[Array, "L 3"]  # point lights: the position; zeros otherwise
    # Aimed emission (`_lights.aimed_pdf`): per light, the fraction of its photons aimed at
    # the water's footprint (sun and sky only; the rest start on the scene's bounding
    # disk). () or all 0: no aiming (not in the compiled program).
    aim: tuple[float, ...] = eqx.field(static=True, default=())
    # [G, G] non-negative weights of the footprint's cells (rows z, columns x) that the aimed
    # photons follow; a 1 x 1 map: uniform over the footprint. A sampling decision: detached.
    aim_map: Float[Array, "G G"] | None = None
    # [4] x0, x1, z0, z1: the rectangle of the water's plane the map covers (the footprint,
    # or the part of it a view needs: `_aim.view_guide`)
    aim_rect: Float[Array, "4"] | None = None

    @property
    def count(self) -> int:
        return len(self.kind)


class Scene(eqx.Module):
    """A scene as one pytree: camera, materials, shapes, water and lights.

    The array fields are the differentiable parameters (pytree leaves); kinds, counts,
    image size and the name are static, so changing them recompiles while changing a
    coefficient does not. Build one with `load_scene` or `scene_from_dict`.
    """

    camera: Camera
    materials: Materials
    rects: Rects
    spheres: Spheres
    water: Water
    lights: Lights
    bounds: Float[Array, "2 3"]  # axis-aligned box of the shapes and the water (not the
    #                                camera, not point lights): the infinite lights' disk
    view_radius: Float[Array, ""]  # half the diagonal of the box of the surfaces the camera
    #                                sees (`_io._view`): the merging radius's reference length
    name: str = eqx.field(static=True, default="scene")

    @property
    def channels(self) -> int:
        return self.materials.albedo.shape[-1]


def bounding_sphere(scene: Scene) -> tuple[Array, Array]:
    lo, hi = scene.bounds[0], scene.bounds[1]
    c = 0.5 * (lo + hi)
    return c, 0.5 * jnp.linalg.norm(hi - lo)
