"""`jaxvcm bench --scaling`: time and memory per pass against the number of paths, and
passes on 1 and 2 devices.

Sweep: `pool.toml` at depth `--max-depth` (default 8), square images whose pixel count is
the number of light (and camera) paths per pass, 64 k to 4 M. Every size runs in chunks of
`CHUNK` paths (`RenderConfig.chunks`, bounded memory), the smaller ones also in one chunk
where that fits in memory. Each program is compiled ahead of time (`lower().compile()`),
its working memory read from XLA's memory analysis, and then timed: the median of
`--throughput-passes` passes (1 for sizes of 1 M paths and more). Devices: the same
`jaxvcm.render` of 8 passes at 128x128 in a child process with 2 forced CPU devices,
`devices=1` against `devices=2`, interleaved, median of 3 (compiled first).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from . import _common as C

TAG = "scaling"
CHUNK = 16384
SIZES = (256, 512, 1024, 2048)  # 64 k, 256 k, 1 M, 4 M paths
WHOLE_MAX = 512  # one chunk up to 512x512 (4 GB of working memory for VCM at depth 8)
TARGET_LINEAR = 0.15

DEVICES_CHILD = r"""
import json, statistics, sys, time
import jax, jaxvcm
scene = jaxvcm.load_scene(sys.argv[1], width=128, height=128)
res = {}
for alg in sys.argv[3].split(","):
    cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=int(sys.argv[2]))
    for n in (1, 2):
        jaxvcm.render(scene, alg, passes=2, config=cfg, progress=False, devices=n)
    t = {1: [], 2: []}
    for _ in range(3):
        for n in (1, 2):
            t0 = time.perf_counter()
            jaxvcm.render(scene, alg, passes=8, config=cfg, progress=False, devices=n)
            t[n].append(time.perf_counter() - t0)
    res[alg] = {str(n): statistics.median(v) for n, v in t.items()}
print("RESULT " + json.dumps(res))
"""


def _one(scene_path, alg, size, depth, chunks, passes, log):
    import jax
    import numpy as np

    import jaxvcm
    from jaxvcm import pass_key, render_pass

    scene = jaxvcm.load_scene(scene_path, width=size, height=size)
    cfg = jaxvcm.RenderConfig(algorithm=alg, max_depth=depth).tuned(chunks=chunks)
    t0 = time.perf_counter()
    exe = jax.jit(render_pass, static_argnums=2).lower(scene, pass_key(0, 0), cfg, 0).compile()
    compile_s = time.perf_counter() - t0
    m = exe.memory_analysis()
    times, overflow = [], False
    for i in range(passes):
        t0 = time.perf_counter()
        img, diag = exe(scene, pass_key(0, i), np.int32(i))
        jax.block_until_ready(img)
        times.append(time.perf_counter() - t0)
        overflow |= bool(diag.merge_overflow)
    n = size * size
    row = {"algorithm": alg, "size": size, "paths": n, "chunks": chunks,
           "compile_s": compile_s, "pass_s": statistics.median(times), "passes": passes,
           "memory_bytes": int(m.temp_size_in_bytes + m.output_size_in_bytes
                               + m.argument_size_in_bytes),
           "merge_overflow": overflow}
    row["us_per_path"] = 1e6 * row["pass_s"] / n
    log(f"scaling: {alg} {size}x{size} chunks {chunks}: {row['pass_s']:.2f} s/pass, "
        f"{row['us_per_path']:.1f} us/path, {row['memory_bytes'] / 2**20:.0f} MiB")
    del exe
    return row


def _run_child(args: list[str], env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(args, env=env, capture_output=True, text=True)


def run_scaling(a, argv, scene: Path, log) -> dict:
    algs = a.algorithms or ["vcm"]
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "scene": scene.name, "max_depth": a.max_depth, "chunk": CHUNK, "rows": []}
    for alg in algs:
        for size in SIZES:
            n = size * size
            passes = max(1, a.throughput_passes) if n < 1 << 20 else 1
            if size <= WHOLE_MAX:
                res["rows"].append(_one(scene, alg, size, a.max_depth, 1, passes, log))
            res["rows"].append(_one(scene, alg, size, a.max_depth, n // CHUNK, passes, log))
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS=" ".join([f for f in os.environ.get("XLA_FLAGS", "").split()
                                   if "device_count" not in f]
                                  + ["--xla_force_host_platform_device_count=2"]))
    p = _run_child([sys.executable, "-c", DEVICES_CHILD, str(scene), str(a.max_depth),
                    ",".join(["pt", "vcm"])], env)
    if p.returncode != 0:
        raise OSError(f"scaling: devices child failed: {p.stderr.strip()[-300:]}")
    res["devices"] = json.loads(p.stdout.split("RESULT ", 1)[1])
    log(f"scaling: devices {res['devices']}")
    body = markdown(res)
    C.publish(a.out, TAG, res, body, log)
    return res


def markdown(res: dict) -> str:
    L = C.section_head("Scale-out: paths per pass, memory, devices", res) + [
         f"- {res['scene']}, depth {res['max_depth']}; paths = pixels = light paths per pass; "
         f"chunks of {res['chunk']} paths (`RenderConfig.chunks`); memory = XLA's memory "
         "analysis of the compiled pass (temporaries + outputs + arguments); time = median "
         "seconds per pass after an ahead-of-time compile.", "",
         "| algorithm | image | paths | chunks | s / pass | us / path | memory | compile |",
         "|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        L.append(f"| {r['algorithm']} | {r['size']}x{r['size']} | {r['paths']:,} | "
                 f"{r['chunks']} | {r['pass_s']:.2f} | {r['us_per_path']:.1f} | "
                 f"{r['memory_bytes'] / 2**20:,.0f} MiB | {r['compile_s']:.0f} s |")
    for alg in sorted({r["algorithm"] for r in res["rows"]}):
        ch = [r for r in res["rows"] if r["algorithm"] == alg and r["chunks"] > 1]
        if len(ch) >= 2:
            per = [r["us_per_path"] for r in ch]
            L.append("")
            L.append(f"{alg}, chunked: time per path from {ch[0]['paths']:,} to "
                     f"{ch[-1]['paths']:,} paths spans {min(per):.1f}-{max(per):.1f} us "
                     f"(max/min {max(per) / min(per):.2f}; linear within "
                     f"{TARGET_LINEAR:.0%} is the target).")
    d = res.get("devices")
    if d:
        L += ["", "2 forced CPU devices on the same cores, 128x128, 8 passes per render "
              "(sums kept on the devices), median of 3 interleaved:", "",
              "| algorithm | 1 device | 2 devices | speed-up |", "|---|---|---|---|"]
        for alg, t in d.items():
            L.append(f"| {alg} | {t['1']:.2f} s | {t['2']:.2f} s | {t['1'] / t['2']:.2f} |")
    return "\n".join(L) + "\n"
