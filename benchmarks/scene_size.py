"""`jaxvcm bench --scene-size`: compile time, memory and pass time against the number of
waves and of lights.

The default pool (`scenes/pool.toml`) at 32x32, VCM at depth 8: its four waves replaced by
`n` waves (wavenumbers 4-18 /m in random directions, amplitudes scaled by 1 / sqrt(n) so
the surface's roughness stays about the pool's), or its one rect light by `n` lights of
the same size in a grid under the ceiling (radiance shared). Each row runs in a fresh
child process: the render program lowered (its StableHLO line count), compiled (seconds;
XLA's temporary memory from its memory analysis), then the median of 3 passes, and the
process's peak resident memory. The per-light and per-wave evaluations are rolled loops
and per-kind code (`_lights.groups`, `_geometry.over_waves`), so the first two columns
must stay flat; the pass time grows with the waves (every height evaluation sums them).
"""

from __future__ import annotations

import json
import subprocess
import sys

TAG = "scene-size"
WAVES = (1, 10, 100, 1000)
LIGHTS = (1, 10, 100)
SIZE = 32

CHILD = r"""
import copy, json, resource, statistics, sys, time, tomllib
import numpy as np, jax
import jaxvcm
from jaxvcm._render import _render_pass_jit
scene_path, waves, lights, size, depth = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
with open(scene_path, "rb") as f:
    d = tomllib.load(f)
rng = np.random.default_rng(0)
if waves:
    ws = []
    for i in range(waves):
        k, th = rng.uniform(4.0, 18.0), rng.uniform(0.0, 2 * np.pi)
        ws.append([0.01 / np.sqrt(waves), k * np.cos(th), k * np.sin(th), rng.uniform(0, 6.3)])
    d["water"]["waves"] = [[float(x) for x in w] for w in ws]
l0 = d["lights"][0]
d["lights"] = []
for i in range(lights):
    l = copy.deepcopy(l0)
    l["center"] = [l0["center"][0] + 0.16 * (i % 10 - 4.5), l0["center"][1],
                   l0["center"][2] + 0.16 * (i // 10 - 4.5)]
    l["radiance"] = l0["radiance"] / lights
    d["lights"].append(l)
d["camera"]["width"] = d["camera"]["height"] = size
scene = jaxvcm.scene_from_dict(d)
cfg = jaxvcm.RenderConfig(algorithm="vcm", max_depth=depth)
key = jaxvcm.pass_key(0, 0)
t0 = time.perf_counter()
low = _render_pass_jit.lower(scene, key, cfg, 0)
lines = low.as_text().count("\n")
t1 = time.perf_counter()
comp = low.compile()
t2 = time.perf_counter()
mem = comp.memory_analysis()
temp = getattr(mem, "temp_size_in_bytes", None) if mem is not None else None
jax.block_until_ready(comp(scene, key, 0))
ts = []
for i in range(3):
    t = time.perf_counter()
    jax.block_until_ready(comp(scene, jaxvcm.pass_key(0, i + 1), 0))
    ts.append(time.perf_counter() - t)
print("RESULT " + json.dumps({"waves": len(d["water"]["waves"]), "lights": lights, "lines": lines,
      "lower_s": t1 - t0, "compile_s": t2 - t1, "temp_bytes": temp,
      "pass_s": statistics.median(ts),
      "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""


def _child(scene_path, waves, lights, size, depth, log) -> dict:
    log(f"scene size: {waves} waves, {lights} lights ...")
    # no compilation cache in the child: every row compiles
    env = {k: v for k, v in __import__("os").environ.items()
           if not k.startswith("JAX_COMPILATION_CACHE")}
    p = subprocess.run([sys.executable, "-c", CHILD, str(scene_path), str(waves), str(lights),
                        str(size), str(depth)], capture_output=True, text=True, env=env)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"scene-size child failed ({waves} waves, {lights} lights):\n"
                       + p.stderr[-2000:])


def run_scene_size(a, argv, scene_path, log) -> dict:
    from . import _common as C
    depth = a.max_depth or 8
    size = 8 if a.quick else SIZE
    waves = WAVES[:2] if a.quick else WAVES
    lights = LIGHTS[:2] if a.quick else LIGHTS
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "scene": str(scene_path), "size": size, "max_depth": depth, "rows": []}
    for n in waves:
        res["rows"].append(_child(scene_path, n, 1, size, depth, log))
    for n in lights[1:]:
        res["rows"].append(_child(scene_path, 0, n, size, depth, log))
    C.publish(a.out, TAG, res, markdown(res), log)
    return res


def markdown(res: dict) -> str:
    from . import _common as C
    L = C.section_head("Scenes that scale: waves and lights", res) + [
        f"- `{res['scene']}` at {res['size']}x{res['size']}, VCM at depth "
        f"{res['max_depth']}: its waves replaced by n random ones (wavenumbers 4-18 /m, "
        "amplitudes 0.01 / sqrt(n) m), or its one rect light by n of them; each row in a "
        "fresh process without the compilation cache: StableHLO lines of the render "
        "program, its compile time, XLA's temporary memory, the process's peak resident "
        "memory, the median of 3 passes (`benchmarks/scene_size.py`).", "",
        "| waves | lights | StableHLO lines | compile | XLA temp | peak RSS | pass |",
        "|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        temp = f"{r['temp_bytes'] / 2**20:.0f} MiB" if r.get("temp_bytes") else "-"
        L.append(f"| {r['waves']} | {r['lights']} | {r['lines']:,} | {r['compile_s']:.1f} s | "
                 f"{temp} | {r['peak_rss_bytes'] / 2**30:.2f} GiB | "
                 f"{1e3 * r['pass_s']:.1f} ms |")
    L.append("")
    L.append("- Reading: the program's size, its compile time and memory do not depend on "
             "the number of waves or lights: the lights run one code copy per kind "
             "(`_lights.groups`: the parameters of the light at hand gathered), the waves "
             "one loop body of four waves (`_geometry.over_waves`); the compile times' "
             "spread is the machine's load (2 cores, shared), not the scene. The pass "
             "time grows "
             "with the waves, because every height evaluation of the march and of the "
             "manifold solves sums them all; with the lights it barely moves (one light "
             "is sampled per connection).")
    L.append("")
    return "\n".join(L) + "\n"
