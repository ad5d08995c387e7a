"""`jaxvcm.profile_stages`: every stage the algorithm runs is timed (positive, finite
seconds), the stages it does not run are absent. Tiny on purpose: each stage is its own
compiled program. (That the staged `technique_images` still renders what it did is
`test_golden.py`.)"""

from __future__ import annotations

import math

import pytest

import jaxvcm
from jaxvcm._integrator import pass_stages

COMMON = ["setup", "camera rays", "subpaths", "mis partials", "emitter hits",
          "vertex connection", "film", "whole pass"]
LIGHT_SIDE = ["light emission", "merging"]


@pytest.fixture(scope="module")
def scene():
    return jaxvcm.load_scene("scenes/pool.toml", width=8, height=8)


# bpm: both sides, the partial sums and merging with its capacity check (one compiled
# program per stage: the suite pays for one small algorithm); which stages every
# algorithm runs is checked without compiling below
BPM = ["setup", "camera rays", "light emission", "subpaths", "mis partials", "emitter hits",
       "merging", "film", "whole pass"]


@pytest.mark.parametrize("alg, expected", [("bpm", BPM)])
def test_profile_stages_names_and_times(scene, alg, expected):
    cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=2)
    prof = jaxvcm.profile_stages(scene, cfg, passes=1, seed=0)
    assert sorted(prof) == sorted(expected)
    assert list(prof)[-1] == "whole pass" and list(prof)[-2] == "film"
    for name, sec in prof.items():
        assert isinstance(sec, float) and math.isfinite(sec) and sec > 0, (name, sec)


def test_pass_stages_follow_the_techniques():
    names = {alg: [n for n, _ in pass_stages(jaxvcm.RenderConfig(algorithm=alg, max_depth=3))]
             for alg in jaxvcm.ALGORITHMS}
    assert "light emission" not in names["pt"] and "camera rays" not in names["lt"]
    assert not set(LIGHT_SIDE) & set(names["pt"])
    assert names["vcm"] == ["setup", "camera rays", "light emission", "subpaths",
                            "mis partials", "emitter hits", "vertex connection", "merging",
                            "film"]
    # one queue for next-event estimation, light tracing and the connections, for the
    # algorithms with any of them (lt: light tracing alone)
    assert "vertex connection" in names["lt"] and "vertex connection" not in names["bpm"]
    assert names["ppm"].index("merging") < names["ppm"].index("film")
    assert "mis partials" not in names["ppm"]  # ppm weights without partial sums
    assert names["vcm"].index("vertex connection") < names["vcm"].index("merging")
    # glints: their roots are found once, before the emitter hits that take a share of
    # them and the technique that adds them
    glint = [n for n, _ in pass_stages(jaxvcm.RenderConfig(algorithm="vcm", glints=True))]
    assert glint.index("glint roots") < glint.index("emitter hits") < glint.index("glints")
