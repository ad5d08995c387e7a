"""`jaxvcm bench --startup`: how long a user waits for the first pass.

For each algorithm, the README's kind of command `jaxvcm render SCENE --passes 1` runs in a
fresh process twice with the same, initially empty, persistent compilation cache
($JAXVCM_CACHE_DIR in a temp directory): *cold* compiles, *warm* loads the compiled
programs from the cache. Per run: the process's wall time (interpreter, imports, scene
load, the pass, writing the outputs) and the first pass's own time (the sidecar's
"seconds": compilation or cache load + one pass). `import` is the wall time of a process
that only imports jaxvcm (the floor under every command). Repeated `--startup-runs` times
(a fresh cache each), medians reported; the runs are sequential on a shared machine.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import _common as C

TAG = "startup"
DEFAULT_ALGORITHMS = ("pt", "bdpt", "vcm")
TARGET_COMPILE_S = 10.0  # VCM's first pass from an empty cache
GLINT_ALGORITHMS = ("pt", "bdpt", "bpm", "vcm")  # the command line turns the glints on
TARGET_WARM_S = 3.0  # from a warm persistent cache


def _env(cache: str) -> dict:
    env = dict(os.environ, JAXVCM_CACHE_DIR=cache, JAX_PLATFORMS=os.environ.get(
        "JAX_PLATFORMS", "cpu"))
    # the test suite's compile-time XLA settings (optimisation level 0, no fusion
    # emitters, one codegen thread: `tests/conftest.py`) must not leak into a user's render
    flags = [f for f in env.get("XLA_FLAGS", "").split()
             if not f.startswith(("--xla_backend_optimization_level",
                                  "--xla_cpu_use_fusion_emitters",
                                  "--xla_cpu_parallel_codegen_split_count"))]
    env["XLA_FLAGS"] = " ".join(flags)
    return env


def _timed(args: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    p = subprocess.run(args, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise OSError(f"startup: {' '.join(args[3:6])} exited with {p.returncode}: "
                      f"{(p.stderr.strip().splitlines() or [''])[-1]}")
    return wall


def run_startup(a, argv, scene: Path, log) -> dict:
    """The cold / warm table for `a.algorithms` (default pt, bdpt, vcm) on `scene` at
    `a.size` (default 256) and `a.max_depth`; markdown section + JSON sidecar."""
    algs = a.algorithms or list(DEFAULT_ALGORITHMS)
    size = a.size
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "scene": scene.name, "size": size, "max_depth": a.max_depth, "runs": a.startup_runs,
           "rows": []}
    py = sys.executable
    imp = []
    for _ in range(a.startup_runs):
        with tempfile.TemporaryDirectory() as cache:
            imp.append(_timed([py, "-c", "import jaxvcm"], _env(cache)))
    res["import_s"] = statistics.median(imp)
    log(f"startup: import jaxvcm {res['import_s']:.2f} s")
    for alg in algs:
        # as the command line renders by default, and (where that adds the glints) without
        for extra in ([], ["--no-glints"]) if alg in GLINT_ALGORITHMS else ([],):
            per = {"cold_process_s": [], "cold_pass_s": [], "warm_process_s": [],
                   "warm_pass_s": []}
            for _ in range(a.startup_runs):
                with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as d:
                    out = Path(d) / "r.exr"
                    args = [py, "-m", "jaxvcm.cli", "render", str(scene), "--algorithm", alg,
                            "--passes", "1", "--width", str(size), "--height", str(size),
                            "--max-depth", str(a.max_depth), "--quiet", "--out", str(out),
                            *extra]
                    for phase in ("cold", "warm"):
                        per[f"{phase}_process_s"].append(_timed(args, _env(cache)))
                        meta = json.loads(out.with_suffix(".json").read_text())
                        per[f"{phase}_pass_s"].append(float(meta["seconds"]))
            label = " ".join([alg, *extra])
            row = {"algorithm": label, **{k: statistics.median(v) for k, v in per.items()},
                   "all": per}
            res["rows"].append(row)
            log(f"startup: {label} {size}x{size} d{a.max_depth}: cold "
                f"{row['cold_process_s']:.1f} s (first pass {row['cold_pass_s']:.1f} s), warm "
                f"{row['warm_process_s']:.1f} s (first pass {row['warm_pass_s']:.1f} s)")
    body = markdown(res)
    C.publish(a.out, TAG, res, body, log)
    return res


def markdown(res: dict) -> str:
    L = C.section_head("Startup: cold and warm first pass", res) + [
         f"- `jaxvcm render {res['scene']} --passes 1 --width {res['size']} --height "
         f"{res['size']} --max-depth {res['max_depth']} --quiet` in a fresh process, twice "
         "with one persistent compilation cache that starts empty: *cold* compiles, *warm* "
         "loads from the cache. *process*: the whole command's wall seconds; *first pass*: "
         "the sidecar's seconds (compilation or cache load, plus one pass). Median of "
         f"{res['runs']} runs, each with a fresh cache. `import jaxvcm` alone: "
         f"{res['import_s']:.2f} s. The command line adds the glints to pt, bdpt, bpm and "
         "vcm; `--no-glints` rows: the algorithm's own program.",
         f"- targets: VCM's first pass from an empty cache <= {TARGET_COMPILE_S:g} s (its "
         "own program); "
         f"a warm start < {TARGET_WARM_S:g} s.", "",
         "| algorithm | cold process | cold first pass | warm process | warm first pass |",
         "|---|---|---|---|---|"]
    for r in res["rows"]:
        L.append(f"| {r['algorithm']} | {r['cold_process_s']:.2f} s | {r['cold_pass_s']:.2f} s"
                 f" | {r['warm_process_s']:.2f} s | {r['warm_pass_s']:.2f} s |")
    return "\n".join(L) + "\n"
