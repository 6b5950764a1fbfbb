"""One name per method, one check per size, one set of rig options: the same everywhere they are used."""

from __future__ import annotations

import pytest

from psfd import vocabulary
from psfd.catalogue import Catalogue
from psfd.cli import build_parser, main, options
from psfd.daemon.plan import check_text, parse_plan, plan_text
from psfd.errors import BadInputError


def test_method_names_and_their_older_aliases():
    assert [vocabulary.method_name(m) for m in ("bernoulli", "target", "two-photo", "pair", "sharp-edge", "edges")] \
        == ["bernoulli", "bernoulli", "two-photo", "two-photo", "sharp-edge", "sharp-edge"]
    with pytest.raises(BadInputError, match="unknown method 'twoscale'"):
        vocabulary.method_name("twoscale")
    assert set(vocabulary.DEFAULT_S) == set(vocabulary.METHODS)
    assert vocabulary.DEFAULT_SOLVER in vocabulary.SOLVERS


@pytest.mark.parametrize("sizes, message", [
    ((0,), "s must be a positive integer up to 8, got 0"),
    ((1000,), "s must be a positive integer up to 8, got 1000"),
    ((4.0,), "s must be a positive integer"),
    ((4, 16), "support must be an odd integer from 3 to 65, got 16"),
    ((4, 100001), "support must be an odd integer from 3 to 65, got 100001"),
    ((4, None, (100000, 1)), "grid must be [nx, ny] with integers from 1 to 32, got (100000, 1)"),
    ((4, None, (0, 2)), "grid must be [nx, ny]"),
])
def test_one_check_of_the_sizes(sizes, message):
    with pytest.raises(BadInputError) as err:
        vocabulary.check_sizes(*sizes)
    assert message in str(err.value)


def test_sizes_at_their_bounds_pass():
    assert vocabulary.check_sizes(8, 65, [32, 32]) == (8, 65, (32, 32))
    assert vocabulary.check_sizes(3) == (3, 13, (1, 1))  # default support 4s + 1


@pytest.mark.parametrize("argv, message", [
    (["estimate", "bernoulli", "x.dng", "-s", "1000"], "-s must be a positive integer up to 8"),
    (["estimate", "two-photo", "a.dng", "b.dng", "--support", "100001"], "--support must be an odd integer"),
    (["estimate", "sharp-edge", "x.dng", "--grid", "100000x1"], "--grid: N and M from 1 to 32, got 100000x1"),
    (["compare", "x.dng", "-s", "9"], "-s must be a positive integer up to 8"),
])
def test_huge_sizes_are_refused_on_the_command_line_before_any_file_is_read(argv, message, capsys):
    # the frames do not exist: the size is refused first, in one line, with the same words as everywhere
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_plans_use_the_same_checks_and_messages():
    base = "[rig]\nsimulate = true\n[target]\nkind = 'bernoulli'\n[capture]\napertures = [8]\nx = [1300]\n"
    problems = check_text(base + "[estimator]\ns = 9\nsupport = 67\ngrid = [33, 1]\nsolver = 'cg'\n")
    assert problems == ["[estimator] s must be a positive integer up to 8, got 9",
                        "[estimator] support must be an odd integer from 3 to 65, got 67",
                        "[estimator] grid must be [nx, ny] with integers from 1 to 32, got [33, 1]",
                        "[estimator] solver must be one of ls, ls-threshold, nnls, got 'cg'"]


def test_an_old_pair_plan_is_a_two_photo_plan_with_its_text_unchanged():
    """Plan texts are hashed in catalogues: a plan saying kind = "pair" must still parse, and resume."""
    text = ("[rig]\nsimulate = true\nscene = \"texture\"\n[target]\nkind = \"pair\"\nnear = 500\nfar = 1600\n"
            "[capture]\napertures = [8]\n")
    plan = parse_plan(text)
    assert plan.kind == "two-photo" and plan.text == text
    assert [s.x for s in plan.steps()] == [(500.0, 1600.0)]


def test_plan_text_round_trips():
    tables = {"rig": {"simulate": True, "scene": "texture", "rail_limits": {"x": [0.0, 3000.0]}},
              "target": {"kind": "two-photo", "near": 587.5, "far": 2200.0},
              "capture": {"apertures": [5.6], "channels": ["g1", "b"]}}
    text = plan_text(tables)
    assert check_text(text) == []
    plan = parse_plan(text)
    assert plan.rig == tables["rig"] and (plan.near, plan.far, plan.channels) == (587.5, 2200.0, ["g1", "b"])


def test_parse_fnumber_is_one_parser():
    assert [vocabulary.parse_fnumber(v) for v in ("5.6", "f/5.6", "F5.6", 8, None)] == [5.6, 5.6, 5.6, 8.0, None]
    with pytest.raises(BadInputError, match="--aperture: expected an f-number such as 5.6"):
        options.parse_fnumber("wide")
    with pytest.raises(BadInputError, match="--aperture: expected a positive f-number"):
        options.parse_fnumber("f/0")
    assert vocabulary.camera_fnumber("implicit auto") is None


RIG = ["--simulate", "--camera-port", "usb:001,004", "--rail-port", "/dev/ttyUSB0", "--rail-limits", "X=0:2000,Y=-5:5"]
RIG_COMMANDS = [
    ["camera", "info"], ["camera", "set", "aperture", "8"], ["rail", "home"], ["rail", "move", "X=10"],
    ["rail", "position"], ["record", "--out", "rec", "--at", "X=1300"], ["capture", "--aperture", "5.6"],
]


@pytest.mark.parametrize("command", RIG_COMMANDS, ids=lambda c: " ".join(c[:2]))
def test_every_rig_command_takes_the_same_rig_options(command):
    args = build_parser().parse_args(command + RIG)
    assert options.rig_config(args) == {"simulate": True, "rail_limits": {"x": [0.0, 2000.0], "y": [-5.0, 5.0]}}
    args = build_parser().parse_args(command + RIG[1:])  # real hardware: the ports count
    assert options.rig_config(args) == {"camera_port": "usb:001,004", "rail_port": "/dev/ttyUSB0",
                                        "rail_limits": {"x": [0.0, 2000.0], "y": [-5.0, 5.0]}}


def test_capture_with_rail_limits_on_the_simulated_rig(tmp_path, capsys):
    db = tmp_path / "cat.sqlite"
    common = ["--catalogue", str(db), "--socket", str(tmp_path / "none.sock"), "--workers", "1", "--channels", "g1"]
    assert main(["capture", "--aperture", "5.6", "--rail", "X=1200", "--rail-limits", "X=0:2000", "--simulate",
                 *common]) == 0
    assert "done: 1 step" in capsys.readouterr().out
    with Catalogue(db) as cat:
        (row,) = cat.query().rows
        plan = cat.run(row["run_id"])["plan_text"]
    assert row["aperture"] == 5.6 and row["step"] == "a5.6/x1200/r0"
    assert "rail_limits = { x = [0.0, 2000.0] }" in plan
    # the limits given are the ones checked, before the rig moves
    assert main(["capture", "--aperture", "5.6", "--rail", "X=2500", "--rail-limits", "X=0:2000", "--simulate",
                 *common]) == 2
    assert capsys.readouterr().err.strip() == "psfd: error: --rail: x = 2500 outside rail_limits.x [0, 2000]"
