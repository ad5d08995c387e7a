"""Timings behind docs/design/merging.md: sorting strategies, hash grid build and query.

    python -m benchmarks.hashgrid [--sort-sizes 65536,262144,1048576,4194304]
                                  [--grid-sizes 65536,262144,1048576] [--repeats 5]

(from the repository root). The grid is `jaxvcm.hashgrid_build` / `hashgrid_query_reduce` /
`hashgrid_sort_order`; the fixed-K `query` and `candidate_counts` are the test helpers of
tests/_hashgrid_oracles.py (built on the grid's private blocks, so they stay with the tests).

Every function is compiled ahead of time (`jit(...).lower(...).compile()`), then run
`repeats` times with `block_until_ready`; the median is reported in milliseconds. Keys are
uniform in [0, M) (a table of M buckets); grid points and queries are uniform in the unit
cube with the radius giving a mean of 30 neighbours, (4/3) pi r^3 M = 30.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import jaxvcm
from tests import _hashgrid_oracles as HO


def _median_ms(fn, args, repeats: int, with_output=False):
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    ms = float(np.median(ts)) * 1e3
    return (ms, out) if with_output else ms


def _compiled(f, *args, static=None):
    return jax.jit(f, static_argnames=static).lower(*args).compile()


# -------------------------------------------------------------------------------- sorts
def _argsort(h):
    return jnp.argsort(h)  # stable


def _sort_key_iota(h):
    return lax.sort((h, lax.iota(jnp.int32, h.shape[0])), num_keys=1, is_stable=False)[1]


def _sort_packed(h):
    return jaxvcm.hashgrid_sort_order(h, h.shape[0])  # uint64 (x64) single-operand sort


def _counting_scan(h):
    """Counting sort: histogram (segment_sum) + exclusive cumsum give each bucket's start;
    the rank of each element inside its bucket needs a sequential pass (lax.scan)."""
    t = h.shape[0]
    counts = jax.ops.segment_sum(jnp.ones_like(h), h, num_segments=t)
    start = jnp.cumsum(counts) - counts

    def step(nxt, hi):
        return nxt.at[hi].add(1), nxt[hi]

    _, pos = lax.scan(step, start, h)
    return jnp.zeros_like(h).at[pos].set(lax.iota(jnp.int32, t), unique_indices=True)


def _ranges_segsum(hs):
    t = hs.shape[0]
    c = jax.ops.segment_sum(jnp.ones_like(hs), hs, num_segments=t)
    return jnp.concatenate([jnp.zeros((1,), c.dtype), jnp.cumsum(c)])


def _ranges_searchsorted(hs):
    return jnp.searchsorted(hs, lax.iota(hs.dtype, hs.shape[0] + 1))


def bench_sorts(sizes, repeats):
    rows = []
    for m in sizes:
        rng = np.random.default_rng(0)
        hn = rng.integers(0, m, m).astype(np.int32)
        h, hs = jnp.asarray(hn), jnp.asarray(np.sort(hn))
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            np.argsort(hn, kind="stable")
            ts.append(time.perf_counter() - t)
        row = {"M": m, "numpy argsort (stable)": float(np.median(ts)) * 1e3}
        for name, f, a in (("jnp.argsort", _argsort, h),
                           ("lax.sort (key, iota), num_keys=1", _sort_key_iota, h),
                           ("lax.sort packed uint64 key", _sort_packed, h),
                           ("ranges: segment_sum + cumsum", _ranges_segsum, hs),
                           ("ranges: searchsorted", _ranges_searchsorted, hs)):
            row[name] = _median_ms(_compiled(f, a), (a,), repeats)
        if m <= 65536:
            row["counting sort (scan ranks)"] = _median_ms(_compiled(_counting_scan, h), (h,),
                                                           max(1, repeats // 2))
        rows.append(row)
        print(row, flush=True)
    return rows


# --------------------------------------------------------------------------------- grid
def bench_grid(sizes, repeats, k=64):
    rows = []
    for m in sizes:
        rng = np.random.default_rng(1)
        p = [jnp.asarray(a) for a in rng.random((3, m), dtype=np.float32)]
        q = [jnp.asarray(a) for a in rng.random((3, m), dtype=np.float32)]
        r = np.float32((30 / (4 / 3 * np.pi * m)) ** (1 / 3))
        build = _compiled(partial(jaxvcm.hashgrid_build, table_size=m), *p, None, r)
        grid = build(*p, None, r)
        reps = repeats if m <= 262144 else 1 if m > 1048576 else max(1, repeats // 3)
        row = {"M = Q": m, "r": float(r), "build": _median_ms(build, (*p, None, r), repeats)}
        cand = np.asarray(HO.candidate_counts(grid, *q))
        query = _compiled(partial(HO.query, max_neighbours=k), grid, *q)
        row["query (K=64)"], (idx, count, overflow) = _median_ms(query, (grid, *q), reps, True)

        def fn(qi, pj, d2):
            return jnp.ones_like(d2) - d2  # a stand-in kernel

        red = _compiled(partial(jaxvcm.hashgrid_query_reduce, fn=fn), grid, *q)
        row["query_reduce"] = _median_ms(red, (grid, *q), reps)
        row.update({"mean neighbours": float(np.mean(np.asarray(count))),
                    "max neighbours": int(np.max(np.asarray(count))),
                    "mean candidates": float(cand.mean()), "max candidates": int(cand.max()),
                    "overflow": bool(overflow), "runs": reps})
        rows.append(row)
        print(row, flush=True)
    return rows


def _table(rows):
    keys = list(rows[0])
    for r in rows[1:]:
        keys += [k for k in r if k not in keys]
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}" if abs(v) < 1 else f"{v:.1f}"
        return str(v)

    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sort-sizes", default="65536,262144,1048576,4194304")
    ap.add_argument("--grid-sizes", default="65536,262144,1048576,4194304")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)  # packed uint64 keys, float64 grid (as in tests)
    print(f"jax {jax.__version__}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()}")
    parse = lambda s: [int(x) for x in s.split(",") if x]  # noqa: E731
    sorts = bench_sorts(parse(a.sort_sizes), a.repeats) if a.sort_sizes else []
    grids = bench_grid(parse(a.grid_sizes), a.repeats) if a.grid_sizes else []
    print(f"\nload average after: {os.getloadavg()}\n")
    if sorts:
        print("Sorting (ms, median)\n\n" + _table(sorts) + "\n")
    if grids:
        print("Hash grid (ms, median)\n\n" + _table(grids))


if __name__ == "__main__":
    main()
