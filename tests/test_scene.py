"""Scene validation: every bad input is one InputError naming the file, key and problem."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mvfem.errors import InputError
from mvfem.scene import load_scene, parse_set_option
from mvfem.units import MMHG_PA, PRESSURE, parse_quantity

BASE = {"mesh": {"generator": "disk", "radius": 5.0, "size": 1.0},
        "region": [{"law": "mny", "params": "MNY-mean"}]}


def test_defaults_and_units():
    s = load_scene(BASE)
    assert s["load"]["pressure"] == 16e3 and s["load"]["follower"] is True
    assert s["region"][0]["thickness"] == 0.85  # from the MNY-mean set
    assert s["region"][0]["params"] == {"c0": 399.0, "c1": 4.325, "c2": 1446.5}
    s2 = s.with_changes({"load.pressure": "120 mmHg", "region.0.thickness": "0.1 cm"})
    assert s2["load"]["pressure"] == pytest.approx(120 * 133.322368, rel=1e-8)
    assert s2["region"][0]["thickness"] == pytest.approx(1.0)
    assert s["load"]["pressure"] == 16e3  # the original is unchanged


@pytest.mark.parametrize("text,value", [("16 kPa", 16e3), ("120 mmHg", 120 * MMHG_PA),
                                        ("0.5MPa", 5e5), (250, 250.0), ("1e3 Pa", 1e3)])
def test_pressure_units(text, value):
    assert parse_quantity(text, PRESSURE, "Pa") == pytest.approx(value)


@pytest.mark.parametrize("change,words", [
    ({"mesh.colour": "red"}, ["mesh.colour", "unknown key"]),
    ({"mesh.generator": "cube"}, ["mesh.generator", "disk"]),
    ({"mesh.radius": -2}, ["mesh.radius", "positive"]),
    ({"mesh.radius": "2 furlongs"}, ["mesh.radius", "unknown unit"]),
    ({"load.pressure": "16 kPaa"}, ["load.pressure", "kPaa"]),
    ({"load.pressure": True}, ["load.pressure"]),
    ({"load.follower": "yes"}, ["load.follower", "true or false"]),
    ({"region.0.thickness": -0.1}, ["region[0].thickness", "positive"]),
    ({"region.0.params": "CP11"}, ["region[0].params", "CP11", "unknown"]),
    ({"region.0.law": "hooke"}, ["region[0].law", "svk"]),
    ({"region.0.law": "svk"}, ["region[0].params", "for law 'mny'"]),
    ({"region.0.params": {"c0": 1.0, "c1": 2.0}}, ["region[0].params.c2", "required"]),
    ({"region.0.params": {"c0": 1.0, "c1": 2.0, "c2": 1.0, "E": 3.0}}, ["region[0].params.e"]),
    ({"region.0.fibre_compression": "no"}, ["region[0].fibre_compression", "true or false"]),
    ({"region.0.law": "svk", "region.0.params": "SVK", "region.0.fibre_compression": False},
     ["region[0].fibre_compression", "no fibre term"]),
    ({"solver.degree": 0}, ["solver.degree", "at least 1"]),
    ({"solver.degree": 1.5}, ["solver.degree", "integer"]),
    ({"solver.degree": 50}, ["solver.degree", "at most 4", "compile for minutes"]),
    # (session 62: gmsh aborted the process, exit code 134, on a disk of radius 1e9 mm)
    ({"mesh.radius": 1e10}, ["mesh.radius", "1e+10 mm is longer than 1e+06 mm"]),
    ({"mesh.radius": "2000 m"}, ["mesh.radius", "longer than"]),
    ({"solver.quadrature_degree": 200}, ["solver.quadrature_degree", "at most 20"]),
    ({"fibres.direction": [0, 0, 0]}, ["fibres.direction", "zero"]),
    ({"fibres.axis": [0, 0, 0]}, ["fibres.axis", "zero"]),
    ({"fibres.centre": [1e300, 0, 0]}, ["fibres.centre", "farther than 1e+06 mm"]),
    ({"fibres.direction": "spiral"}, ["fibres.direction", "circumferential"]),
    ({"output.probes": [{"name": "a", "point": [0, 0]}]}, ["output.probes[0].point"]),
    ({"mesh.generator": "file", "mesh.file": "no/such.vtu"}, ["mesh.file", "no such file"]),
    # (session 62: these were "no such file", and a name too long an OSError traceback)
    ({"mesh.generator": "file", "mesh.file": "/"}, ["mesh.file", "a directory, not a file"]),
    ({"mesh.generator": "file", "mesh.file": "/dev/null"}, ["mesh.file", "not a regular file"]),
    ({"mesh.generator": "file", "mesh.file": "a" * 300 + ".vtu"},
     ["mesh.file", "cannot be looked up (File name too long)"]),
    ({"colour": 1}, ["colour", "unknown key"]),
    # (session 62: TOML integers have any number of digits; float() of these overflowed)
    ({"mesh.radius": 10**400}, ["mesh.radius", "401 digits", "beyond the range of a float"]),
    ({"solver.max_it": -10**309}, ["solver.max_it", "310 digits"]),
    ({"mesh.size": 10**400}, ["mesh.size", "401 digits"]),
    ({"fibres.centre": [10**320, 0, 0]}, ["fibres.centre", "a component is an integer of 321"]),
    ({"output.probes": [{"name": "a", "point": [0, -10**320, 0]}]},
     ["output.probes[0].point", "321 digits"]),
    # (session 62: a path through a value, not a table, was a TypeError)
    ({"region.0.law.a.b": 1}, ["--set region.0.law.a.b", "region.0.law is not a table"]),
    ({"mesh.radius.x.y": 1}, ["--set mesh.radius.x.y", "mesh.radius is not a table"]),
    ({"region.0.params.E.x": 1}, ["region.0.params is not a table"]),
])
def test_bad_values(change, words):
    with pytest.raises(InputError) as e:
        load_scene(BASE).with_changes(change)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("<dict>: ")
    for w in words:
        assert w in msg, msg


@pytest.mark.parametrize("given", [[1e200, 1e200, 0.0], [1e-200, 1e-200, 0.0], [3.0, 3.0, 0.0]])
def test_fibre_vectors_are_unit_vectors_at_any_scale(given):
    """A direction or axis of any length is its unit vector ([1e200, 1e200, 0] overflowed to
    NaN directions and a stop, exit code 3, until session 62)."""
    s = load_scene(BASE).with_changes({"fibres.direction": given, "fibres.axis": given})
    half = 0.5 ** 0.5
    assert s["fibres"]["direction"] == pytest.approx([half, half, 0.0], rel=1e-15)
    assert s["fibres"]["axis"] == pytest.approx([half, half, 0.0], rel=1e-15)


def test_point_files_beyond_a_kilometre_are_refused(tmp_path):
    """A loop of points 1e7 mm from the origin (an annulus target in the wrong unit) is
    refused naming the file and the point: until session 62 it asked for 1.4 PiB after the
    solve, in a traceback."""
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    far = tmp_path / "far.csv"
    np.savetxt(far, np.c_[1e7 * np.cos(t), 1e7 * np.sin(t), 0 * t], delimiter=",")
    near = tmp_path / "near.csv"
    np.savetxt(near, np.c_[9 * np.cos(t), 9 * np.sin(t), 0 * t], delimiter=",")
    assert load_scene(BASE).with_changes({"annulus.target": str(near)})
    with pytest.raises(InputError, match=r"annulus\.target: .*far\.csv: point 0 .* farther "
                                         r"than 1e\+06 mm"):
        load_scene(BASE).with_changes({"annulus.target": str(far)})
    valve = {"mesh": {"generator": "valve", "annulus": str(far)}, "region": BASE["region"]}
    with pytest.raises(InputError, match=r"mesh\.annulus: .*far\.csv: point 0"):
        load_scene(valve)


def test_bad_files(tmp_path):
    with pytest.raises(InputError, match="no such scene file"):
        load_scene(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[mesh\ngenerator = 'disk'\n")
    with pytest.raises(InputError, match=r"bad.toml: not valid TOML"):
        load_scene(bad)
    with pytest.raises(InputError, match=r"^/dev/null: not a regular file$"):
        load_scene("/dev/null")
    with pytest.raises(InputError, match=r"a{300}\.toml: cannot be looked up \(File name too"):
        load_scene(tmp_path / ("a" * 300 + ".toml"))
    nomesh = tmp_path / "nomesh.toml"
    nomesh.write_text("[[region]]\nlaw = 'mny'\nparams = 'CP01'\n")
    with pytest.raises(InputError, match=r"nomesh.toml: mesh: required"):
        load_scene(nomesh)


def test_a_directory_or_an_unreadable_file_is_one_line(tmp_path, monkeypatch):
    """A directory given as the scene, and a scene file that cannot be read (no permission:
    root reads anything, so the read is made to fail), are input errors naming the path;
    until session 55 the first said "no such scene file" and the second was a traceback."""
    from pathlib import Path

    with pytest.raises(InputError, match=r": a directory, not a scene file$"):
        load_scene(tmp_path)
    scene = tmp_path / "locked.toml"
    scene.write_text("[mesh]\ngenerator = 'disk'\n")

    def refused(self, *a, **k):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "read_text", refused)
    with pytest.raises(InputError, match=r"locked.toml: cannot be read \(Permission denied\)"):
        load_scene(scene)


def test_set_option_parsing():
    assert parse_set_option("solver.degree=2") == ("solver.degree", 2)
    assert parse_set_option("load.pressure=120 mmHg") == ("load.pressure", "120 mmHg")
    assert parse_set_option('load.pressure="16 kPa"') == ("load.pressure", "16 kPa")
    assert parse_set_option("load.follower=false") == ("load.follower", False)
    with pytest.raises(InputError):
        parse_set_option("nokey")


def test_example_scenes_validate():
    from pathlib import Path

    scenes = sorted((Path(__file__).resolve().parents[1] / "scripts" / "scenes").glob("*.toml"))
    assert scenes
    for path in scenes:
        s = load_scene(path)
        assert s["mesh"]["generator"] and s["region"]


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[1] / "scripts" / "scenes")
                                        .glob("*.toml")), ids=lambda p: p.stem)
def test_example_scenes_load(path):
    """Every example scene in scripts/scenes is valid (its files found relative to it)."""
    scene = load_scene(path)
    assert scene["load"]["pressure"] > 0
