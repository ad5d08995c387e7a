"""The figures of docs/design/water.md: the pool's surface and its intersection
(`water_surface.png`), and the spectral water data (`water_optics.png`).

Run from the repository root: `python -m docs.design.make_water_figures`. Public API only;
the heightfield is evaluated here in NumPy from the scene's wave parameters.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

import jaxvcm

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
STEPS = 16  # the intersector's default march (RenderConfig.march_steps)


def _waves(scene):
    w = scene.water
    return (float(w.level), np.asarray(w.amp, np.float64), np.asarray(w.kx, np.float64),
            np.asarray(w.kz, np.float64), np.asarray(w.phase0, np.float64),
            np.asarray(w.footprint, np.float64))


def _height(waves, x, z):
    level, A, kx, kz, ph, _ = waves
    h = np.full(np.broadcast(x, z).shape, level)
    for a, u, v, p in zip(A, kx, kz, ph):
        h = h + a * np.sin(u * x + v * z + p)
    return h


def surface_figure(out: Path) -> None:
    scene = jaxvcm.load_scene(str(ROOT / "scenes" / "pool.toml"))
    waves = _waves(scene)
    level, A, kx, kz, _, fp = waves
    L = float(np.sum(np.abs(A) * np.hypot(kx, kz)))
    half = float(np.sum(np.abs(A))) + 1e-3

    fig = Figure(figsize=(10.0, 4.0), dpi=110)
    ax = fig.add_subplot(1, 2, 1)
    x = np.linspace(fp[0], fp[1], 400)
    z = np.linspace(fp[2], fp[3], 400)
    X, Z = np.meshgrid(x, z)
    im = ax.imshow(1e3 * (_height(waves, X, Z) - level), extent=(fp[0], fp[1], fp[3], fp[2]),
                   cmap="RdBu_r", origin="upper")
    fig.colorbar(im, ax=ax, label="h - level (mm)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title(f"scenes/pool.toml: four waves,\nslope bound L = {L:.2f}", fontsize=10)

    # a shallow ray through the surface's box: f(t) = o_y + t d_y - h, the march, the root
    o = np.array([-1.0, level + 0.02, -0.3])
    d = np.array([1.0, -0.012, 0.35])
    d = d / np.linalg.norm(d)
    ylo, yhi = level - half, level + half
    t_lo, t_hi = [], []
    for c, (a, b) in enumerate(((fp[0], fp[1]), (ylo, yhi), (fp[2], fp[3]))):
        ta, tb = (a - o[c]) / d[c], (b - o[c]) / d[c]
        t_lo.append(min(ta, tb))
        t_hi.append(max(ta, tb))
    t0, t1 = max(max(t_lo), 0.0), min(t_hi)

    def f(t):
        p = o[None] + np.asarray(t)[:, None] * d[None]
        return p[:, 1] - _height(waves, p[:, 0], p[:, 2])

    tt = np.linspace(t0, t1, 2000)
    tm = t0 + (t1 - t0) * np.arange(STEPS + 1) / STEPS
    fm = f(tm)
    k = int(np.argmax((fm[1:] >= 0) != (fm[0] >= 0)))
    ax = fig.add_subplot(1, 2, 2)
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.plot(tt, 1e3 * f(tt), color="C0", lw=1.2, label="f(t) = o_y + t d_y - h")
    ax.plot(tm, 1e3 * fm, "o", color="C1", ms=4, label=f"march: {STEPS} segments")
    ax.axvspan(tm[k], tm[k + 1], color="C2", alpha=0.2, label="bracket of the first crossing")
    ax.set_xlabel("t along the ray (m)")
    ax.set_ylabel("f(t) (mm)")
    ax.set_title(f"a grazing ray, |d_y| / |d_xz| = {abs(d[1]) / np.hypot(d[0], d[2]):.3f} < L:\n"
                 "the first sign change brackets the first crossing", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(out)


def optics_figure(out: Path) -> None:
    lam = np.linspace(380.0, 720.0, 341)
    wl, a_w = jaxvcm.pope_fry_table()
    model = jaxvcm.WaterModel(a_cdom=0.05, b_p=0.1, n_p=1.0)

    fig = Figure(figsize=(12.0, 3.8), dpi=110)
    ax = fig.add_subplot(1, 3, 1)
    ax.semilogy(lam, np.asarray(jaxvcm.pure_water_absorption(lam)), color="C0",
                label="pure water a_w (Pope & Fry 1997)")
    ax.semilogy(wl, a_w, ".", color="C0", ms=3)
    ax.semilogy(lam, np.asarray(jaxvcm.pure_water_scattering(lam)), color="C1",
                label="pure water b_w (Zhang et al. 2009)")
    ax.semilogy(lam, np.asarray(model.sigma_a(lam)), "--", color="C0",
                label="sigma_a with a_cdom = 0.05 /m")
    ax.semilogy(lam, np.asarray(model.sigma_s(lam)), "--", color="C1",
                label="sigma_s with b_p = 0.1 /m")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("1/m")
    ax.set_title("absorption and scattering")
    ax.legend(fontsize=7)

    ax = fig.add_subplot(1, 3, 2)
    ax.plot(lam, np.asarray(jaxvcm.water_ior(lam)), color="C2")
    ax.axvline(550.0, color="0.7", lw=0.8)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("n")
    ax.set_title("refractive index (Daimon & Masumura 2007, 20 °C)")

    names, wj, kd = jaxvcm.jerlov_table()
    ax = fig.add_subplot(1, 3, 3)
    for i, name in enumerate(names):
        ax.semilogy(wj, kd[:, i], "o-", ms=3, lw=1, label=name,
                    color=f"C{i % 10}")
    ax.semilogy(lam, np.asarray(jaxvcm.pure_water_absorption(lam)), color="k", lw=0.8,
                label="a_w")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("K_d (1/m)")
    ax.set_title("Jerlov (1976) water types")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out)


def main() -> None:
    surface_figure(HERE / "water_surface.png")
    optics_figure(HERE / "water_optics.png")
    print(f"wrote {HERE / 'water_surface.png'} and {HERE / 'water_optics.png'}")


if __name__ == "__main__":
    main()
