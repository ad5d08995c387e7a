"""VCM and BDPT on paths through a delta interface AND a scattering medium, against path
tracing.

The scene: a 1 m x 1 m pool, 0.6 m deep, built from rectangles (white Lambertian floor and
three walls, albedo 0.6; the fourth wall below the water line is a rect light facing into
the pool), filled with scattering water (sigma_s 0.5 / 0.75 / 1.0 per metre, sigma_a
0.15 / 0.06 / 0.03, Henyey-Greenstein g = 0.4, so the phase function's forward and reverse
pdfs differ in the MIS sums) under a flat smooth dielectric surface (ior 1.33: a delta
interface, reflection or refraction chosen by Fresnel, total internal reflection from
below). Two views of the same scene (they differ in camera values only, so both compile
the same programs):

  above: the camera 1.2 m over the water looks down through the surface: every camera
         path starts with a delta vertex (z_1), then medium vertices (NEE, connections and
         volume merging from medium vertices), the floor and the walls seen through the
         surface;
  under: the camera in the water looks obliquely up, beyond the critical angle, away
         from the light towards the walls it lights: the top of the image is the
         surface's total internal reflection, a delta vertex between two medium segments;
         the camera itself is in the medium (light tracing and s >= 2 connections carry
         30-35 % of this image).

Reference: path tracing (emitter hits + NEE, MIS between them) converges here: the light is
an area light inside the water, so NEE from medium and surface vertices reaches it
directly, and the paths whose vertex next to the light is the delta surface are still made
by emitter hits. PT is therefore an independent estimator of the same depth-truncated image
(max_depth 4: camera -> surface -> medium -> medium -> light and the like). The expected
value of each compared quantity is PT's: both sides estimate the same integral, so
E[alg] - E[pt] = 0, and the test asserts |mean_alg - mean_pt| < K sqrt(SE_alg^2 + SE_pt^2)
on the means of the image's left and right halves (per channel; above: near / far from
the lit wall), over independent passes (different seeds), with the combined SE below
1.25 % of the value (so a 5 % difference would be at least 4 SE). Halves rather than 2 x 2
blocks: above, the far half is 4x dimmer than the near one, and 2 x 2 blocks would need 3x
the passes to keep its combined SE under 1.25 %.

What VCM puts where (technique images, 32 passes): above, merges carry 7-9 % of the image
(mostly at z_2 on the floor seen through the surface; volume merges about 1 %: removing
them lowers the halves by 0.4-0.7 % and 1.2-1.5 %), s = 2 connections 9-11 %; under, light
tracing and connections with s >= 2 carry 30-35 % and merges 1-2 % (volume merges
< 0.1 %). This test resolves about 3-4 % (the combined SE is 0.56-1.07 %): it does not see
the volume-merging kernel on its own (tests/merge/test_merge.py::
test_medium_furnace_with_medium_merging does, in a furnace without a delta interface); it
sees what changes the medium transport, or the weights of whole technique families through
the surface, by a few per cent.

Sizes: 8 x 8 pixels, 16 spp: N = 1024 paths per side, so PT's camera subpaths (1024 lanes)
and BDPT / VCM's joint trace (2N = 2048 lanes) each run as one dense round of
`_subpath.trace`.

Measured (PASSES = 160 per render; pt seed 1, bdpt seed 2, vcm seed 3; ratio alg / pt of
the left ("near") and right ("far") halves, R G B; max |diff| / combined SE):
  above bdpt  near 1.006 1.004 1.002  far 1.021 1.018 1.016   combined SE 0.56-0.84 %  2.86
  above vcm   near 1.012 1.009 1.007  far 1.015 1.015 1.014   combined SE 0.56-1.07 %  2.14
  under bdpt  near 1.000 1.000 0.999  far 0.990 0.992 0.994   combined SE 0.66-0.94 %  1.48
  under vcm   near 0.999 0.999 0.998  far 0.992 0.996 1.000   combined SE 0.74-0.99 %  1.03
At 480 passes (other seeds), above: bdpt / pt near 1.006 (2.0 SE) far 0.990-0.995 (-1.3 to
-2.0 SE); vcm / pt near 1.009 (2.2-2.8 SE) far 1.005-1.007 (0.8-1.2 SE); vcm at radius
0.005: near 1.003-1.005 (0.8-1.6 SE).
Teeth: sigma_s x 1.1 in the bdpt / vcm render only (PT unchanged) fails every case, at
4.7 / 5.5 / 5.3 / 5.9 SE (ratios down to 0.95). Merging radius: at 0.04 (instead of 0.01)
VCM's merging bias shows (above: near 0.982, far 1.016-1.020, 3.3 SE), so the radius stays
small.
Runtime: 3 compiled programs (pt, bdpt, vcm; the views share them) and 6 renders of 160
passes: 65 s CPU with a cold compilation cache, 44 s CPU with XLA's persistent cache warm.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig

from .. import _analytic as A
from .. import _scenes as S

K = 4.0
W = H = 8
SPP = 16
DEPTH = 4
RADIUS = 0.01  # merging radius, fraction of the view radius (7 mm above, 4 mm under water)
PASSES = 160
BLOCKS = (1, 2)  # image rows x columns of blocks: halves near / far from the lit wall

SIGMA_A = [0.15, 0.06, 0.03]
SIGMA_S = [0.5, 0.75, 1.0]

# camera (position, target, up) of each view; everything else is shared
VIEWS = {
    "above": ((0.05, 1.2, 0.0), (0.0, -0.6, 0.0), (0.0, 0.0, -1.0)),
    "under": ((-0.3, -0.35, -0.3), (0.4, -0.05, 0.2), (0.0, 1.0, 0.0)),
}


def pool(view: str, sigma_s_scale: float = 1.0) -> dict:
    pos, target, up = VIEWS[view]

    def wall(center, normal):
        return {"type": "rect", "center": center, "normal": normal, "size": [1.0, 0.7],
                "up": [0.0, 1.0, 0.0], "material": "white"}

    return {
        "camera": S.camera(pos, target, 36.0, W, H, up=up),
        "materials": {"white": {"type": "diffuse", "albedo": 0.6}},
        "shapes": [
            {"type": "rect", "center": [0.0, -0.6, 0.0], "normal": [0.0, 1.0, 0.0],
             "size": [1.0, 1.0], "material": "white"},
            wall([0.5, -0.25, 0.0], [-1.0, 0.0, 0.0]),
            wall([0.0, -0.25, 0.5], [0.0, 0.0, -1.0]),
            wall([0.0, -0.25, -0.5], [0.0, 0.0, 1.0]),
        ],
        "water": {"level": 0.0, "sigma_a": SIGMA_A,
                  "sigma_s": [sigma_s_scale * s for s in SIGMA_S],
                  "phase": "hg", "g": 0.4, "ior": 1.33,
                  "footprint": [-0.5, 0.5, -0.5, 0.5], "floor": -0.6},
        # the wall x = -0.5 below the water line emits into the pool
        "lights": [{"type": "rect", "center": [-0.5, -0.3, 0.0], "normal": [1.0, 0.0, 0.0],
                    "size": [1.0, 0.6], "up": [0.0, 1.0, 0.0], "radiance": [1.0, 1.0, 1.0]}],
    }


@functools.lru_cache(maxsize=None)
def block_stats(view: str, alg: str, seed: int, sigma_s_scale: float = 1.0):
    """(mean, SE) over PASSES independent passes of the block means [rows, columns, C]."""
    scene = jaxvcm.scene_from_dict(pool(view, sigma_s_scale), "pool")  # one name: it is static
    cfg = RenderConfig(algorithm=alg, max_depth=DEPTH, spp=SPP, radius=RADIUS)
    _, _, imgs, bad = A.render_stats(scene, cfg, PASSES, seed=seed)
    assert bad == 0, f"{alg} {view}: {bad} non-finite contributions"
    P = imgs.shape[0]
    R, C = BLOCKS
    b = imgs.reshape(P, R, H // R, C, W // C, -1).mean(axis=(2, 4))
    return b.mean(0), b.std(0, ddof=1) / np.sqrt(P)


def compare(view, alg, seed, sigma_s_scale=1.0):
    """(pt's block means, alg's block means, their combined standard error)."""
    ref, ref_se = block_stats(view, "pt", 1)
    got, got_se = block_stats(view, alg, seed, sigma_s_scale)
    se = np.sqrt(ref_se**2 + got_se**2)
    return ref, got, se


@pytest.mark.parametrize("view", sorted(VIEWS))
@pytest.mark.parametrize("alg", ["bdpt", "vcm"])
def test_agrees_with_pt_through_delta_surface_and_medium(alg, view):
    ref, got, se = compare(view, alg, seed=2 if alg == "bdpt" else 3)
    assert np.all(ref > 0)
    assert np.all(se < 0.0125 * ref), (
        f"{alg} vs pt ({view}): combined standard error {se / ref} of the block means "
        f"cannot see 5 % at {K} SE")
    err = np.abs(got - ref)
    assert np.all(err < K * se), (
        f"{alg} vs pt ({view}): block means {got} vs {ref}, ratio {got / ref}, "
        f"|diff| / SE {err / se} exceeds {K}")
