"""Scene files over shared bases (`base = ...`): the merge rule (tables key by key,
[[shapes]] and [[lights]] appended, other values replaced), the Cornell variants as small
files over scenes/_base/, and one-line errors for missing files, cycles and bad values."""

from __future__ import annotations

import os

import numpy as np
import pytest

import jaxvcm
from jaxvcm import SceneError
from jaxvcm._io._scene_file import MAX_BASES, merge_docs, read_scene_doc

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
VARIANTS = ["cornell", "cornell_spheres", "cornell_sun", "cornell_background", "cornell_point"]

CAMERA = """[camera]
position = [0.0, 0.0, 4.0]
target = [0.0, 0.0, 0.0]
fov = 30.0
width = 4
height = 4
"""
SPHERE = """[materials.grey]
type = "diffuse"
albedo = 0.5

[[shapes]]
type = "sphere"
center = [0.0, 0.0, 0.0]
radius = 1.0
material = "grey"
"""


def test_merge_rule():
    base = {"camera": {"fov": 30.0, "width": 4}, "shapes": [1], "lights": [2], "name": "a"}
    over = {"camera": {"fov": 45.0}, "shapes": [3], "name": "b", "water": {"level": 0.0}}
    assert merge_docs(base, over) == {"camera": {"fov": 45.0, "width": 4}, "shapes": [1, 3],
                                      "lights": [2], "name": "b", "water": {"level": 0.0}}


def test_bases_in_order_then_the_file(tmp_path):
    (tmp_path / "cam.toml").write_text(CAMERA)
    (tmp_path / "ball.toml").write_text(SPHERE)
    (tmp_path / "s.toml").write_text(
        'base = ["cam.toml", "ball.toml"]\n[camera]\nfov = 20.0\n'
        '[[shapes]]\ntype = "sphere"\ncenter = [2.0, 0.0, 0.0]\nradius = 0.5\nmaterial = "grey"\n'
        '[[lights]]\ntype = "background"\nradiance = 1.0\n')
    sc = jaxvcm.load_scene(str(tmp_path / "s.toml"))
    # the base's sphere first, then the file's; the file's fov replaced the base's
    np.testing.assert_allclose(np.asarray(sc.spheres.radius), [1.0, 0.5])
    assert float(sc.camera.tan_half_fov) == pytest.approx(np.tan(np.radians(10.0)), rel=1e-6)
    assert sc.name == "s"


@pytest.mark.parametrize("name", VARIANTS)
def test_cornell_variants_are_small_files_over_shared_bases(name):
    path = os.path.join(ROOT, "scenes", f"{name}.toml")
    lines = [ln for ln in open(path).read().splitlines() if ln.strip() and not ln.startswith("#")]
    assert len(lines) <= 16, f"{name}: {len(lines)} lines; the shared parts belong in _base/"
    doc = read_scene_doc(path)
    assert "base" not in doc and len(doc["shapes"]) >= 7  # 5 walls and its own shapes


@pytest.mark.parametrize("text,field,msg", [
    ('base = "missing.toml"\n', "base", "file not found"),
    ('base = 3\n', "base", "expected a file name"),
    ('base = []\n', "base", "expected a file name"),
    ('base = ["s.toml"]\n', "base[0]", "a cycle"),
], ids=["missing", "number", "empty", "self"])
def test_bad_base_names_the_field(tmp_path, text, field, msg):
    p = tmp_path / "s.toml"
    p.write_text(text + CAMERA)
    with pytest.raises(SceneError) as e:
        jaxvcm.load_scene(str(p))
    line = str(e.value)
    assert f": {field}: " in line and msg in line and "\n" not in line, line


def test_cycle_through_another_file_and_chain_length(tmp_path):
    (tmp_path / "a.toml").write_text('base = "b.toml"\n' + CAMERA)
    (tmp_path / "b.toml").write_text('base = "a.toml"\n')
    with pytest.raises(SceneError, match="a cycle"):
        jaxvcm.load_scene(str(tmp_path / "a.toml"))
    for i in range(MAX_BASES + 1):  # c0 <- c1 <- ... : one file more than a chain may hold
        (tmp_path / f"c{i}.toml").write_text(f'base = "c{i + 1}.toml"\n' if i < MAX_BASES
                                             else CAMERA)
    with pytest.raises(SceneError, match="chain of bases"):
        jaxvcm.load_scene(str(tmp_path / "c0.toml"))
