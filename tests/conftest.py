"""Test configuration: x64 available, strict dtype promotion, persistent compilation cache.

x64 is enabled so that float64 oracles and float64 renders are possible; the renderer's
own dtype comes from the scene (float32 by default), and strict promotion turns any
accidental float32/float64 mixing inside the kernels into an error.
"""

import os

# The suite is compile-bound (hundreds of small programs, each compiled once and run a few
# times at 16x16-ish sizes), so its programs are compiled for compile time:
# - XLA's CPU backend at LLVM optimisation level 0;
# - fusions by XLA:CPU's elemental IR emitter rather than its MLIR fusion emitters
#   (`xla_cpu_use_fusion_emitters=false`). On a 16x16 pool pass at depth 8 this compiles
#   PT, PPM, BDPT and VCM in 1.8 / 1.7 / 4.3 / 5.3 s against 3.1 / 3.3 / 6.5 / 7.4 s, with
#   the same image bit for bit; the code runs 1.3-1.5x slower, which only the tests that
#   run many large passes would feel, and those compile at the default level
#   (`tests/_analytic.py`, `OPTIMISED`).
# - LLVM code generation on one thread (`xla_cpu_parallel_codegen_split_count=1`): the two
#   workers already keep both cores busy, and splitting each module for threads that
#   cannot run costs more than it gains. Two processes compiling PT, PPM, BDPT and VCM at
#   16x16 side by side, as the workers do: 19.3 s of compilation summed against 22.0 s
#   (the same executable code: the split only groups the kernels into LLVM modules).
# The arithmetic is the same IEEE arithmetic (no fast-math either way): the fixed-key
# renders of tests/transport/test_golden.py, recorded at the default settings, still agree
# to float32 round-off. Renders outside the tests keep XLA's defaults (level 0 makes passes
# 2-3x slower). Set before jax is imported; subprocesses (the CLI tests) inherit it.
for _flag in ("--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false",
              "--xla_cpu_parallel_codegen_split_count=1"):
    if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
_cache = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".jax_cache")
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)


import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop in-memory compiled programs after each test module. A single pytest process
    otherwise keeps every executable of the whole suite alive (hundreds of programs, many
    GB), enough for XLA to abort while it serialises an executable for the persistent
    cache late in a run. Later modules that need a program again get it back from the
    persistent cache."""
    yield
    jax.clear_caches()
    gc.collect()


# ---- scheduling under pytest-xdist (`-n 2 --dist loadfile`, as CI runs the suite)
# xdist hands out whole files in the order of their test counts (largest first), so files
# with few but long tests (test_gradients: 2 tests, over a minute; test_inline: 4) would come
# last, one worker running them alone after the other has finished. Known long files go
# first instead (longest first: the remaining short files then even out the two workers'
# ends); the others keep xdist's order. Keys: files as pytest names them (from the
# repository root); seconds: a whole run on the 2-core machine from a cold compilation cache
# (`JAXVCM_TEST_COMPILE_LOG`, below, gives them per file).
_LONG_FILES = {"tests/transport/test_bidir.py": 315, "tests/merge/test_merge.py": 193,
               "tests/fit/test_fit.py": 174, "tests/sampling/test_aim.py": 168,
               "tests/docs/test_tutorials.py": 164, "tests/transport/test_spectral.py": 162,
               "tests/host/test_memory.py": 147, "tests/transport/test_mnee.py": 137,
               "tests/transport/test_glints.py": 117, "tests/io/test_cli.py": 111,
               "tests/transport/test_cornell.py": 109, "tests/mis/test_mis_recursive.py": 108,
               "tests/host/test_devices.py": 107, "tests/mis/test_glossy_mis.py": 102,
               "tests/transport/test_delta_medium.py": 69, "tests/transport/test_caustics.py": 67,
               "tests/mis/test_join_pdfs.py": 66, "tests/manifold/test_solver.py": 55,
               "tests/mis/test_mis_partial.py": 55, "tests/transport/test_transport.py": 48,
               "tests/merge/test_precise.py": 47, "tests/transport/test_golden.py": 44,
               "tests/subpath/test_inline.py": 44, "tests/subpath/test_queue.py": 42,
               "tests/io/test_snapshots.py": 41, "tests/geometry/test_hard_cases.py": 41,
               "tests/mis/test_techniques.py": 41, "tests/fit/test_fit_spectral.py": 41,
               "tests/geometry/test_geometry.py": 40}


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook: no error where it is absent
def pytest_xdist_make_scheduler(config, log):
    if config.getoption("dist", None) != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class LongFilesFirst(LoadFileScheduling):
        _ordered = False

        def _assign_work_unit(self, node):
            if not self._ordered:  # the queue is complete when the first unit is assigned
                self._ordered = True
                queue = sorted(self.workqueue.items(),  # stable: ties keep xdist's order
                               key=lambda kv: -_LONG_FILES.get(kv[0].replace(os.sep, "/"), 0))
                self.workqueue.clear()
                self.workqueue.update(queue)
            super()._assign_work_unit(node)

    return LongFilesFirst(config, log)


@pytest.fixture(autouse=True)
def _join_output_import_thread():
    """The CLI imports its output writers on a daemon thread (`_io.prefetch_imports`); let
    it finish with the test that started it, so that no import compiles concurrently with
    pytest's own at the end of a worker (CPython 3.11.7's AST recursion counter is not
    thread-safe: 'SystemError: AST constructor recursion depth mismatch' can end a worker)."""
    yield
    import threading

    for t in threading.enumerate():
        if t.name == "jaxvcm-prefetch-imports":
            t.join()


# ---- where the suite's time goes (opt-in: JAXVCM_TEST_COMPILE_LOG=path.jsonl)
# One JSON line per test: its wall time and the seconds JAX spent tracing, lowering and
# compiling (or reading from the persistent cache) inside it, per function name, so the
# programs that cost the suite most can be found and shared. Subprocesses (the CLI tests)
# are not seen; their time shows as wall time without compile events.
_COMPILE_LOG = os.environ.get("JAXVCM_TEST_COMPILE_LOG")
if _COMPILE_LOG:
    import json
    import time

    import jax.monitoring

    _events: list = []
    _names = {"/jax/core/compile/jaxpr_trace_duration": "trace",
              "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
              "/jax/core/compile/backend_compile_duration": "compile"}

    def _listen(event, seconds, **kw):
        if event in _names and seconds > 0.05:
            _events.append((_names[event], kw.get("fun_name", "?"), round(seconds, 3)))

    jax.monitoring.register_event_duration_secs_listener(_listen)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        _events.clear()
        start = time.perf_counter()
        yield
        wall = time.perf_counter() - start
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(f"{_COMPILE_LOG}.{worker}", "a") as f:
            f.write(json.dumps({"test": item.nodeid, "wall": round(wall, 3),
                                "events": list(_events)}) + "\n")
