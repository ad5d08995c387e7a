"""The water medium: free-flight sampling and phase functions.

Free flight (chromatic, unbiased). Distances are sampled proportionally to *scattering*
only: pick a channel c uniformly and draw t ~ sigma_s[c] exp(-sigma_s[c] t); absorption
is applied analytically as the exact factor exp(-sigma_a t). The pdf is the one-sample
MIS (balance) mixture over channels,
    p_scatter(t) = mean_c sigma_s[c] exp(-sigma_s[c] t),   P_pass(t) = mean_c exp(-sigma_s[c] t),
so the per-channel weights are
    scatter:  sigma_s exp(-sigma_t t) / p_scatter(t),   reach surface: exp(-sigma_t t) / P_pass(t).
Absorption-dominated water (sigma_a >> sigma_s in the red) therefore never wastes
samples on absorbed flights, optical depth 100 stays finite, and sigma_s = 0 reduces to
Beer-Lambert exactly. Sampled distances and pdfs are detached; sigma_a and sigma_s stay
attached in the weights, which is what makes d/d sigma unbiased.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _sampling as sampling
from . import _vec as vec
from ._scene import PHASE_HG, PHASE_ISOTROPIC, PHASE_WATER, Water
from ._vec import Vec3

BIG = 1e30


class FreeFlight(NamedTuple):
    t: Array  # distance to the event (scatter) or to the surface
    scatter: Array  # True: a real scattering event before the surface
    weight: Array  # [C] transmittance (times sigma_s at a scatter) / pdf
    pdf: Array  # p_scatter(t) (volume measure along the ray) or P_pass(t_surf)


def scatter_pdf(sigma_s, t):
    """Distance pdf of a scattering event at t (any shape; channels are the last axis of sigma_s)."""
    t = jnp.minimum(t, BIG)[..., None]
    return _channel_mean(sigma_s * jnp.exp(-sigma_s * t))


def pass_prob(sigma_s, t):
    """Probability of flying a distance t without a scattering event (any shape of t)."""
    t = jnp.minimum(t, BIG)[..., None]
    return _channel_mean(jnp.exp(-sigma_s * t))


def _channel_mean(x):
    """Mean over the (few) channels of the last axis, summed one by one: elementwise for
    the compiler, where `jnp.mean` over a short trailing axis would be a reduction kernel
    of its own on the CPU."""
    C = x.shape[-1]
    s = x[..., 0]
    for c in range(1, C):
        s = s + x[..., c]
    return s / C


def transmittance(w: Water, t):
    t = jnp.minimum(t, BIG)
    return jnp.exp(-(w.sigma_a + w.sigma_s) * t)


def sample_free_flight(w: Water, t_surf, u_ch, u_t) -> FreeFlight:
    C = w.sigma_s.shape[-1]
    sig_s = jax.lax.stop_gradient(w.sigma_s)
    c = jnp.minimum((u_ch * C).astype(jnp.int32), C - 1)
    sc = sig_s[c]
    ts = -jnp.log1p(-u_t) / jnp.where(sc > 0, sc, 1.0)
    ts = jnp.where(sc > 0, ts, jnp.inf)
    scatter = ts < t_surf
    t = jnp.where(scatter, ts, t_surf)
    pdf = jnp.where(scatter, scatter_pdf(sig_s, t), pass_prob(sig_s, t))
    tr = transmittance(w, t)
    num = jnp.where(scatter, w.sigma_s * tr, tr)
    weight = jnp.where(pdf > 0, num / jnp.where(pdf > 0, pdf, 1.0), 0.0)
    return FreeFlight(jax.lax.stop_gradient(t), scatter, weight, pdf)


# ---- phase functions: mu = cos(angle between propagation direction d and wi) ----
def phase_eval(kind: int, w: Water, mu):
    if kind == PHASE_ISOTROPIC:
        return jnp.full_like(mu, sampling.INV_4PI)
    if kind == PHASE_HG:
        return sampling.hg_pdf(mu, w.g)
    if kind == PHASE_WATER:
        return sampling.water_phase_pdf(mu, w.b)
    raise ValueError(kind)


def phase_sample(kind: int, w: Water, d: Vec3, u1, u2) -> tuple[Vec3, Array]:
    """Sample wi around propagation direction d; returns (wi, pdf). Weight is exactly 1."""
    if kind == PHASE_ISOTROPIC:
        loc = sampling.isotropic_sample(u1, u2)
    elif kind == PHASE_HG:
        loc = sampling.hg_sample(u1, u2, jax.lax.stop_gradient(w.g))
    elif kind == PHASE_WATER:
        loc = sampling.water_phase_sample(u1, u2, jax.lax.stop_gradient(w.b))
    else:
        raise ValueError(kind)
    wi = vec.to_world(loc, d)
    return wi, jax.lax.stop_gradient(phase_eval(kind, w, loc.z))
