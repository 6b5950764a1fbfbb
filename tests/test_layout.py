"""The package's layout as its docstring describes it: the module map, the direction of imports, a light parser."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import psfd

PACKAGE = Path(psfd.__file__).parent
# Bottom-up order of the package docstring: a module imports only modules of its own level or below.
LEVELS = {"errors": 0, "vocabulary": 1, "workers": 1, "exif": 1, "estimator": 2, "drivers": 3, "printing": 3, "figures": 4, "catalogue": 4,
          "daemon": 5, "cli": 6, "__main__": 7}


def modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


def part(path: Path) -> str:
    """``estimator`` for psfd/estimator/raw.py, ``catalogue`` for psfd/catalogue.py."""
    rel = path.relative_to(PACKAGE)
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def psfd_imports(path: Path) -> set[str]:
    """The psfd parts a module imports anywhere (module level or inside functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "psfd":
            names = node.module.split(".")[1:] or [alias.name for alias in node.names]
            found.update(n.split(".")[0] for n in (names[:1] if node.module != "psfd" else names))
        elif isinstance(node, ast.Import):
            found.update(a.name.split(".")[1] for a in node.names if a.name.startswith("psfd."))
    return found - {"__version__"}


def test_the_package_docstring_names_every_module():
    doc = psfd.__doc__
    missing = [str(p.relative_to(PACKAGE)) for p in modules()
               if p.name not in ("__init__.py", "__main__.py") and f"``{p.stem}``" not in doc]
    assert missing == []
    for folder in ("estimator", "drivers", "daemon", "cli"):
        assert f"``{folder}/``" in doc


def test_imports_run_down_the_layers():
    upward = [f"{p.relative_to(PACKAGE)} imports psfd.{target}"
              for p in modules() for target in psfd_imports(p)
              if target in LEVELS and LEVELS[target] > LEVELS[part(p)]]
    assert upward == []


def test_building_the_parser_loads_no_numerics():
    """`psfd --help` and `psfd --version` need the parser only: no numpy, OpenCV, scipy, catalogue or drivers."""
    code = ("import sys; from psfd.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('numpy', 'cv2', 'scipy', 'sqlite_utils', 'psfd.catalogue', 'psfd.drivers', "
            "'psfd.estimator', 'psfd.figures') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
