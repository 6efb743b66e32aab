"""One plant spec: build_plant from names, plant files that round-trip exactly, one-line errors
naming the file, the key and the allowed values."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.effects import REGISTRY
from jaxcart.errors import UserError
from jaxcart.plantsource import load_plant
from jaxcart.plantspec import (
    build_plant,
    describe_plant,
    parameter_names,
    plant_values,
    read_plant_file,
    write_plant_file,
)

#: One value per parameter of every registered effect (inside its declared range).
VALUES = {
    "v_sat": 5.5,
    "f_c": 0.41,
    "f_s": 0.62,
    "delay": 0.0031,
    "deadzone": 0.27,
    "k_s": 12.5,
    "y_rest": -0.05,
    "backlash": 3e-4,
    "i_max": 1.7,
    "quantization": 2.275e-5,
    "f_track": (0.1, 0.3, 0.2, 0.4, 0.25),
}


def _values_of(names):
    out = {}
    for name in names:
        for p in REGISTRY[name].params:
            out[p.name] = VALUES.get(p.name, p.start)
    return out


def test_every_parameter_is_named_once_with_unit_and_range():
    names = parameter_names()
    assert len(names) == len(set(names))
    for must in (
        "M",
        "B_eq",
        "gamma_scale",
        "v_sat",
        "f_c",
        "f_s",
        "delay",
        "deadzone",
        "k_s",
        "y_rest",
        "i_max",
        "quantization",
    ):
        assert must in names


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_naming_a_parameter_adds_its_effect(name):
    plant = build_plant({"B_eq": 4.0, **_values_of([name])})
    assert plant.structure == (name,)
    assert plant.B_eq == 4.0


@pytest.mark.parametrize("pair", list(itertools.combinations(sorted(REGISTRY), 2))[::3])
def test_plant_files_round_trip_exactly(tmp_path, pair):
    plant = build_plant({"M": 1.13, "gamma_scale": 0.93, **_values_of(pair)})
    path = write_plant_file(tmp_path / "p.toml", plant, fit={"rms_after": 1e-4, "held": ["M"]})
    again, fit = read_plant_file(path)
    assert again == plant
    assert fit == {"rms_after": 1e-4, "held": ["M"]}
    # And the values rebuild it through the one builder.
    assert build_plant(plant_values(plant)) == plant


def test_every_effect_together_round_trips(tmp_path):
    plant = build_plant(_values_of(REGISTRY))
    assert set(plant.structure) == set(REGISTRY)
    path = write_plant_file(tmp_path / "all.toml", plant)
    assert read_plant_file(path)[0] == plant
    assert load_plant(path) == plant
    text = describe_plant(plant)
    assert all(n in text for n in REGISTRY)


def test_tap_plant_file_keeps_the_unplugged_motor(tmp_path):
    plant = jc.tap_plant(B_eq=1.5, f_c=0.44)
    again = read_plant_file(write_plant_file(tmp_path / "tap.toml", plant))[0]
    assert again == plant and again.motor_connected is False


def test_an_experiment_file_gives_its_plant(tmp_path):
    (tmp_path / "run.csv").write_text("t,y\n0,0\n0.001,0\n0.002,0\n")
    (tmp_path / "exp.toml").write_text(
        'kind = "tap"\nsample_time = 0.001\ndata = "run.csv"\n[plant]\nB_eq = 2.0\nf_c = 0.3\n'
    )
    plant = load_plant(tmp_path / "exp.toml")
    assert plant.B_eq == 2.0 and plant.structure == ("coulomb",) and not plant.motor_connected


@pytest.mark.parametrize(
    ("values", "expected"),
    [
        ({"Beq": 2.0}, ["'Beq'", "known:", "B_eq"]),
        ({"f_c": -0.1}, ["f_c = -0.1 N", "out of its range [0, 20] N"]),
        ({"delay": 1.0}, ["delay = 1.0 s", "out of its range"]),
        ({"M": 0.0}, ["M = 0.0 kg", "out of its range"]),
        ({"f_c": "high"}, ["f_c = 'high'", "give a number", "N"]),
        ({"f_track": [0.1]}, ["f_track", "list of 2 or more"]),
    ],
)
def test_bad_values_are_one_line_naming_the_key(values, expected):
    with pytest.raises(UserError) as info:
        build_plant(values, where="p.toml")
    message = str(info.value)
    assert "\n" not in message and message.startswith("p.toml")
    for piece in expected:
        assert piece in message


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "[plant]\nf_c = 0.3\n[effects.coulomb]\nf_c = 0.4\n",
            ["'coulomb' is named twice", "give each effect once"],
        ),
        ("[effects.coulomb]\nf_c = 0.3\n[effects.coulomb]\nf_c = 0.4\n", ["twice"]),
        ("[effects.friction]\nf_c = 0.3\n", ["unknown effect 'friction'", "coulomb"]),
        ("[effects.coulomb]\nf_s = 0.3\n", ["effects.coulomb", "unknown parameter 'f_s'", "f_c"]),
        ('structure = ["coulomb", "coulomb"]\n[effects.coulomb]\n', ["named twice"]),
        ('structure = ["delay"]\n[effects.coulomb]\n', ["structure", "match"]),
        ("colour = 1\n", ["unknown key 'colour'"]),
    ],
)
def test_bad_plant_files_are_one_line(tmp_path, text, expected):
    path = tmp_path / "bad.toml"
    path.write_text('format = "jaxcart-plant"\nversion = 1\n' + text)
    with pytest.raises(UserError) as info:
        read_plant_file(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    for piece in expected:
        assert piece in message


def test_no_plant_file_is_written_over(tmp_path):
    path = write_plant_file(tmp_path / "p.toml", jc.handout_plant())
    with pytest.raises(UserError, match="exists"):
        write_plant_file(path, jc.handout_plant(f_c=0.3))
    assert read_plant_file(path)[0] == jc.handout_plant()


def test_a_file_that_is_not_a_plant_file(tmp_path):
    path = tmp_path / "gains.toml"
    path.write_text("kp = 1.0\n")
    with pytest.raises(UserError, match='format = "jaxcart-plant"'):
        read_plant_file(path)


def test_values_are_plain_floats():
    values = plant_values(build_plant({"B_eq": np.float64(3.0), "f_track": [0.1, 0.2]}))
    assert values == {"B_eq": 3.0, "f_track": (0.1, 0.2)}
