"""A module of another psfd checkout, loaded beside this one's for in-process comparisons (standard library only)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path


def module_of(checkout: Path, name: str):
    """``psfd/estimator/<name>.py`` of ``checkout``, loaded as ``<name>_reference`` beside this checkout's module.

    Only that file comes from the other checkout: what it imports is this one's.
    """
    path = Path(checkout) / "psfd" / "estimator" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"{name}_reference", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module
