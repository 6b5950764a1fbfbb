"""Start-up of the `psfd` process: each command loads only what it runs.

Every command a user times pays its imports; scipy.stats and scipy.signal
alone cost more than the estimate of a target photo.
"""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys

import numpy as np
import pytest
import scipy.stats

from psfd.cli import COMMANDS, COMMAND_MODULES, build_parser, command_modules


def _words(module: str) -> set[str]:
    parser = argparse.ArgumentParser()
    importlib.import_module(f"psfd.cli.{module}").register(parser.add_subparsers())
    return set(parser._subparsers._group_actions[0].choices)


def test_every_command_word_names_the_module_that_registers_it():
    registered = {word: module for module in COMMAND_MODULES for word in _words(module)}
    assert registered == COMMANDS


@pytest.mark.parametrize("argv, modules", [
    (["--version"], ()),
    (["--help"], COMMAND_MODULES),
    (["--version", "--help"], COMMAND_MODULES),
    (["estimate", "target", "x.pgm"], ("estimate",)),
    (["rail", "unlock", "--simulate"], ("hardware",)),
    (["no-such-command"], COMMAND_MODULES),  # argparse then lists the commands there are
])
def test_the_command_word_chooses_the_modules(argv, modules):
    assert command_modules(argv) == modules


def test_a_command_parses_as_with_the_whole_parser():
    argv = ["estimate", "pair", "near.pgm", "far.pgm", "-s", "3"]
    assert vars(build_parser(argv).parse_args(argv)) == vars(build_parser().parse_args(argv))


def test_the_estimators_load_neither_scipy_stats_nor_scipy_signal():
    code = ("import sys; import psfd.cli.estimate, psfd.cli.compare, psfd.estimator.bernoulli, "
            "psfd.estimator.twoscale, psfd.estimator.sharpedge, psfd.estimator.pair_register, "
            "psfd.estimator.geometry; print(sorted(m for m in ('scipy.stats', 'scipy.signal') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("q", [0.001, 0.01, 0.05])
@pytest.mark.parametrize("dof", [1, 13, 37, 1000])
def test_the_f_quantile_is_scipy_stats_one(q, dof):
    from scipy import special

    assert special.fdtri(3, dof, 1.0 - q) == pytest.approx(scipy.stats.f.isf(q, 3, dof), rel=1e-10)
