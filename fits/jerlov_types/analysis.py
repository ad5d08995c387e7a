"""Why the 3-parameter model cannot match some Jerlov types: render-free diagnostics.

1. Unreachable red: the model only ADDS to pure water (Pope & Fry a_w, Zhang b_w), so in
   the target model's terms its attenuation s(lambda, d) (the non-scattering equivalent of
   the Jerlov K_d, ~ a + b_b; see targets.py) can never fall below a_w + b_w / 2. Jerlov's
   K_d is below that in the red for the clear types (e.g. type I: K_d(700) = 0.56 /m <
   a_w(700) = 0.624 /m). "reachable" clips s at that floor and reports the colour change.
2. Surrogate fits (surrogate.py: the renderer's exact colour for non-scattering water,
   with sigma = a + b_b standing in for the particles): the best the model family can do
   without render noise, with the main fit's three terms, with a_cdom and b_p alone (no
   flat term), and with the CDOM slope S freed as well.
Writes analysis.json here. Usage (from the repo root): python -m fits.jerlov_types.analysis [--types I,II]
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
from . import targets as T
from .run import DEPTHS, water_init
from .surrogate import pure_floor, surrogate_fit, surrogate_xyz


def reachable_xyz(name, d):
    lam = T.grid()
    kd = T.jerlov_kd(name, lam)
    s = np.maximum(T.QUAD.equivalent_attenuation(kd, d), pure_floor(lam))
    return surrogate_xyz(s, d)


P2 = ("a_cdom", "b_p")
P3 = ("a_cdom", "b_p", "a_flat")
P4 = ("a_cdom", "b_p", "a_flat", "S")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--types", default="I,IA,IB,II,III,C1,C3,C5,C7,C9")
    args = ap.parse_args()
    out = {}
    for t in args.types.split(","):
        r = {"reachable_delta_e2000": [T.delta_e(reachable_xyz(t, d), T.target_xyz(t, d))
                                       for d in DEPTHS],
             "surrogate_3p": surrogate_fit(t, DEPTHS, water_init(P3), P3),
             "surrogate_2p_no_flat": surrogate_fit(t, DEPTHS, water_init(P2), P2),
             "surrogate_3p_free_S": surrogate_fit(t, DEPTHS, water_init(P4), P4)}
        # where the Jerlov nodes fall below the pure-water floor (in K_d terms, mu_d at 0-)
        from jaxvcm import jerlov_table

        names, wl, kd = jerlov_table()
        k = kd[:, names.index(t)]
        r["kd_below_pure_water_proxy"] = {f"{w:g}": [float(k[i]), float(pure_floor(w)
                                                                          / T.QUAD.mu_d())]
                                          for i, w in enumerate(wl)
                                          if k[i] < pure_floor(w) / T.QUAD.mu_d()}
        out[t] = r
        print(t, json.dumps(r))
    with open(os.path.join(HERE, "analysis.json"), "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
