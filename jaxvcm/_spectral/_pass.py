"""Spectral passes: hero wavelengths drawn per pass, the RGB core rendered at them, the
film in CIE 1931 XYZ (the estimator is derived in `_spectral/_scene.py`'s docstring), and
the progressive spectral render on the one host driver (`_render.progressive`)."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .. import _memory
from .._config import RenderConfig
from .._integrator import min_chunks
from .._render import Diagnostics, check_budget, pass_key, progressive, render_pass, with_retry
from ._scene import LAMBDA_MIN, LAMBDA_RANGE, SpectralScene


def sample_wavelengths(key: PRNGKeyArray, n: int, dtype=jnp.float32) -> Array:
    """Hero wavelength uniform on [380, 720) and its n - 1 equally spaced rotations [n]."""
    u = jax.random.uniform(key, (), dtype)
    offs = jnp.arange(n, dtype=dtype) / n
    return LAMBDA_MIN + LAMBDA_RANGE * jnp.mod(u + offs, 1.0)


def split_pass_key(key: PRNGKeyArray) -> tuple[PRNGKeyArray, PRNGKeyArray]:
    """(wavelength key, key handed to the core's `render_pass`) of one spectral pass."""
    k_lam, k_render = jax.random.split(key)
    return k_lam, k_render


class SpectralDiagnostics(eqx.Module):
    """What a spectral pass reports besides its XYZ image.

    The core pass's diagnostics, the pass's wavelengths and its radiance per wavelength."""

    core: Diagnostics  # the core's per-pass diagnostics
    wavelengths: Float[Array, "C"]  # nm, the pass's hero wavelength first
    radiance: Float[Array, "H W C"]  # the raw per-wavelength radiance of the pass


def render_pass_spectral(spectral: SpectralScene, key: PRNGKeyArray,
                         config: RenderConfig = RenderConfig(), pass_index=0
                         ) -> tuple[Float[Array, "H W 3"], SpectralDiagnostics]:
    """One spectral pass: an unbiased per-pixel estimate of CIE 1931 XYZ (over 380-720 nm).

    Pure and jit/vmap/grad-able (config is static); shapes depend only on the static
    n_wavelengths and the image size."""
    k_lam, k_render = split_pass_key(key)
    lam = sample_wavelengths(k_lam, spectral.n_wavelengths, spectral.scene.bounds.dtype)
    if spectral.dispersion == "off":
        scene_c = spectral.at_wavelengths(lam)
        L, diag = render_pass(scene_c, k_render, config, pass_index)
    elif spectral.dispersion == "hero":
        scene_c = spectral.at_wavelengths(lam, spectral.ior_at(lam))
        L, diag = render_pass(scene_c, k_render, config, pass_index)
    else:
        # one single-wavelength scene per wavelength, each with its own index; the same core
        # key for all (correlated, each one unbiased)
        def one(l1, n1):
            return render_pass(spectral.at_wavelengths(l1, n1), k_render, config, pass_index)

        # lax.map, not vmap: keeps the work queues' lax.cond skips (`_queue`)
        Ls, diags = jax.lax.map(lambda a: one(*a), (lam[:, None], spectral.ior_at(lam)))
        L = jnp.moveaxis(Ls[..., 0], 0, -1)
        diag = jax.tree_util.tree_map(
            lambda x: jnp.any(x) if x.dtype == jnp.bool_ else jnp.sum(x).astype(x.dtype), diags)
    xyz = L @ spectral.xyz_weights(lam).astype(L.dtype)
    return xyz, SpectralDiagnostics(diag, lam, L)


@functools.partial(jax.jit, static_argnums=(2,))
def render_pass_spectral_jit(spectral, key, config, pass_index=0):
    """`render_pass_spectral` jitted with `config` static: the pass `render_spectral` runs."""
    return render_pass_spectral(spectral, key, config, pass_index)


def xyz_to_srgb(xyz) -> np.ndarray:
    """CIE XYZ (Y = 1 for the white of a unit white light) -> linear sRGB (colour-science)."""
    import colour

    return np.asarray(colour.XYZ_to_RGB(np.asarray(xyz, np.float64), "sRGB"))


def render_spectral(spectral: SpectralScene, passes: int | None = 16, seed: int = 0,
                    config: RenderConfig | None = None, out: str | None = None,
                    exposure: float = 0.0, time: float | None = None,
                    snapshot_every: float | None = None, progress: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Render a spectral scene progressively: passes averaged in CIE XYZ, output in sRGB.

    The one host driver (`_render.progressive`: the same pass keys `pass_key(seed, i)`,
    merge-capacity re-runs, time budget, snapshots and progress as `render`): passes are
    averaged in XYZ and converted to linear sRGB (colour-science) for the outputs. Returns
    (linear sRGB [H, W, 3], XYZ [H, W, 3]); with `out`, writes the sRGB image as EXR + PNG
    + JSON. An image whose host buffers exceed the host's memory is refused before any
    pass (`_memory.check_host`), and a pass too large for int32 indices is traced in
    chunks (`_integrator.min_chunks`); the pass's memory is not budgeted (one chunk)."""
    check_budget(passes, time)
    config = config or RenderConfig()
    _memory.check_host(spectral.scene)  # refused before anything runs
    if config.tuning.chunks == 1:  # as many chunks as keep the indices within int32
        config = config.tuned(chunks=min_chunks(spectral.scene, config))
    state = {"config": config}

    def run_pass(i):
        xyz, diag, state["config"] = with_retry(render_pass_spectral_jit, spectral,
                                                pass_key(seed, i), state["config"], i,
                                                lambda d: d.core, spectral.scene)
        return xyz, diag.core.nonfinite

    def meta(n, seconds, nonfinite, snapshot):
        cfg = state["config"]
        return {"scene_name": spectral.scene.name, "mode": "spectral",
                "n_wavelengths": spectral.n_wavelengths, "algorithm": cfg.algorithm,
                "config": cfg.record(), "passes": n, "seed": seed,
                "nonfinite": nonfinite, "width": spectral.scene.camera.width,
                "height": spectral.scene.camera.height, "seconds": round(seconds, 3),
                "snapshot": snapshot}

    xyz, _, _ = progressive(run_pass, xyz_to_srgb, meta, passes=passes, time=time, out=out,
                            snapshot_every=snapshot_every, progress=progress,
                            exposure=exposure)
    return xyz_to_srgb(xyz), xyz
