"""`jaxvcm bench --quick`: a markdown table with finite rates and errors, a plot, reused
references and per-tag sections that keep each other."""

from __future__ import annotations

import json
import math

from benchmarks import _common
from benchmarks import bench as _bench


def _table(md: str, first_col: str) -> list[dict]:
    """Rows of the markdown table whose header starts with `| first_col |`."""
    lines = md.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(f"| {first_col} |"))
    head = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = []
    for ln in lines[start + 2:]:
        if not ln.startswith("|"):
            break
        rows.append(dict(zip(head, (c.strip() for c in ln.strip("|").split("|")))))
    return rows


def _num(s: str) -> float:
    return float(s.replace(",", "").rstrip("*"))


def test_bench_quick(tmp_path, capsys):
    out, refs = tmp_path / "bench.md", tmp_path / "refs"
    args = ["--quick", "--scenes", "scenes/pool_sky.toml", "--out", str(out),
            "--reference-dir", str(refs)]
    assert _bench.main(args) == 0
    err = capsys.readouterr().err
    assert "rendering" in err and "reused" not in err

    md = out.read_text()
    assert md.startswith("# ")
    assert "os.cpu_count()" in md and "jax " in md
    assert md.count("<!-- bench:pt:begin -->") == 1 and md.count("<!-- bench:pt:end -->") == 1
    rows = _table(md, "scene")
    assert [r["budget s"] for r in rows] == ["0.5", "1"]
    for r in rows:
        assert r["scene"] == "pool_sky" and r["algorithm"] == "pt" and r["size"] == "32x32"
        assert _num(r["passes"]) >= 1
        for col in ("passes/s", "camera paths/s"):
            v = _num(r[col])
            assert math.isfinite(v) and v > 0, (col, r)
        for col in ("RMSE", "relRMSE", "relMAE"):
            v = _num(r[col])
            assert math.isfinite(v) and v >= 0, (col, r)
    tp = _table(md, "scene | algorithm | size | max depth")
    assert len(tp) == 1 and _num(tp[0]["camera paths/s"]) > 0
    assert (tmp_path / "bench_pool_sky.png").stat().st_size > 1000

    sidecar = refs / "pool_sky_pt_32x32_d8.json"
    meta = json.loads(sidecar.read_text())
    assert meta["passes"] >= 2 and meta["width"] == 32 and meta["max_depth"] == 8
    assert meta["seed"] != 0 and len(meta["scene_sha256"]) == 64
    before = (sidecar.stat().st_mtime_ns, (refs / "pool_sky_pt_32x32_d8.exr").stat().st_mtime_ns)

    # A second run under another tag reuses the reference and keeps the first section.
    assert _bench.main(args + ["--tag", "again", "--budgets", "0.5"]) == 0
    err = capsys.readouterr().err
    assert "reused" in err and "rendering" not in err
    after = (sidecar.stat().st_mtime_ns, (refs / "pool_sky_pt_32x32_d8.exr").stat().st_mtime_ns)
    assert after == before
    md2 = out.read_text()
    assert md2.count("<!-- bench:pt:begin -->") == 1 and "<!-- bench:again:end -->" in md2
    assert md2.index("bench:pt:end") < md2.index("bench:again:begin")
    assert set(json.loads((tmp_path / "bench.json").read_text())) == {"pt", "again"}
    # The pt section is untouched: its table rows are still those of the first run.
    assert _table(md2, "scene") == rows


def test_bench_bad_arguments(capsys):
    assert _bench.main(["--algorithms", "nope"]) == 2
    assert _bench.main(["--budgets", "0"]) == 2
    assert _bench.main(["--scenes", "no/such/scene.toml"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and all(ln.startswith("jaxvcm: error: bench: ") for ln in err)


# ---- vertex-merging modes (--compare-mis, --equal-time): arguments and report plumbing only
def test_bench_vm_mode_defaults():
    a = _bench._settings(["--compare-mis"])
    assert a.mode == "compare-mis" and a.algorithms == ["vcm", "bdpt"] and a.size == 64
    assert [p.stem for p in a.scene_paths] == ["pool", "pool_sun"] and a.mis_pairs == 8
    a = _bench._settings(["--equal-time", "30", "--size", "96", "--algorithms", "pt,vcm"])
    assert a.mode == "equal-time" and a.equal_time == 30.0 and a.size == 96
    assert a.algorithms == ["pt", "vcm"]
    assert [p.stem for p in a.scene_paths] == ["pool", "pool_sun", "pool_wall"]
    a = _bench._settings(["--equal-time", "2"])
    assert a.algorithms == ["pt", "bdpt", "ppm", "vcm"] and a.size == 128
    assert _bench._settings([]).mode is None


def test_bench_vm_bad_arguments(capsys):
    assert _bench.main(["--equal-time", "0"]) == 2
    assert _bench.main(["--compare-mis", "--equal-time", "5"]) == 2
    assert _bench.main(["--compare-mis", "--full-size"]) == 2
    assert _bench.main(["--compare-mis", "--mis-pairs", "0"]) == 2
    assert _bench.main(["--equal-time", "5", "--algorithms", "nope"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 5 and all(ln.startswith("jaxvcm: error: bench: ") for ln in err)


def test_bench_vm_sections_and_figure(tmp_path):
    import numpy as np

    from benchmarks import vertex_merging as _bench_vm

    md = tmp_path / "b.md"
    md.write_text("# title\n\nhand-written text\n")
    _common.upsert_section(md, "mis-forms", "first\n")
    _common.upsert_section(md, "equal-time", "table\n")
    _common.upsert_section(md, "mis-forms", "second\n")
    text = md.read_text()
    assert text.startswith("# title\n\nhand-written text\n")
    assert "first" not in text and text.count("<!-- bench:mis-forms:begin -->") == 1
    assert text.index("second") < text.index("table")

    rng = np.random.default_rng(0)
    row = [{"image": rng.random((8, 8, 3)) * s, "passes": 3, "seconds": 1.0}
           for s in (1.0, 2.0)]
    assert abs(_bench_vm.row_exposure([np.full((4, 4, 3), 4.0)]) + 2.0) < 1e-12
    png = tmp_path / "grid.png"
    _bench_vm.equal_time_figure(png, [row, row], ["a", "b"], ["pt", "vcm"])
    assert png.stat().st_size > 1000


def test_report_merge_keeps_hand_written_text_and_adds_no_marker_from_the_header():
    # A run replaces only its own section (in place) and the generated header; the header's
    # description of the markers must not itself parse as a section (it once did, adding an
    # empty block on every run), and hand-written sections outside the markers survive.
    from benchmarks.bench import _SECTION_RE, HEADER, _merge_markdown

    header = HEADER.format(json="benchmarks.json", off=1, eps=0.01, depth=8, tscene="pool",
                           target=1.5, tcpu=2, machine="- m")
    assert not list(_SECTION_RE.finditer(header))
    old = _merge_markdown("", header, "a", "first A")
    old = old + "\n## Hand-written\nkeep me\n"
    new = _merge_markdown(old, header, "b", "B")
    new = _merge_markdown(new, header, "a", "second A")
    assert "keep me" in new and "second A" in new and "first A" not in new
    assert [m.group("tag") for m in _SECTION_RE.finditer(new)] == ["a", "b"]
    assert new.count("# jaxvcm benchmarks") == 1


def test_bench_startup_mode(tmp_path, monkeypatch):
    # --startup: defaults (pool, 256, pt bdpt vcm) and the table from the timed runs; the
    # subprocess runs are replaced by fixed times and a sidecar with the first pass's
    # seconds, so the table's cells must be exactly the medians of those
    from benchmarks import startup as _st

    a = _bench._settings(["--startup"])
    assert a.mode == "startup" and a.size == 256 and a.algorithms == ["pt", "bdpt", "vcm"]
    assert [p.stem for p in a.scene_paths] == ["pool"] and a.startup_runs == 3
    assert _bench.main(["--startup", "--profile"]) == 2
    a = _bench._settings(["--startup", "--algorithms", "vcm", "--startup-runs", "3",
                          "--size", "8", "--out", str(tmp_path / "b.md")])
    times = iter([1.0, 1.2, 0.8,  # import, 3 runs
                  20.0, 2.0, 22.0, 2.5, 21.0, 2.2,  # (cold, warm) x 3 runs, as the CLI renders
                  10.0, 2.0, 12.0, 2.2, 11.0, 2.1])  # ... and with --no-glints
    seen = []

    def fake(args, env):
        assert env["JAXVCM_CACHE_DIR"] and "optimization_level" not in env["XLA_FLAGS"]
        assert "fusion_emitters" not in env["XLA_FLAGS"]
        assert "codegen_split_count" not in env["XLA_FLAGS"]
        seen.append("--no-glints" in args)
        t = next(times)
        if "render" in args:
            out = args[args.index("--out") + 1]
            with open(out[:-4] + ".json", "w") as f:
                json.dump({"seconds": t - 1.5}, f)
        return t

    monkeypatch.setattr(_st, "_timed", fake)
    res = _st.run_startup(a, ["--startup"], a.scene_paths[0], lambda *x: None)
    assert res["import_s"] == 1.0
    row = _table((tmp_path / "b.md").read_text(), "algorithm")[0]
    assert row["algorithm"] == "vcm"
    assert row["cold process"] == "21.00 s" and row["warm process"] == "2.20 s"
    assert row["cold first pass"] == "19.50 s" and row["warm first pass"] == "0.70 s"
    assert json.loads((tmp_path / "b_startup.json").read_text())["rows"][0]["all"][
        "warm_process_s"] == [2.0, 2.5, 2.2]
    # vcm's own program without the glints the command line adds: a second row, last 6 runs
    assert seen == [False] * 9 + [True] * 6
    row = _table((tmp_path / "b.md").read_text(), "algorithm")[1]
    assert row["algorithm"] == "vcm --no-glints"
    assert row["cold process"] == "11.00 s" and row["cold first pass"] == "9.50 s"
    assert row["warm process"] == "2.10 s" and row["warm first pass"] == "0.60 s"


def test_bench_scaling_mode(tmp_path, monkeypatch):
    # --scaling: the sweep's rows and the devices child are replaced by fixed figures, so
    # the table, the linearity line (max/min of us per path over the chunked rows) and the
    # devices speed-up must be exactly those figures'
    import subprocess as sp

    from benchmarks import scaling as _sc

    a = _bench._settings(["--scaling"])
    assert a.mode == "scaling" and a.algorithms == ["vcm"]
    assert [p.stem for p in a.scene_paths] == ["pool"]
    assert _bench.main(["--scaling", "--startup"]) == 2
    a = _bench._settings(["--scaling", "--out", str(tmp_path / "b.md")])
    us = {(256, 1): 50.0, (256, 4): 40.0, (512, 1): 55.0, (512, 16): 38.0,
          (1024, 64): 40.0, (2048, 256): 44.0}

    def fake_one(scene, alg, size, depth, chunks, passes, log):
        n = size * size
        return {"algorithm": alg, "size": size, "paths": n, "chunks": chunks,
                "compile_s": 30.0, "pass_s": us[size, chunks] * n / 1e6, "passes": passes,
                "memory_bytes": 2**20 * (n // chunks) // 64, "merge_overflow": False,
                "us_per_path": us[size, chunks]}

    def fake_run(args, env):
        assert "--xla_force_host_platform_device_count=2" in env["XLA_FLAGS"]
        out = "RESULT " + json.dumps({"pt": {"1": 3.0, "2": 2.0}, "vcm": {"1": 6.0, "2": 4.8}})
        return sp.CompletedProcess(args, 0, out, "")

    monkeypatch.setattr(_sc, "_one", fake_one)
    monkeypatch.setattr(_sc, "_run_child", fake_run)
    _sc.run_scaling(a, ["--scaling"], a.scene_paths[0], lambda *x: None)
    text = (tmp_path / "b.md").read_text()
    rows = _table(text, "algorithm")
    assert [(r["image"], r["chunks"]) for r in rows[:6]] == [
        ("256x256", "1"), ("256x256", "4"), ("512x512", "1"), ("512x512", "16"),
        ("1024x1024", "64"), ("2048x2048", "256")]
    assert rows[5]["us / path"] == "44.0" and rows[5]["paths"] == "4,194,304"
    assert "spans 38.0-44.0 us (max/min 1.16;" in text
    dev = _table(text.split("2 forced CPU devices", 1)[1], "algorithm")
    assert [(r["algorithm"], r["speed-up"]) for r in dev] == [("pt", "1.50"), ("vcm", "1.25")]


def test_bench_scene_size_mode(tmp_path, monkeypatch):
    # --scene-size: the children are replaced by fixed figures; the rows are the waves'
    # sweep (one light) then the lights' (the shipped four waves), in the table as given
    from benchmarks import scene_size as _ss

    a = _bench._settings(["--scene-size"])
    assert a.mode == "scene-size" and a.algorithms == ["vcm"]
    assert [p.stem for p in a.scene_paths] == ["pool"]
    assert _bench.main(["--scene-size", "--scaling"]) == 2
    a = _bench._settings(["--scene-size", "--out", str(tmp_path / "b.md")])
    calls = []

    def fake_child(scene_path, waves, lights, size, depth, log):
        calls.append((waves, lights, size, depth))
        return {"waves": waves or 4, "lights": lights, "lines": 22000 + waves, "lower_s": 3.0,
                "compile_s": 10.0 + lights / 100, "temp_bytes": 5 * 2**20,
                "pass_s": 0.02 * (1 + waves / 10), "peak_rss_bytes": 2**30}

    monkeypatch.setattr(_ss, "_child", fake_child)
    _ss.run_scene_size(a, ["--scene-size"], a.scene_paths[0], lambda *x: None)
    assert calls == [(1, 1, 32, 8), (10, 1, 32, 8), (100, 1, 32, 8), (1000, 1, 32, 8),
                     (0, 10, 32, 8), (0, 100, 32, 8)]
    rows = _table((tmp_path / "b.md").read_text(), "waves")
    assert [(r["waves"], r["lights"], r["StableHLO lines"]) for r in rows] == [
        ("1", "1", "22,001"), ("10", "1", "22,010"), ("100", "1", "22,100"),
        ("1000", "1", "23,000"), ("4", "10", "22,000"), ("4", "100", "22,000")]
    assert rows[3]["pass"] == "2020.0 ms" and rows[5]["compile"] == "11.0 s"
    assert json.loads((tmp_path / "b_scene-size.json").read_text())["size"] == 32


# ---- SmallVCM's scene 0 (--smallvcm): settings, the ratios and the verdict, no rendering
def test_bench_smallvcm_settings_and_ratios():
    import numpy as np

    from benchmarks import smallvcm as _sv
    a = _bench._settings(["--smallvcm"])
    assert a.mode == "smallvcm" and a.algorithms == ["pt", "bdpt", "ppm", "bpm", "vcm"]
    assert a.reference_time == 600.0
    # SmallVCM's first radius in metres: 0.00665 = radius fraction x the view radius
    scene = type("S", (), {"view_radius": 2.0})()
    cfg = _sv.config("ppm", scene)
    assert cfg.mis == "balance" and cfg.max_depth == 10 and cfg.alpha == 0.75
    assert math.isclose(cfg.radius * 2.0, 0.00665, rel_tol=1e-12)
    # the reference's noise comes off in quadrature: sqrt(0.05^2 - 0.03^2) = 0.04
    assert math.isclose(_sv.rmse_corrected(0.05, 0.03), 0.04, rel_tol=1e-12)
    assert _sv.rmse_corrected(0.02, 0.03) == 0.0
    # a uniform error of 0.05 in every pixel, reference noise 0.04: corrected RMSE 0.03;
    # vcm at 30 / 90 s: 0.03 / 0.0489 = 0.61, 0.03 / 0.0322 = 0.93 (met); 65,536 x 2
    # paths per pass, 10 passes in 1 s: 1,310,720 paths/s, SmallVCM's 532 k / that = 0.41
    ref = np.zeros((4, 4, 3))
    runs = [{"budget": b, "passes": 10, "seconds": 1.0, "image": ref + 0.05,
             "camera_paths": 655_360, "light_paths": 655_360, "over_budget": False}
            for b in _sv.BUDGETS]
    rows = _sv.rows_for("vcm", runs, ref, 0.04)
    assert math.isclose(rows[1]["rmse_ratio"], 0.03 / 0.0489, rel_tol=1e-9)
    assert math.isclose(rows[2]["paths_ratio"], 532e3 / 1_310_720, rel_tol=1e-9)
    for r in rows:
        r["warm_up_s"] = 1.0
    text = _sv.verdict(rows)
    assert "missed: none" in text and "vcm RMSE at 90 s (0.93)" in text
    rows[2]["rmse_ratio"] = 1.5  # a planted miss must be reported
    assert "missed: vcm RMSE at 90 s (1.50)" in _sv.verdict(rows)
