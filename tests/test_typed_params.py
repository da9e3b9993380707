"""Typed plugin parameters (src/mfnormal/models/properties.py): every parameter of
``normalmap_microfacet``, ``mfnormal_path`` and ``mfnormal_prb`` takes only values of its type and
range, through ``mi.load_dict``, XML and ``mi.traverse`` updates, and refuses any other at load in one
line that names the plugin, the parameter and what it expects (the last line of Mitsuba's
"failed to instantiate" wrapper; the command line prints it alone).

- The cases found by hand: ``terminator_offset`` given as the string "false" or "no", or NaN, was
  taken as true; "abc" for a number, NaN or ±inf for an integer, 5 for ``tangents``, 2^40 or NaN
  for ``max_depth`` were errors that did not name the parameter, or loaded and failed at render;
  ``max_bounces`` 1.5 became 1.
- A sweep: every wrong value of every parameter (tests/param_fuzzing.py decides which, by the kind
  and range) through ``mi.load_dict`` and XML; every valid one loads and is in effect.
- ``mi.traverse``: an update of an exposed parameter to a wrong number is refused and undone.
- The parameter tables of the plugin reference list exactly the typed parameters.
- The fuzzer: random sets of several parameters, each valid or wrong, through both ways
  (``CI_INPUTS`` in the default run, ``LONG_INPUTS`` behind MFNORMAL_SLOW=1), and random
  ``mi.traverse`` updates.
"""

from __future__ import annotations

import math
import re

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import mitsuba as mi
import numpy as np
import pytest
from hypothesis import strategies as st

from cli_checks import assert_one_line_error
from fuzzing import fuzz_test, input_count
from helpers import write_maps, xml_plugin, xml_scene
from param_fuzzing import (PLUGINS, assert_names, params, plugin_dict, plugin_xml, refusal, valid_values,
                           write_map, wrong_updates, wrong_values)

CI_INPUTS, LONG_INPUTS = 60, 3000


@pytest.fixture(scope="module")
def map_file(tmp_path_factory):
    return write_map(tmp_path_factory.mktemp("typed_params"))


def load_dict(plugin, values):
    return refusal(lambda: mi.load_dict(plugin_dict(plugin, values)))


def load_xml(plugin, values, map_file):
    return refusal(lambda: mi.load_string(plugin_xml(plugin, values, map_file)))


# -- 1. The cases found by hand ----------------------------------------------------------------------

INTEGRATORS = ["mfnormal_path", "mfnormal_prb"]


@pytest.mark.parametrize("plugin", INTEGRATORS)
@pytest.mark.parametrize("value", ["false", "no", math.nan, 0])
def test_terminator_offset_is_a_boolean(plugin, value, map_file):
    """Given as a string, NaN or 0 (through load_dict and XML) it was taken as true."""
    for line in (load_dict(plugin, {"terminator_offset": value}),
                 load_xml(plugin, {"terminator_offset": value}, map_file)):
        assert_names(line, plugin, ["terminator_offset"])
        assert "must be a boolean" in line and '<boolean name="terminator_offset"' in line, line


@pytest.mark.parametrize("plugin", INTEGRATORS)
def test_terminator_offset_given_as_a_boolean_is_taken(plugin):
    for value in (True, False):
        assert mi.load_dict({"type": plugin, "terminator_offset": value}).terminator_offset is value
        xml = f'<boolean name="terminator_offset" value="{str(value).lower()}"/>'
        scene = mi.load_string(f'<scene version="3.0.0"><integrator type="{plugin}">{xml}</integrator></scene>')
        assert scene.integrator().terminator_offset is value
    assert mi.load_dict({"type": plugin}).terminator_offset is True


HAND_CASES = [("normalmap_microfacet", "strength", "abc"), ("normalmap_microfacet", "neighbourhood", "abc"),
              ("normalmap_microfacet", "height_scale", "abc"), ("normalmap_microfacet", "mis_boost_max", "abc"),
              ("normalmap_microfacet", "max_bounces", math.nan), ("normalmap_microfacet", "max_bounces", math.inf),
              ("normalmap_microfacet", "rr_depth", "abc"), ("normalmap_microfacet", "tangents", 5),
              ("normalmap_microfacet", "max_bounces", 1.5), ("mfnormal_path", "rr_depth", "abc")] + [
    (plugin, "max_depth", value) for plugin in INTEGRATORS for value in ("abc", 2 ** 40, math.nan)]


@pytest.mark.parametrize("plugin,name,value", HAND_CASES)
def test_a_wrong_value_names_the_parameter_at_load(plugin, name, value, map_file):
    """Through load_dict and XML alike: one line, the parameter, what it expects, what it got."""
    for line in (load_dict(plugin, {name: value}), load_xml(plugin, {name: value}, map_file)):
        assert assert_names(line, plugin, [name]) == name
        assert (repr(value) if isinstance(value, str) else str(value)) in line, line


# -- 2. Every wrong and every valid value of every parameter --------------------------------------------

def test_every_wrong_value_of_every_parameter_is_refused_in_one_line(map_file):
    """About 300 values × (load_dict, XML); each names its parameter."""
    count = 0
    for plugin in PLUGINS:
        for name, param in params(plugin).items():
            for value in wrong_values(param):
                assert_names(load_dict(plugin, {name: value}), plugin, [name])
                assert_names(load_xml(plugin, {name: value}, map_file), plugin, [name])
                count += 1
    assert count > 250


def test_every_valid_value_of_every_parameter_loads_and_is_in_effect(map_file):
    """Each valid value alone (a walk's max_bounces, rr_depth and mis_boost_max shown by the model,
    an integrator's attributes) loads through load_dict and XML."""
    for plugin in PLUGINS:
        for name, param in params(plugin).items():
            for value in valid_values(param):
                assert load_dict(plugin, {name: value}) is None, (plugin, name, value)
                assert load_xml(plugin, {name: value}, map_file) is None, (plugin, name, value)
    for value in (2 ** 31 - 1, 1):
        assert mi.load_dict({"type": "mfnormal_path", "max_depth": value}).max_depth == value
    assert mi.load_dict({"type": "mfnormal_prb", "rr_depth": 7}).rr_depth == 7
    bsdf = mi.load_dict(plugin_dict("normalmap_microfacet", {"max_bounces": 9, "rr_depth": 0, "mis_boost_max": 2}))
    assert bsdf.model.ok == (9, 0, 2.0)


def test_the_parameter_tables_list_every_typed_parameter():
    """The plugin reference (each plugin's docstring) and the typed parameters name the same
    parameters: a new parameter needs both."""
    from mfnormal.plugins import mfnormal_path, mfnormal_prb, normalmap_microfacet

    for module in (normalmap_microfacet, mfnormal_path, mfnormal_prb):
        rows = re.findall(r"^ \* - (.+)$", module.__doc__, re.M)
        documented = {n.strip() for row in rows for n in row.split(",")} - {"(nested bsdf)"}
        assert documented == {p.name for p in module.PARAMS}, module.__name__


# -- 3. mi.traverse updates ----------------------------------------------------------------------------

UPDATES = [("max_bounces", 1.5), ("max_bounces", math.nan), ("max_bounces", math.inf), ("max_bounces", 2.0 ** 40),
           ("rr_depth", 2.5), ("rr_depth", -1), ("mis_boost_max", -math.inf), ("strength", math.inf)]


def walk_bsdf():
    return mi.load_dict(plugin_dict("normalmap_microfacet", {}))


@pytest.mark.parametrize("key,value", UPDATES)
def test_an_update_to_a_wrong_number_is_refused_and_undone(key, value):
    """1.5 for an integer was truncated to 1 by the update; now it reaches the check (the integers
    are exposed as float64 arrays) and is refused like a value out of range."""
    bsdf = walk_bsdf()
    tree = mi.traverse(bsdf)
    before = np.array(tree[key]).tolist()
    tree[key] = value
    with pytest.raises(ValueError) as err:
        tree.update()
    line = f"ValueError: {err.value}"
    del err                                  # see tests/test_walk_params.py: no cycle holds the BSDF
    assert "\n" not in line and assert_names(line, "normalmap_microfacet", [key]) == key
    assert np.array(mi.traverse(bsdf)[key]).tolist() == before


def test_an_update_to_a_whole_number_is_taken():
    bsdf = walk_bsdf()
    tree = mi.traverse(bsdf)
    tree["max_bounces"], tree["rr_depth"], tree["mis_boost_max"] = 8, 2.0, 3
    tree.update()
    assert bsdf.model.ok == (8, 2, 3.0)


def test_an_update_to_a_string_is_refused_by_mitsuba_and_changes_nothing():
    """``mi.traverse`` converts an update to the exposed array's type as it is assigned: a string
    is refused there (Dr.Jit's TypeError, at the assignment) and the value stays."""
    bsdf = walk_bsdf()
    tree = mi.traverse(bsdf)
    for key in ("max_bounces", "strength"):
        with pytest.raises(TypeError):
            tree[key] = "abc"
    tree.update()
    assert bsdf.model.ok == (1024, 3, 64.0) and np.array(tree["strength"]).tolist() == [1.0]


# -- 4. The command line: one line ---------------------------------------------------------------------

CLI_SCENES = {
    "offset.xml": ('<integrator type="mfnormal_path"><string name="terminator_offset" value="false"/></integrator>',
                   ["mfnormal_path: terminator_offset must be a boolean", "got 'false' (a string)"]),
    "bounces.xml": ('<integrator type="path"><integer name="max_depth" value="3"/></integrator>',
                    ["normalmap_microfacet: max_bounces must be between 1", "got 1.5"]),
}


@pytest.mark.parametrize("name", sorted(CLI_SCENES))
def test_render_refuses_a_wrong_type_in_one_line(worker, tmp_path, name):
    integrator, needles = CLI_SCENES[name]
    write_maps(tmp_path)
    # Only the error under test: the other scene gives max_bounces as the integer it is (Mitsuba loads a
    # scene's objects in parallel, so a second error could come first).
    tag = "float" if name == "bounces.xml" else "integer"
    shape = ('<shape type="rectangle">' + xml_plugin(extra=f'<{tag} name="max_bounces" value="$mb"/>') + "</shape>")
    text = xml_scene(shape, {"model": "separable", "nm": "normalmap.png", "mb": "1.5" if name == "bounces.xml"
                             else "8"}).replace('<integrator type="path"><integer name="max_depth" value="3"/>'
                                                "</integrator>", integrator)
    (tmp_path / name).write_text(text)
    proc = worker.completed(["render", name, "-o", tmp_path / "out" / "render"], cwd=tmp_path, timeout=120)
    assert_one_line_error(proc, *needles)
    assert proc.returncode == 2 and not (tmp_path / "out").exists()


# -- 5. The fuzzer -----------------------------------------------------------------------------------------

def draw_values(data, plugin) -> tuple[dict, set]:
    """Some of ``plugin``'s parameters, each a valid or a wrong value: (values, the wrong ones' names)."""
    values, wrong = {}, set()
    specs = params(plugin)
    for name in data.draw(st.lists(st.sampled_from(sorted(specs)), min_size=1, max_size=4, unique=True)):
        choices = valid_values(specs[name])
        if not choices or data.draw(st.booleans()):
            values[name] = data.draw(st.sampled_from(wrong_values(specs[name])))
            wrong.add(name)
        else:
            values[name] = data.draw(st.sampled_from(choices))
    return values, wrong


def check_load(plugin, values, wrong, line):
    """One wrong value or more: refused, naming one of them. All valid: loaded, or refused for the
    one combination that is not (a ``same`` tangent facet on a model without one)."""
    if wrong:
        assert_names(line, plugin, wrong)
    else:
        assert line is None or "tangent_facet 'same' needs model=" in line, (values, line)


def fuzz_loads(data, map_file):
    plugin = data.draw(st.sampled_from(sorted(PLUGINS)))
    values, wrong = draw_values(data, plugin)
    if plugin == "normalmap_microfacet" and values.get("model") == "faithful" and not wrong:
        values["model"] = "analytic"               # the same checks, without building faithful's tables
    check_load(plugin, values, wrong, load_dict(plugin, values))
    check_load(plugin, values, wrong, load_xml(plugin, values, map_file))


@fuzz_test(input_count(CI_INPUTS, LONG_INPUTS))
def test_fuzz_typed_parameters_quick(data, map_file):
    fuzz_loads(data, map_file)


@pytest.mark.slow
@fuzz_test(LONG_INPUTS)
def test_fuzz_typed_parameters(data, map_file):
    fuzz_loads(data, map_file)


EXPOSED = ("max_bounces", "rr_depth", "mis_boost_max", "strength")


@pytest.mark.slow
@fuzz_test(LONG_INPUTS // 10)
def test_fuzz_traverse_updates(data):
    """Random updates of the exposed parameters, valid or wrong numbers: a wrong one is refused
    naming its parameter and every value stays; a valid one is taken."""
    bsdf = walk_bsdf()
    tree = mi.traverse(bsdf)
    specs = params("normalmap_microfacet")
    for _ in range(data.draw(st.integers(1, 4))):
        key = data.draw(st.sampled_from(EXPOSED))
        valid = valid_values(specs[key])
        value = data.draw(st.sampled_from(wrong_updates(specs[key]) + valid))
        before = {k: np.array(tree[k]).tolist() for k in EXPOSED}
        tree[key] = value
        if value in valid:
            tree.update()
            assert np.array(tree[key]).tolist() == [float(value)], (key, value)
            continue
        with pytest.raises(ValueError) as err:
            tree.update()
        line = f"ValueError: {err.value}"
        del err
        assert_names(line, "normalmap_microfacet", [key])
        assert {k: np.array(tree[k]).tolist() for k in EXPOSED} == before
