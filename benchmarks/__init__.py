"""jaxvcm's benchmarks (not part of the installed package; they live in the source checkout).

- `bench`: `jaxvcm bench` / `python -m benchmarks.bench`, speed vs error -> docs/benchmarks.md
- `vertex_merging`: its `--compare-mis` and `--equal-time` modes
- `spectral`: its `--dispersion` mode
- `hashgrid`: `python -m benchmarks.hashgrid`, the timings of docs/design/merging.md
- `_common`: helpers shared by the above (machine description, report files)

They use only the public API of `jaxvcm`.
"""
