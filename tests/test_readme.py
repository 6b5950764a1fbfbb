"""The README works as written: every command block is run, in order, in a new folder.

A block is a fenced ``sh`` block. The HTML comment on the line before it may mark it:

- ``<!-- hardware-only: why -->``: needs a camera, a rail, the user's own photographs or root; not run,
  but every ``psfd`` command in it must parse as written and every repository file it names must exist;
- ``<!-- slow -->``: the set-up blocks (a new virtual environment, packages from the index, the whole
  demo or test suite), run by ``pytest -m slow`` in a copy of the repository.

Every other block runs in the default suite, in one temporary folder holding ``tests/data`` (the
photographs the README uses), with the simulated rig, a private ``$XDG_DATA_HOME`` and no service.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MARKERS = ("hardware-only", "slow")
MARKER = re.compile(r"^<!--\s*([a-z-]+)\b[^>]*-->\s*$")


@dataclass
class Block:
    line: int  # where the fence opens, 1-based
    code: str
    marker: str | None

    def __str__(self) -> str:
        return f"README.md line {self.line}:\n{self.code}"


def blocks(text: str) -> list[Block]:
    """The fenced ``sh`` blocks of a Markdown text with the marker on the line before each."""
    lines = text.splitlines()
    found, i = [], 0
    while i < len(lines):
        if lines[i].strip() == "```sh":
            start = i
            i += 1
            while lines[i].strip() != "```":
                i += 1
            above = next((lines[j].strip() for j in range(start - 1, -1, -1) if lines[j].strip()), "")
            match = MARKER.match(above)
            found.append(Block(start + 1, "\n".join(lines[start + 1 : i]), match[1] if match else None))
        i += 1
    return found


README_BLOCKS = blocks(README.read_text(encoding="utf-8"))


def commands(block: Block) -> list[list[str]]:
    """The words of each command line of a block (comments dropped, `&&` chains split)."""
    out = []
    for line in block.code.splitlines():
        words = shlex.split(line, comments=True)
        chunk: list[str] = []
        for word in words + ["&&"]:
            if word in ("&&", "||", ";", "|", ">"):
                if chunk:
                    out.append(chunk)
                chunk = []
            else:
                chunk.append(word)
    return out


def environment(tmp_path: Path) -> dict[str, str]:
    """This interpreter's environment first on PATH (its `psfd` script), private data, no service."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PSFD_", "XDG_DATA_HOME", "JOURNAL_STREAM"))}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["XDG_DATA_HOME"] = str(tmp_path / "data-home")
    env["PSFD_SOCKET"] = str(tmp_path / "no-service.sock")
    return env


def run_block(block: Block, cwd: Path, env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-e", "-o", "pipefail", "-c", block.code], cwd=cwd, env=env, text=True,
                          capture_output=True, timeout=timeout)


def test_every_block_is_run_or_marked():
    assert README_BLOCKS, "no command blocks found in README.md"
    unknown = [str(b) for b in README_BLOCKS if b.marker is not None and b.marker not in MARKERS]
    assert unknown == []
    assert any(b.marker is None for b in README_BLOCKS)
    # the README's own fences are all sh blocks: a block in another language would escape the test
    fences = re.findall(r"^```(\S*)\s*$", README.read_text(encoding="utf-8"), re.M)
    assert set(fences) <= {"sh", ""}


def test_the_readme_runs_as_written(tmp_path):
    """Every unmarked block, in order, in one folder: each exits 0, and what the README says it shows, it shows."""
    work = tmp_path / "work"
    (work / "tests").mkdir(parents=True)
    (work / "tests" / "data").symlink_to(ROOT / "tests" / "data")
    env = environment(tmp_path)
    outputs = []
    for block in (b for b in README_BLOCKS if b.marker is None):
        done = run_block(block, work, env, timeout=900)
        assert done.returncode == 0, f"{block}\nexit {done.returncode}\nstdout:\n{done.stdout}\nstderr:\n{done.stderr}"
        outputs.append(done.stdout)
    shown = "\n".join(outputs)
    # what the README's comments promise
    assert (work / "target.pdf").exists() and (work / "target.seed7.noise.pgm").exists()
    assert re.search(r"^aperture\s+8\s", shown, re.M)  # the simulated camera remembered `camera set`
    assert "X=1300 Y=-40 Z=0" in shown  # and the rail its position
    assert (work / "example" / "metrics.csv").exists() and len(list((work / "compare").glob("compare.png"))) == 1
    assert "units:" in shown and "lp/mm" in shown  # query prints its units, MTF50 in lp/mm (the DNG's pitch)
    status = json.loads(next(line for line in shown.splitlines() if line.startswith('{"service"')))
    assert set(status) == {"service", "catalogue", "runs"} and status["service"] is None
    assert status["runs"][0]["state"] == "done"
    for name in ("report.png", "report.pdf", "metadata.json", "metrics.csv", "psfs.jsonl", "pair.jsonl"):
        assert (work / name).stat().st_size > 0, name
    assert (work / "report.pdf").read_bytes().startswith(b"%PDF")
    assert "databases" in json.loads((work / "metadata.json").read_text())
    assert (work / "metrics.csv").read_text().splitlines()[0].startswith("id,file,camera")


def test_hardware_blocks_name_commands_that_exist():
    """A block the suite cannot run still shows only psfd commands that parse, and files that exist."""
    from psfd.cli import build_parser

    parser = build_parser()
    checked = 0
    for block in (b for b in README_BLOCKS if b.marker == "hardware-only"):
        for words in commands(block):
            if words[0] == "sudo":
                words = words[1:]
            if Path(words[0]).name == "psfd":
                parser.parse_args(words[1:])  # argparse exits (SystemExit) on a command that does not exist
                checked += 1
            for word in words:
                if word.startswith("systemd/"):
                    assert (ROOT / word).exists(), f"{block}\nnames {word}, which is not in the repository"
    assert checked >= 5


def test_every_run_block_uses_existing_options():
    """The same parse check for the blocks that run, so a renamed option fails here first, with the line."""
    from psfd.cli import build_parser

    parser = build_parser()
    for block in (b for b in README_BLOCKS if b.marker is None):
        for words in commands(block):
            if words[0] == "psfd":
                parser.parse_args(words[1:])


def test_ci_runs_what_the_readme_says():
    """The README's test command is what .ci/run runs (so CI checks the set-up the README gives)."""
    ci = (ROOT / ".ci" / "run").read_text()
    assert "pip install" in ci and "-e '.[test]'" in ci and "python -m pytest -q" in ci
    setup = [b for b in README_BLOCKS if b.marker == "slow"]
    assert any("-e '.[test]'" in b.code and "python -m pytest -q" in b.code for b in setup)
    assert all(b.code.startswith("python3 -m venv .venv && . .venv/bin/activate && ") for b in setup)


@pytest.mark.slow
@pytest.mark.timeout(2 * 3600 + 300)  # each set-up block has its own hour (run_block below)
def test_the_set_up_blocks_work_in_a_fresh_copy(tmp_path):
    """The slow blocks (new virtual environment, install from the package index, demo, tests) in a copy of the
    repository, outside any virtual environment."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    copy = tmp_path / "psfd"
    for name in filter(None, files.decode().split("\0")):
        if (ROOT / name).is_file():
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, copy / name)
    env = environment(tmp_path)
    here = str(Path(sys.executable).parent)
    env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if p != here)
    env.pop("VIRTUAL_ENV", None)
    for block in (b for b in README_BLOCKS if b.marker == "slow"):
        done = run_block(block, copy, env, timeout=3600)
        assert done.returncode == 0, f"{block}\nexit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    assert (copy / "psfd-demo" / "report.png").stat().st_size > 0
