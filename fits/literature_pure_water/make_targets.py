"""Write the scenes and the two fit configs of fits/literature_pure_water from the
literature reference (reference.py: Pope & Fry absorption, colour-science colours; no
rendering). Usage (from the repo root): python -m fits.literature_pure_water.make_targets
"""

from __future__ import annotations

import os

from . import reference as R

HERE = os.path.dirname(os.path.abspath(__file__))

SIZE = 8  # pixels (the camera sees only the floor: fov 2 deg)
RENDER = """[render]
algorithm = "pt"
max_depth = 20     # 8 internal round trips: the truncated series is 0.03 dE2000 short (NOTES.md)
rr_depth = 100     # no Russian roulette (CRN objective stays smooth)
passes = 32
seed = 1
"""


def fmt(v):
    return "[" + ", ".join(repr(float(x)) for x in v) + "]"


def scene_toml(depth, sky):
    d = R.scene_dict(depth, sky, size=SIZE)
    c, w, s = d["camera"], d["water"], d["shapes"][0]
    return f"""# White Lambertian floor {depth:g} m under a flat pool of (pure) water, uniform sky;
# camera {R.CAM_HEIGHT} m above the floor looking down. Written by make_targets.py.
# The water's sigma_a / sigma_s here are placeholders: the fits replace them.
name = "{d['name']}"

[camera]
position = {fmt(c['position'])}
target = {fmt(c['target'])}
up = {fmt(c['up'])}
fov = {c['fov']}
width = {c['width']}
height = {c['height']}

[materials.floor]
type = "diffuse"
albedo = 1.0

[[shapes]]
type = "rect"
center = {fmt(s['center'])}
normal = {fmt(s['normal'])}
size = {fmt(s['size'])}
material = "floor"

[water]
level = 0.0
sigma_a = {w['sigma_a']}
sigma_s = {w['sigma_s']}
ior = {w['ior']}
footprint = {fmt(w['footprint'])}
floor = {w['floor']}

[[lights]]
type = "sky"
radiance = {sky!r}   # 1 / L_f(0): the floor through absorption-free water has Y = 1
"""


def regions(space):
    out = []
    for d in R.DEPTHS:
        t = R.target_lab(d) if space == "lab" else R.target_xyz(d)
        out.append(f"""[[regions]]
name = "floor_{d:g}m"
scene = "{d:g}m"
rect = [0, 0, {SIZE}, {SIZE}]
target = {fmt(t)}
""")
    return "\n".join(out)


def scenes():
    return "\n".join(f'[scenes.\"{d:g}m\"]\nfile = "scene_{d:g}m.toml"\n' for d in R.DEPTHS)


HEAD = """# fits/literature_pure_water: targets are colour-science colours of a white floor at 0.5,
# 1, 2 and 4 m under a D65 sky through pure water (Pope & Fry 1997 absorption, no
# scattering; reference.py), NOT renders. Written by make_targets.py.
"""


def main():
    sky = R.sky_radiance()
    for d in R.DEPTHS:
        with open(os.path.join(HERE, f"scene_{d:g}m.toml"), "w") as f:
            f.write(scene_toml(d, sky))
    with open(os.path.join(HERE, "rgb.toml"), "w") as f:
        f.write(HEAD + """# (a) RGB model: one sigma_a per linear-sRGB channel for all four depths; sigma_s fixed at
# ~0 (1e-6 /m: the reference has no scattering). Residuals in CIELAB (1 unit = 1 dE*ab).
# Run: jaxvcm fit fits/literature_pure_water/rgb.toml --out fits/literature_pure_water/rgb
space = "lab"

""" + RENDER + """
[solver]
max_steps = 30
rtol = 1e-4
atol = 1e-4
free = "sigma_a"

[init]
sigma_a = [0.1, 0.1, 0.1]
sigma_s = 1e-6

""" + scenes() + "\n" + regions("lab"))
    with open(os.path.join(HERE, "spectral.toml"), "w") as f:
        f.write(HEAD + """# (b) spectral model: sigma_a(lambda) = a_w_scale a_w(lambda) + a_cdom e^(-S (lambda - 440))
# + a_flat (jaxvcm.WaterModel, pure-water scattering off as in the reference), started
# clearly wrong; the literature answer is a_w_scale = 1, a_cdom = a_flat = 0.
# Run: jaxvcm fit fits/literature_pure_water/spectral.toml --out fits/literature_pure_water/spectral
mode = "spectral"
space = "lab"
params = ["a_w_scale", "a_cdom", "a_flat"]
linear = ["a_cdom", "a_flat"]   # fitted as they are (may cross 0); a_w_scale in log space

""" + RENDER + """
[spectral]
n_wavelengths = 8
ior = "data"       # Daimon & Masumura n(550 nm), as the reference

[water]            # the model's fixed fields
S = 0.015
pure_scattering = false

[solver]
max_steps = 30
rtol = 1e-4
atol = 1e-4

[init]
a_w_scale = 2.0
a_cdom = 0.1
a_flat = 0.05

[truth]
a_w_scale = 1.0
a_cdom = 0.0
a_flat = 0.0

""" + scenes() + "\n" + regions("lab"))


if __name__ == "__main__":
    main()
