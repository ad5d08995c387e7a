"""The path-sampling core: one bounce of one path, vmapped over rays, scanned over depth.

Camera paths with next-event estimation and MIS (emitter hit vs light sampling),
free-flight sampling in the water, Russian roulette. Per vertex the core also reports
the quantities later techniques need (position, normal / medium flag, throughput,
forward pdf in area/volume measure with RR included, delta flag, alive mask), as the
`Vertex` records stacked by `lax.scan` into [max_depth, N] arrays; unused records are
removed by XLA's dead-code elimination.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from . import _geometry as G
from . import _lights as Lt
from . import _materials as M
from . import _media as Md
from . import _sampling as S
from . import _vec as V
from ._config import RenderConfig
from ._scene import MAT_DIFFUSE, Scene
from ._vec import Vec3

N_UNIFORMS = 9  # random numbers consumed per bounce (layout in `step`)


class PathState(NamedTuple):
    o: Vec3  # origin of the current ray (already offset off its surface)
    p_prev: Vec3  # the vertex the ray left (o without the offset): distances for pdfs
    d: Vec3  # unit direction of the current ray
    beta: Array  # [C] throughput of the path so far (estimator weight, carries gradients)
    L: Array  # [C] radiance gathered so far
    alive: Array  # path still being extended
    in_water: Array  # the current ray travels inside the water body
    pdf_w: Array  # solid-angle pdf with which d was sampled (MIS at emitter hits)
    specular: Array  # d left a delta vertex or the camera: emitter hits take weight 1
    nonfinite: Array  # int32, count of non-finite contributions that were zeroed


class Vertex(NamedTuple):
    p: Vec3  # position of the vertex
    n: Vec3  # geometric normal (surface vertices)
    medium: Array  # True: scattering vertex inside the water
    beta: Array  # [C] throughput arriving at the vertex
    pdf_fwd: Array  # pdf of the vertex in area (surface) or volume (medium) measure
    delta: Array  # the vertex scatters by a delta lobe (mirror / dielectric)
    alive: Array  # the vertex exists


def _offset(p: Vec3, n: Vec3, w: Vec3) -> Vec3:
    """Spawn point on the side of the surface that w points to (avoids self-hits)."""
    scale = 1.0 + jnp.maximum(jnp.maximum(jnp.abs(p.x), jnp.abs(p.y)), jnp.abs(p.z))
    eps = 1e-4 * scale
    s = jnp.where(V.dot(w, n) >= 0, eps, -eps)
    return p + n * s


def _mis(cfg: RenderConfig, a, b):
    return S.power_heuristic(a, b) if cfg.mis == "power" else S.balance_heuristic(a, b)


def init_state(scene: Scene, o: Vec3, d: Vec3) -> PathState:
    dt = o.x.dtype
    C = scene.channels
    return PathState(
        o=o, p_prev=o, d=d,
        beta=jnp.ones((C,), dt), L=jnp.zeros((C,), dt),
        alive=jnp.ones((), bool),
        in_water=G.inside_water(scene.water, o),
        pdf_w=jnp.ones((), dt), specular=jnp.ones((), bool),
        nonfinite=jnp.zeros((), jnp.int32),
    )


def step(scene: Scene, cfg: RenderConfig, depth, s: PathState, u) -> tuple[PathState, Vertex]:
    """Trace segment `depth + 1` of one camera path and scatter at its end.

    Random numbers u[0:9]: 0 channel, 1 distance (free flight); 2 light choice,
    3-4 light point (NEE); 5-6 direction, 7 lobe (BSDF / phase); 8 Russian roulette.
    """
    water = scene.water
    dt = s.o.x.dtype
    C = scene.channels
    kinds = jnp.asarray(scene.materials.kind, jnp.int32)

    # ---- intersect ----
    hit = G.intersect_scene(scene, s.o, s.d, 0.0, jnp.inf, cfg.march_steps)

    # ---- free flight in the water ----
    if water.enabled:
        ff = Md.sample_free_flight(water, hit.t, u[0], u[1])
        scatter = s.alive & s.in_water & ff.scatter
        beta = jnp.where(s.in_water, s.beta * ff.weight, s.beta)
        t = jnp.where(s.in_water, ff.t, hit.t)
        p_dist = jnp.where(s.in_water, ff.pdf, 1.0)
    else:
        scatter = jnp.zeros((), bool)
        beta = s.beta
        t = hit.t
        p_dist = jnp.ones((), dt)
    surf = ~scatter & jnp.isfinite(hit.t)
    esc = ~scatter & ~jnp.isfinite(hit.t)
    p = s.o + s.d * jnp.where(jnp.isfinite(t), t, 0.0)
    wo = -s.d
    n = hit.n

    # Distance from the previous vertex itself (not the offset origin), so that the pdfs of
    # the two strategies MIS compares are evaluated on the same geometry.
    dist = V.length(p - s.p_prev)

    # ---- emission: emitter hit or sky (technique s = 0) ----
    Le_s, pdf_ls = Lt.emitted_surface(scene, hit.light, wo, n, dist)
    Le_e, pdf_le = Lt.emitted_escape(scene, s.d)
    Le = jnp.where(surf, Le_s, jnp.where(esc & ~s.in_water, Le_e, 0.0))
    pdf_l = jnp.where(surf, pdf_ls, pdf_le)
    w_em = jnp.where(s.specular, 1.0, _mis(cfg, s.pdf_w, pdf_l))
    dL = jnp.where(s.alive, beta * Le * w_em, 0.0)

    # ---- vertex ----
    mat = jnp.maximum(hit.mat, 0)
    kind = jnp.where(surf, kinds[mat], -1)
    albedo = scene.materials.albedo[mat]
    ior = scene.materials.ior[mat]
    cos_hit = jnp.abs(V.dot(wo, n))
    safe_t = jnp.where(jnp.isfinite(t) & (dist > 0), dist, 1.0)
    pdf_fwd = s.pdf_w * p_dist * jnp.where(scatter, 1.0, cos_hit) / (safe_t * safe_t)
    vertex = Vertex(p, n, scatter, beta, jax.lax.stop_gradient(pdf_fwd), M.is_delta(kind),
                    s.alive & (scatter | surf))

    # ---- next-event estimation (technique s = 1) ----
    can_nee = s.alive & (scatter | (surf & (kind == MAT_DIFFUSE))) & (depth + 2 <= cfg.max_depth)
    ls = Lt.sample_light(scene, p, u[2], u[3], u[4])
    f_s, pdf_s = M.eval_bsdf(kind, albedo, wo, ls.wi, n)
    if water.enabled:
        ph = Md.phase_eval(water.phase_kind, water, V.dot(s.d, ls.wi))
        f = jnp.where(scatter, ph * jnp.ones((C,), dt), f_s)
        pdf_b = jnp.where(scatter, jax.lax.stop_gradient(ph), pdf_s)
    else:
        f, pdf_b = f_s, pdf_s
    o_sh = V.where(scatter, p, _offset(p, n, ls.wi))
    tmax = jnp.where(jnp.isfinite(ls.dist), ls.dist * (1.0 - 1e-4), jnp.inf)
    vis = G.unoccluded(scene, o_sh, ls.wi, tmax, cfg.march_steps)
    if water.enabled:
        sh_water = scatter | G.inside_water(water, o_sh)
        Tr = jnp.where(sh_water, Md.transmittance(water, ls.dist), 1.0)
    else:
        Tr = 1.0
    w_nee = jnp.where(ls.delta, 1.0, _mis(cfg, ls.pdf_w, pdf_b))
    nee = beta * f * ls.Le * Tr * (w_nee / ls.pdf_w)
    dL = dL + jnp.where(can_nee & ls.valid & vis, nee, 0.0)

    # ---- sample the continuation: BSDF or phase function ----
    bs = M.sample_bsdf(kind, albedo, ior, wo, n, u[5], u[6], u[7], radiance=True)
    if water.enabled:
        wi_ph, pdf_ph = Md.phase_sample(water.phase_kind, water, s.d, u[5], u[6])
        wi = V.where(scatter, wi_ph, bs.wi)
        beta = jnp.where(scatter, beta, beta * bs.weight)
        pdf_w = jnp.where(scatter, pdf_ph, bs.pdf)
    else:
        wi, beta, pdf_w = bs.wi, beta * bs.weight, bs.pdf
    specular = ~scatter & bs.delta
    alive = s.alive & (scatter | surf) & jnp.any(beta > 0)

    # ---- Russian roulette ----
    q = jnp.clip(jax.lax.stop_gradient(jnp.max(beta)), 0.05, 1.0)
    q = jnp.where(depth + 1 >= cfg.rr_depth, q, 1.0)
    alive = alive & (u[8] < q)
    beta = beta / q

    # ---- spawn ----
    o = V.where(scatter, p, _offset(p, n, wi))
    in_water = scatter | G.inside_water(water, o) if water.enabled else s.in_water

    bad = ~jnp.all(jnp.isfinite(dL))
    L = s.L + jnp.where(bad, 0.0, dL)
    state = PathState(o, p, wi, beta, L, alive, in_water, jax.lax.stop_gradient(pdf_w), specular,
                      s.nonfinite + bad.astype(jnp.int32))
    return state, vertex


def trace_camera_paths(scene: Scene, cfg: RenderConfig, o: Vec3, d: Vec3, u) -> tuple[PathState, Vertex]:
    """Trace N camera paths. o, d: batched Vec3 [N]; u: [max_depth, N, N_UNIFORMS]."""
    s0 = jax.vmap(init_state, in_axes=(None, 0, 0))(scene, o, d)
    vstep = jax.vmap(step, in_axes=(None, None, None, 0, 0))

    def body(s, x):
        depth, ud = x
        return vstep(scene, cfg, depth, s, ud)

    depths = jnp.arange(cfg.max_depth, dtype=jnp.int32)
    return jax.lax.scan(body, s0, (depths, u))
