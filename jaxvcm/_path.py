"""What a technique needs of a path besides its MIS weight: the pdf through a neighbouring
vertex that every join re-evaluates (`reverse_pdf`), light tracing's multiplicity
(`log_n_light_tracing`) and the spectral dispersion factor of joined subpaths
(`both_dispersed`). The weights themselves are `_mis`'s."""

from __future__ import annotations

import jax.numpy as jnp

from . import _subpath as subpath
from ._config import RenderConfig
from ._vec import Vec3, length


def both_dispersed(C: int, a, b):
    """1/C where both subpaths carry the dispersion factor C (it counts once per full path:
    `_materials` doc), else 1. [...] -> [..., 1] to scale [..., C] contributions."""
    return jnp.where(a & b, 1.0 / C, 1.0)[..., None]


def reverse_pdf(scene, kind, mat, n: Vec3, p: Vec3, w_from: Vec3, w_to: Vec3, q: Vec3,
                q_medium, q_n: Vec3, seg_water):
    """p(q | v) in q's area (volume) measure, for one lane: the BSDF / phase pdf at the
    vertex v = (kind, mat, n, p) of scattering a path that arrives from direction `w_from`
    into `w_to` (pointing at q), times the solid angle -> area factor at q
    (`_subpath.to_area`; `seg_water`: the segment v-q runs through the water). Returns
    (area pdf, solid-angle pdf). This is the pdf through the neighbouring vertex that every
    join re-evaluates on both sides."""
    pdf_w = subpath.bsdf_pdf(scene, kind, mat, None, w_from, w_to, n)
    dv = q - p
    d = length(dv)
    return pdf_w * subpath.to_area(1.0, q_medium, q_n, dv / jnp.maximum(d, 1e-30), d,
                                   seg_water, scene.water), pdf_w


def log_n_light_tracing(cfg: RenderConfig, n_paths, dtype):
    """log of light tracing's sample count relative to the camera techniques, per pixel:
    each of the N = pixels * spp light paths splats once (n = N per pixel, Veach 1997
    10.3.4) while a pixel has spp camera paths, so n_LT / n_camera = N / spp = pixels.
    `n_paths` is a chunk's count: every chunk's light paths splat (`Tuning.chunks`)."""
    return jnp.log(jnp.asarray(n_paths * cfg.tuning.chunks // cfg.spp, dtype))


