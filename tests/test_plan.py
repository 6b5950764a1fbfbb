"""Plans: parsing, every problem reported, deterministic step keys."""

from __future__ import annotations

import textwrap

import pytest

from psfd.cli import main
from psfd.daemon.plan import Step, check_text, load_plan, parse_plan, plan_changes, plan_content, plan_key
from psfd.drivers import open_rig
from psfd.drivers.sim import SimRig
from psfd.errors import BadInputError, CameraError

GOOD = """
[rig]
simulate = true
rail_limits = { x = [0, 3000], y = [-100, 100], z = [-100, 100] }

[target]
kind = "bernoulli"

[capture]
apertures = [5.6, 8]
x = [1200]
y = [-40, 40]
z = [10, -10]
channels = ["g1", "b"]
repeats = 2

[estimator]
s = 4
support = 17
solver = "nnls"
grid = [2, 1]
"""

PAIR = """
[rig]
simulate = true
scene = "texture"
[target]
kind = "pair"
near = 500
far = 1600
[capture]
apertures = [8]
"""

# One plan with a problem in every table.
BAD = """
[rig]
simulate = "yes"
rail_limits = { x = [0, 1000], w = [0, 1] }

[target]
kind = "bernouli"

[capture]
apertures = [5.6, -2]
x = [1200]
channels = ["g3"]
repeats = 0
exposure = 3

[estimator]
support = 16
solver = "magic"
grid = [0, 1]

[extra]
"""


def test_good_plan_expands_to_keyed_steps_in_serpentine_order():
    plan = parse_plan(GOOD, "good.toml")
    steps = plan.steps()
    assert len(steps) == 2 * 2 * 2 * 2  # apertures x y x z x repeats
    assert steps[0].key == "a5.6/x1200/y-40/z10/r0"
    assert [s.key for s in steps[:4]] == [
        "a5.6/x1200/y-40/z10/r0", "a5.6/x1200/y-40/z10/r1", "a8/x1200/y-40/z10/r0", "a8/x1200/y-40/z10/r1"]
    # second row of the field grid walks z backwards (shortest lateral move)
    assert [(s.y, s.z) for s in steps[::4]] == [(-40, 10), (-40, -10), (40, -10), (40, 10)]
    assert len({s.key for s in steps}) == len(steps)
    assert plan.channels == ["g1", "b"]
    assert plan.estimator_options() == {"s": 4, "support": 17, "solver": "nnls", "grid": (2, 1)}
    # the keys are a function of the plan only
    assert [s.key for s in parse_plan(GOOD).steps()] == [s.key for s in steps]


def test_step_payload_round_trip():
    for step in parse_plan(GOOD).steps() + parse_plan(PAIR).steps():
        assert Step.from_payload(step.payload()) == step


def test_pair_plan_keys_carry_both_distances():
    steps = parse_plan(PAIR).steps()
    assert [s.key for s in steps] == ["a8/x500-1600/r0"]
    assert steps[0].payload()["near"] == 500 and steps[0].payload()["far"] == 1600


def test_every_problem_is_reported():
    problems = check_text(BAD)
    text = "\n".join(problems)
    for needle in ("unknown table [extra]", "simulate must be true or false", "unknown axis 'w'",
                   "kind must be one of", "positive numbers, got -2", "unknown channel(s) 'g3'",
                   "repeats must be a positive integer", "unknown key 'exposure'", "support must be an odd",
                   "solver must be one of", "grid must be [nx, ny]", "x = 1200 outside rail_limits.x"):
        assert needle in text, needle
    assert len(problems) >= 12


@pytest.mark.parametrize("text, needle", [
    ("[target\nkind=1", "not valid TOML"),
    ("[rig]\nsimulate = true\n", "missing table [target]"),
    (PAIR.replace("far = 1600", "far = 500"), "must be closer than far"),
    (PAIR.replace("apertures = [8]", "apertures = [8]\nx = [1]"), "x does not apply to a pair"),
    (PAIR.replace("simulate = true", 'camera_port = "usb:"'), "needs rail_port"),
    (PAIR.replace('scene = "texture"', ""), 'simulated pair needs scene = "texture"'),
    (GOOD.replace("x = [1200]", ""), "needs x"),
    (GOOD.replace("y = [-40, 40]", "y = [1, 1]"), "[capture] y lists 1 twice"),
    # a boolean is no camera setting's value (TOML's true is not the "1" or "On" a camera offers)
    (GOOD.replace("simulate = true", "simulate = true\nsettings = { iso = true }"), "[rig] settings iso = true:"),
    # the simulated rig's default travel (200..3000 mm) applies when the plan gives no rail_limits
    ("[rig]\nsimulate = true\n[target]\nkind = 'bernoulli'\n[capture]\napertures = [8]\nx = [1200, 9999]\n",
     "x = 9999 outside the simulated rail's limits.x [200, 3000]"),
    # lambda = far / near must exceed s (SIAM 2012, Remark 2): 900 / 800 = 1.12 < 3
    (PAIR.replace("near = 500", "near = 800").replace("far = 1600", "far = 900"), "far / near = 1.12 must exceed s = 3"),
])
def test_single_problems(text, needle):
    assert any(needle in p for p in check_text(text)), check_text(text)


def test_load_plan_names_first_problem_and_counts_rest(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(BAD)
    with pytest.raises(BadInputError, match=r"more; run 'psfd plan check"):
        load_plan(path)
    with pytest.raises(BadInputError, match="cannot read plan"):
        load_plan(tmp_path / "missing.toml")


def test_plan_check_command_lists_all_problems(tmp_path, capsys):
    bad, good = tmp_path / "bad.toml", tmp_path / "good.toml"
    bad.write_text(BAD)
    good.write_text(GOOD)
    assert main(["plan", "check", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == len(check_text(BAD)) + 1  # one line per problem, then the error line
    assert all(line.startswith(f"{bad}: ") for line in err[:-1])
    assert err[-1].startswith("psfd: error:")
    assert main(["plan", "check", str(good)]) == 0
    assert "ok, 16 steps, 16 frames, 64 PSFs" in capsys.readouterr().out  # 2 channels x 2x1 grid


def test_docstring_example_frames_the_target_on_the_simulated_rig():
    """The module's example plan is valid and uses the simulated rig's own geometry, so every step
    sees the whole target (x at its working distance, y/z the 3x3 field walk of `SimRig.field_offsets`)."""
    import psfd.daemon.plan as plan_module
    from psfd.drivers.sim import SimRig

    example = textwrap.dedent(plan_module.__doc__.split("::\n\n", 1)[1].split("\n\nRail positions", 1)[0])
    assert check_text(example) == []
    plan = parse_plan(example)
    rig = SimRig()
    y, z = rig.field_offsets(3)
    assert plan.x == [rig.distance_for_scale()]
    assert plan.y == pytest.approx([float(v) for v in y], abs=0.01)
    assert plan.z == pytest.approx([float(v) for v in z], abs=0.01)
    assert len(plan.steps()) == 27


def test_plan_check_takes_no_runner_options(tmp_path, capsys):
    good = tmp_path / "good.toml"
    good.write_text(GOOD)
    with pytest.raises(SystemExit):
        main(["plan", "check", str(good), "--workers", "2"])
    assert "unrecognized arguments: --workers" in capsys.readouterr().err


def test_plan_content_ignores_the_wording_and_changes_name_the_keys():
    """What a plan says, not how: the one content for a reworded plan; a changed value is named by its key."""
    reworded = "# lens cap removed\n" + GOOD.replace("[5.6, 8]", "[5.60, 8.0]").replace("s = 4\n", "s=4  # x\n")
    assert plan_content(reworded) == plan_content(GOOD) and plan_changes(GOOD, reworded) == []
    changed = GOOD.replace("[5.6, 8]", "[5.6, 11]").replace("grid = [2, 1]\n", "")
    assert plan_content(changed) != plan_content(GOOD)
    assert plan_changes(GOOD, changed) == ["[capture] apertures [5.6, 8] -> [5.6, 11]",
                                           "[estimator] grid [2, 1] -> [1, 1]"]


BARE = """
[rig]
simulate = true

[target]
kind = "bernoulli"

[capture]
apertures = [5.6, 8]
x = [1300]
"""


def test_a_plan_is_what_it_does_not_which_defaults_it_writes_out():
    """Defaults written out, comments, key order, channels in another order or as "all": the one plan
    (`plan_key`); anything that changes a frame or an estimate is another, and `plan_changes` names it."""
    same = [
        BARE.replace("x = [1300]", 'channels = ["g1"]\nrepeats = 1\nx = [1300.0]  # mm'),
        "# lens cap on\n" + BARE + "\n[estimator]\ns = 4\nsupport = 17\nsolver = \"nnls\"\ngrid = [1, 1]\n",
        BARE.replace("simulate = true", 'simulate = true\nseed = 0\nrail = "simulated"\ncamera = { focus = "off" }'),
        BARE.replace("x = [1300]", "scale = [0.25]"),  # where the simulated rig puts a cell at 1/4 px: x = 1300
    ]
    for text in same:
        assert plan_key(text) == plan_key(BARE) and plan_changes(BARE, text) == [], text
    all_four = BARE + 'channels = "all"\n'
    assert plan_key(all_four) == plan_key(BARE + 'channels = ["b", "g2", "r", "g1"]\n')
    other = {
        BARE.replace("[5.6, 8]", "[5.6, 11]"): "[capture] apertures [5.6, 8] -> [5.6, 11]",
        BARE.replace("[5.6, 8]", "[8, 5.6]"): "[capture] apertures [5.6, 8] -> [8, 5.6]",
        BARE.replace("[1300]", "[1310]"): "[capture] x [1300] -> [1310]",
        BARE.replace("x = [1300]", "scale = [0.2]"): "[capture] x [1300] -> [",  # farther: a cell to 0.2 px
        BARE + "y = [0]\n": "[capture] y unset -> [0]",
        all_four: '[capture] channels ["g1"] -> ["r", "g1", "g2", "b"]',
        BARE + "repeats = 2\n": "[capture] repeats 1 -> 2",
        BARE + "[estimator]\ns = 3\nsupport = 17\n": "[estimator] s 4 -> 3",
        BARE + "[estimator]\nsupport = 21\n": "[estimator] support 17 -> 21",
        BARE + '[estimator]\nsolver = "ls"\n': '[estimator] solver "nnls" -> "ls"',
        BARE + "[estimator]\ngrid = [2, 1]\n": "[estimator] grid [1, 1] -> [2, 1]",
        BARE.replace("true", 'true\nsettings = { iso = "100" }'): '[rig] settings {} -> {"iso": "100"}',
        BARE.replace("true", "true\ncamera = { settle_s = 1.0 }"): "[rig] camera",
        BARE.replace("true", "true\nseed = 1"): "[rig] seed 0 -> 1",
        BARE.replace("true", "true\npitch_um = 6"): "[rig] pitch_um 8 -> 6",
    }
    for text, change in other.items():
        assert plan_key(text) != plan_key(BARE), text
        changes = plan_changes(BARE, text)
        assert len(changes) == 1 and changes[0].startswith(change), (changes, change)
    assert plan_key("not = [toml") == plan_content("not = [toml")  # no plan: only its text's content


SIM_STEP = """
[rig]
simulate = true
{option}
[target]
kind = "bernoulli"
[capture]
apertures = [5.6]
x = [1300]
"""


@pytest.mark.parametrize("option, needle", [
    ("seed = -1", "seed must be a non-negative integer, got -1"),
    ("s = 0", "s must be a positive integer up to 8, got 0"),
    ("support = 4", "support must be an odd integer from 3 to 65, got 4"),
    ('corner_aberration = "x"', "corner_aberration must be a number of waves, 0 or more, got 'x'"),
    ("exposure = 5", "exposure must be a fraction of the raw range, above 0 and at most 1, got 5"),
    ('sensor = "big"', "sensor must be [rows, columns], two positive even integers, got 'big'"),
    ("sensor = [481, 640]", "sensor must be [rows, columns], two positive even integers, got [481, 640]"),
    ("texture_mm = -3", "texture_mm must be a number from 10 to 100000 mm, got -3"),
    ("limits = { x = [3000, 200] }", "limits.x must be [low, high] with low <= high, got [3000, 200]"),
    # absurd but positive optics: the renderer took all memory (MemoryError at the first frame, pitch_um = 1e9)
    ("pitch_um = 1e9", "pitch_um must be a number from 0.5 to 50 um, got 1000000000.0"),
    ("focal_mm = 1e6", "focal_mm must be a number from 4 to 2000 mm, got 1000000.0"),
    ("cell_mm = 1e-9", "cell_mm must be a number from 0.01 to 100 mm, got 1e-09"),
    # within those, a view the simulated camera cannot render at the plan's rail X or aperture
    ("pitch_um = 50\nfocal_mm = 4", "at x = 1300 a target cell (cell_mm) images to 0.00309 channel pixels "
                                   "(pitch_um = 50, focal_mm = 4), too small to simulate (at least 0.05)"),
    ("focal_mm = 1500", "x = 1300 inside the focal length (focal_mm = 1500)"),
    ("pitch_um = 0.6\ns = 8", "pitch_um = 0.6 is finer than the simulated PSF renders at s = 8 and f/5.6 (0.64 um "
                              "at least)"),
])
def test_simulated_rig_options_are_checked_before_the_run(tmp_path, capsys, option, needle):
    """A simulated rig's own [rig] keys are refused by plan check and by run with exit 2 and one line, before
    a catalogue is made: before, plan check passed them and the run made its catalogue, then ended in a
    traceback (exit 1) at the first frame, leaving a paused run behind."""
    plan = tmp_path / "plan.toml"
    plan.write_text(SIM_STEP.format(option=option))
    assert main(["plan", "check", str(plan)]) == 2
    err = capsys.readouterr().err
    assert f"{plan}: [rig] {needle}" in err, err
    db = tmp_path / "run" / "cat.sqlite"
    code = main(["run", str(plan), "--local", "--catalogue", str(db), "--socket", str(tmp_path / "none.sock")])
    err = capsys.readouterr().err
    assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()



def test_a_target_imaged_smaller_than_it_is_found_from_is_refused_before_the_run():
    """scale = [0.15] (a cell at 0.15 channel pixel) passed plan check; the run then failed every step with "no
    calibration target found" (the target is found from 0.175 pixel per cell, psfd.estimator.detect). The rail X
    of a plan with known optics is held to the same bound."""
    text = SIM_STEP.format(option="")
    assert check_text(text.replace("x = [1300]", "scale = [0.15, 0.25]")) == [
        "[capture] scale = 0.15: a target cell images to 0.15 channel pixel, smaller than the 0.175 the target "
        "is found from (bring it closer: scale 0.175 or more)"]
    # the simulated rig's optics (50 mm, 8 um, 0.1 mm cells): 1300 mm is 0.25 pixel per cell, 2000 mm 0.16
    assert check_text(text.replace("x = [1300]", "x = [1300, 2000]")) == [
        "[capture] x = 2000: a target cell images to 0.16 channel pixel, smaller than the 0.175 the target is "
        "found from (bring it closer: scale 0.175 or more)"]
    assert check_text(text.replace("x = [1300]", "scale = [0.175]")) == []

def test_values_one_step_key_apart_are_listed_twice(tmp_path, capsys):
    """Steps are journalled by their key (`Step.key`, 6 significant digits): two positions that print alike
    are one step. plan check said ok, 2 steps, and only psfd run refused the plan (duplicate step keys)."""
    plan = tmp_path / "plan.toml"
    plan.write_text(SIM_STEP.format(option="").replace("x = [1300]", "x = [1300.001, 1300.004]"))
    assert main(["plan", "check", str(plan)]) == 2
    err = capsys.readouterr().err
    assert "[capture] x lists 1300.001 and 1300.004, one value (1300) to the 6 significant digits" in err
    assert check_text(GOOD.replace("[5.6, 8]", "[5.6, 5.6]")) == ["[capture] apertures lists 5.6 twice"]


def test_the_simulated_rig_prints_the_cell_the_plan_scales_for():
    """[target] cell_mm with ``scale`` on the simulated rig: the rail went where a 0.2 mm cell images to 1/4
    pixel and the rig rendered its own 0.1 mm cells there, at 1/8 pixel. The rig's cell follows [target]
    now (to the 0.01 mm the rail X is rounded to, 1e-6 pixel); given in both tables, they must agree."""
    text = SIM_STEP.format(option="").replace('"bernoulli"', '"bernoulli"\ncell_mm = 0.2').replace("x = [1300]",
                                                                                                  "scale = [0.25]")
    plan = parse_plan(text)
    camera, _ = open_rig(plan.rig_config())
    assert camera.rig.cell_mm == 0.2 and camera.rig.pixels_per_cell(plan.x[0]) == pytest.approx(0.25, abs=1e-5)
    assert check_text(text.replace("simulate = true", "simulate = true\ncell_mm = 0.2")) == []
    assert check_text(text.replace("simulate = true", "simulate = true\ncell_mm = 0.1")) == [
        "[target] cell_mm = 0.2 and [rig] cell_mm = 0.1 disagree: the simulated rig prints its target with "
        "[target]'s cell when [rig] gives none (give it once)"]


def test_a_view_too_small_to_render_is_refused_by_the_simulated_camera(tmp_path):
    """A capture by hand where a target cell images to 1/50 pixel (pitch 50 um, 4 mm lens, rail at 200 mm) is
    refused in one line, nothing written: the bound keeps the renderer's padded raster small."""
    rig = SimRig(pitch_um=50, focal_mm=4)
    assert rig.pixels_per_cell() == pytest.approx(4 / 196 * 0.1 / 0.1)
    with pytest.raises(CameraError, match=r"cannot render this view: at x = 200 a target cell \(cell_mm\) images to "
                                          r"0.0204 channel pixels .* \(at least 0.05\)"):
        rig.camera.capture(tmp_path / "out")
    assert not list((tmp_path / "out").iterdir())


REAL = """
[rig]
rail_port = "/dev/ttyUSB0"
camera_port = "usb:001,004"

[target]
kind = "bernoulli"

[capture]
apertures = [5.6, 8]
x = [-1300]
"""


def test_a_camera_setting_is_the_text_its_widget_takes():
    """gphoto2 widgets take text ("100", "1/125", "-0.3"): a setting written as a number is that number's text,
    so iso = 100, 100.0 and "100" are one plan (before, the number 100 and the text "100" were two plans, and
    a run paused under one could not be resumed under the other); another value is another plan."""
    settings = 'settings = { iso = "100", shutterspeed = "1/125", exposurecompensation = "-0.3" }'
    text = BARE.replace("true", f"true\n{settings}")
    for same in (text.replace('"100"', "100"), text.replace('"100"', "100.0"), text.replace('"-0.3"', "-0.3")):
        assert plan_key(same) == plan_key(text) and plan_changes(text, same) == [], same
        assert plan_changes(same, text) == []
    for other in (text.replace('"100"', "200"), text.replace('"1/125"', '"1/250"'), text.replace('"100"', '"Auto"')):
        assert plan_key(other) != plan_key(text)
        assert len(plan_changes(text, other)) == 1 and plan_changes(text, other)[0].startswith("[rig] settings")


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "true", "[100]", "{ value = 100 }", "1979-05-27"])
def test_a_setting_no_camera_widget_takes_is_refused_by_plan_check_in_one_line(tmp_path, capsys, value):
    """A camera widget is set to text: a finite number becomes its text, a string is sent as written. nan and
    inf (TOML numbers with no camera choice of theirs), a boolean, a list, a table or a date are none: plan
    check said ok to nan and inf, and the run paused at the camera's refusal."""
    plan = tmp_path / "plan.toml"
    plan.write_text(BARE.replace("true", f"true\nsettings = {{ shutterspeed = \"1/125\", iso = {value} }}"))
    assert main(["plan", "check", str(plan)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and err[0].startswith(f"{plan}: [rig] settings iso = {value}: "), err
    assert "shutterspeed" not in err[0]


def test_an_aperture_among_the_settings_is_refused_by_plan_check():
    """Each step sets the aperture from [capture] apertures: one in [rig] settings as well was checked against
    every frame's EXIF, so plan check said ok and the run paused at the first step of another aperture."""
    for value in ("5.6", '"5.6"', '"f/5.6"'):
        problems = check_text(BARE.replace("true", f"true\nsettings = {{ aperture = {value} }}"))
        assert len(problems) == 1 and problems[0].startswith("[rig] settings aperture: "), problems
        assert "[capture] apertures" in problems[0]


def test_how_the_rig_is_reached_is_not_what_a_plan_does():
    """A camera or rail controller plugged back in on another port (usb:001,004 -> 005, ttyUSB0 -> 1), and
    the timeouts, speed and baud rate of the link, shoot the same frames: the run they paused resumes
    under the edited plan (the runner checks that the camera is the one the run began with)."""
    edits = [
        REAL.replace("usb:001,004", "usb:001,005"),
        REAL.replace("ttyUSB0", "ttyUSB1"),
        REAL.replace('camera_port = "usb:001,004"\n', ""),
        REAL.replace("[target]", "timeout = 30\nrail_timeout = 5\nrail_feed = 600\nrail_baudrate = 250000\n\n[target]"),
    ]
    for text in edits:
        assert plan_key(text) == plan_key(REAL) and plan_changes(REAL, text) == [], text
    limits = REAL.replace("[target]", "rail_limits = { x = [-1500, 0] }\n\n[target]")
    assert plan_changes(REAL, limits) == ['[rig] rail_limits unset -> {"x": [-1500, 0]}']
