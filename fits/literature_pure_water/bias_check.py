"""Is the renderer biased against reference.py at these settings? RGB renders (grey-free:
sigma_a = 0.02, 0.1, 0.4 /m in the three channels, no scattering, sky 1) of the 0.5 m and
4 m scenes at 16x16 pixels, P passes (argument, default 256), PT max_depth 20, against the
quadrature truncated to the same (20 - 3) // 2 = 8 internal round trips. Prints the
relative error and its standard error (pixels x passes as independent samples), in %.
Usage (from the repo root): python -m fits.literature_pure_water.bias_check [P]
"""
import sys, time
import jax
from jaxvcm import enable_compilation_cache
enable_compilation_cache()
import jax.numpy as jnp, numpy as np
import jaxvcm
from jaxvcm import RenderConfig, render_pass
from . import reference as R
D = 20
cfg = RenderConfig(algorithm="pt", max_depth=D, rr_depth=100)
f = jax.jit(jax.vmap(render_pass, in_axes=(None, 0, None)), static_argnums=2)
sig = np.array([0.02, 0.1, 0.4])
def trunc(depth, sigma, trips, n=R.N_WATER):
    th_c=np.arcsin(1/n); x,w=np.polynomial.legendre.leggauss(400)
    def rule(lo,hi): return 0.5*(hi-lo)*x+0.5*(hi+lo),0.5*(hi-lo)*w
    t1,w1=rule(0,th_c); t2,w2=rule(th_c,np.pi/2)
    F=R._fresnel(np.cos(t1),1/n); sa=np.asarray(sigma)[:,None]
    cs1,cs2=np.cos(t1)*np.sin(t1),np.cos(t2)*np.sin(t2)
    e=2*np.pi*np.sum(w1*n**2*(1-F)*np.exp(-sa*depth/np.cos(t1))*cs1,-1)
    k=2*np.pi*(np.sum(w1*F*np.exp(-2*sa*depth/np.cos(t1))*cs1,-1)+np.sum(w2*np.exp(-2*sa*depth/np.cos(t2))*cs2,-1))
    return e/np.pi*sum((k/np.pi)**j for j in range(trips+1))
P, B = int(sys.argv[1]) if len(sys.argv) > 1 else 256, 32
for d in (0.5, 4.0):
    dd = R.scene_dict(d, 1.0, size=16); dd["water"]["sigma_a"] = sig.tolist(); dd["water"]["sigma_s"] = 0.0
    scene = jaxvcm.scene_from_dict(dd)
    t = time.perf_counter(); imgs = []
    for b in range(0, P, B):
        keys = jnp.stack([jaxvcm.pass_key(7, b + i) for i in range(B)])
        img, diag = f(scene, keys, cfg); imgs.append(np.asarray(img, np.float64))
    x = np.concatenate(imgs).reshape(-1, 3)
    m, se = x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x))
    ref = trunc(d, sig, (D - 3) // 2) * np.exp(-sig * R.CAM_HEIGHT)
    print(d, f"{time.perf_counter()-t:.0f}s", "rel err %", np.round((m / ref - 1) * 100, 3), "se %", np.round(se / ref * 100, 3), flush=True)
