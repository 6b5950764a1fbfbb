"""Start-up of the `psfd` process: each command loads only what it runs.

Every command a user times pays its imports; scipy.stats and scipy.signal
alone cost more than the estimate of a target photo.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from psfd.cli import COMMANDS, COMMAND_MODULES, build_parser, command_modules

DATA = Path(__file__).parent / "data"


def _words(module: str) -> set[str]:
    parser = argparse.ArgumentParser()
    importlib.import_module(f"psfd.cli.{module}").register(parser.add_subparsers())
    return set(parser._subparsers._group_actions[0].choices)


def _listing(parser: argparse.ArgumentParser) -> dict[str, str]:
    return {choice.dest: choice.help for choice in parser._subparsers._group_actions[0]._choices_actions}


def test_every_command_word_names_the_module_that_registers_it_and_its_help_line():
    registered = {word: module for module in COMMAND_MODULES for word in _words(module)}
    assert registered == {word: module for word, (module, _) in COMMANDS.items()}
    assert _listing(build_parser()) == {word: line for word, (_, line) in COMMANDS.items()}


@pytest.mark.parametrize("argv, modules", [
    (["--version"], ()),
    (["--help"], ()),  # the commands listed from COMMANDS, not built
    (["--version", "--help"], ()),
    (["estimate", "target", "x.pgm"], ("estimate",)),
    (["rail", "unlock", "--simulate"], ("hardware",)),
    (["no-such-command"], ()),  # argparse then lists the commands there are
])
def test_the_command_word_chooses_the_modules(argv, modules):
    assert command_modules(argv) == modules


@pytest.mark.parametrize("argv", [["--help"], ["no-such-command"], []])
def test_the_listed_commands_print_as_the_whole_parser(argv, capsys):
    """The top-level help and argparse's messages (a word psfd does not know, no command) are those of the
    parser with every command built, without importing a command module (50 ms of start-up)."""
    printed = []
    for parser in (build_parser(argv), build_parser()):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)
        printed.append(capsys.readouterr())
    assert printed[0] == printed[1] and printed[0].out + printed[0].err
    code = f"import sys; from psfd.cli import build_parser; build_parser({argv!r}); print(sorted(sys.modules))"
    modules = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert [m for m in COMMAND_MODULES if f"'psfd.cli.{m}'" in modules] == []


def test_a_command_parses_as_with_the_whole_parser():
    argv = ["estimate", "pair", "near.pgm", "far.pgm", "-s", "3"]
    assert vars(build_parser(argv).parse_args(argv)) == vars(build_parser().parse_args(argv))


def test_the_estimators_load_neither_scipy_stats_nor_scipy_signal():
    code = ("import sys; import psfd.cli.estimate, psfd.cli.compare, psfd.estimator.bernoulli, "
            "psfd.estimator.twoscale, psfd.estimator.sharpedge, psfd.estimator.pair_register, "
            "psfd.estimator.geometry; print(sorted(m for m in ('scipy.stats', 'scipy.signal') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def _imported(argv: list[str]) -> set[str]:
    """Every module a whole `psfd ...` process has loaded when it ends, on every thread.

    Read from sys.modules at exit rather than from -X importtime, whose report
    leaves out a module imported on a second thread (cli.estimate imports the
    estimator beside the decoding).
    """
    code = ("import atexit, runpy, sys\n"
            "atexit.register(lambda: sys.__stderr__.write('modules: ' + ' '.join(sorted(sys.modules)) + '\\n'))\n"
            f"sys.argv = ['psfd', *{argv!r}]\n"
            "runpy.run_module('psfd', run_name='__main__')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    line = next(line for line in done.stderr.splitlines() if line.startswith("modules: "))
    return set(line.split()[1:])


@pytest.fixture(scope="module")
def small_dng(tmp_path_factory) -> Path:
    from psfd.estimator import simulate

    dng = tmp_path_factory.mktemp("startup") / "target.dng"
    simulate.simulate_target(dng, psf=simulate.diffraction_psf(5.6, s=4, support=17), pixels_per_cell=0.37,
                             rotation_deg=3.0, sensor=(500, 600), centre=(0.5, 0.5), seed=1)
    return dng


@pytest.mark.parametrize("frame", ["pgm", "dng"])
def test_estimating_a_target_imports_no_scipy_and_no_numpy_ma(frame, small_dng):
    """`psfd estimate target`: scipy (0.5-1 s of start-up) and numpy.ma (35-55 ms) are never loaded,
    on a single-channel image and on the four planes of a RAW file; multiprocessing only to fork workers."""
    modules = _imported(["estimate", "target", str(DATA / "img_example.pgm" if frame == "pgm" else small_dng)])
    assert "psfd.estimator.bernoulli" in modules
    assert sorted(m for m in modules if m.split(".")[0] == "scipy" or m.split(".")[:2] == ["numpy", "ma"]) == []
    if frame == "pgm":  # one window, solved in this process: no pool (multiprocessing: 13 ms of imports)
        assert "multiprocessing" not in modules


def test_writing_the_results_imports_no_scipy(tmp_path):
    """With --out the figures load matplotlib (and numpy.ma with it), still no scipy."""
    modules = _imported(["estimate", "target", str(DATA / "img_example.pgm"), "--out", str(tmp_path / "out")])
    assert "matplotlib" in modules
    assert sorted(m for m in modules if m.split(".")[0] == "scipy") == []


def test_the_estimate_runs_every_openblas_on_one_thread_without_threadpoolctl():
    """bernoulli._one_blas_thread sets the loaded OpenBLAS libraries (numpy's, OpenCV's) to one thread and back,
    as threadpoolctl would, which is not imported for it (20-45 ms a process)."""
    code = ("import sys, cv2, numpy; from psfd.estimator import bernoulli\n"
            "with bernoulli._one_blas_thread():\n"
            "    print('threadpoolctl' in sys.modules)\n"
            "    from threadpoolctl import threadpool_info\n"
            "    inside = sorted((d['filepath'], d['num_threads']) for d in threadpool_info() if d['internal_api'] == 'openblas')\n"
            "outside = sorted((d['filepath'], d['num_threads']) for d in threadpool_info() if d['internal_api'] == 'openblas')\n"
            "print(inside); print(outside)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "2"})
    imported, inside, outside = done.stdout.strip().splitlines()
    inside, outside = ast.literal_eval(inside), ast.literal_eval(outside)
    assert imported == "False"
    assert inside and [n for _, n in inside] == [1] * len(inside)
    assert [p for p, _ in outside] == [p for p, _ in inside] and all(n == 2 for _, n in outside)
