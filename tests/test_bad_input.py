"""What an unkind operator types: absurd sizes and headers, huge plans, closed pipes, Ctrl-C, and the exit codes.

Every bad input must end in one line on stderr and the exit code of the README's table, before
anything large is allocated and before anything is written.
"""

from __future__ import annotations

import signal
import socket
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from psfd.catalogue import Catalogue
from psfd.cli import main
from psfd.daemon.plan import check_text
from psfd.vocabulary import BACKLOG_MAX, MAX_PIXELS, PLAN_STEPS_MAX, WORKERS_MAX

from test_runner import small_plan

DATA = Path(__file__).parent / "data"
TARGET = DATA / "img_example.pgm"


def cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


# -- absurd image headers --------------------------------------------------------------------------------


def huge_pgm(path: Path) -> Path:
    path.write_bytes(b"P5 99999999 99999999 65535\n" + bytes(1000))
    return path


def huge_png(path: Path) -> Path:
    """A valid PNG signature and IHDR chunk announcing 100000 x 100000 16-bit grey pixels, and a tiny body."""
    ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 16, 0, 0, 0, 0)
    chunk = lambda kind, data: (struct.pack(">I", len(data)) + kind + data  # noqa: E731
                                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))
    return path


def huge_tiff(path: Path) -> Path:
    """A little-endian TIFF whose one IFD announces 200000 x 200000 uint16 pixels in one strip."""
    entries = [(256, 4, 1, 200_000), (257, 4, 1, 200_000), (258, 3, 1, 16), (259, 3, 1, 1), (262, 3, 1, 1),
               (273, 4, 1, 8), (277, 3, 1, 1), (278, 4, 1, 200_000), (279, 4, 1, 64)]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHII", tag, kind, count, value) if kind == 4 else struct.pack("<HHIHH", tag, kind, count,
                                                                                      value, 0)
        for tag, kind, count, value in entries) + struct.pack("<I", 0)
    path.write_bytes(b"II*\0" + struct.pack("<I", 8 + 64) + bytes(64) + ifd)
    return path


@pytest.mark.parametrize("make", [huge_pgm, huge_png, huge_tiff], ids=["pgm", "png", "tiff"])
def test_absurd_image_headers_are_refused_before_decoding(tmp_path, capsys, make):
    image = make(tmp_path / f"huge{ {'huge_pgm': '.pgm', 'huge_png': '.png', 'huge_tiff': '.tif'}[make.__name__]}")
    for argv in (["estimate", "bernoulli", image], ["estimate", "bernoulli", TARGET, "--pattern", image],
                 ["estimate", "two-photo", image, TARGET], ["estimate", "sharp-edge", image],
                 ["target", "--noise", image, "--out", tmp_path / "t.png"]):
        code, out, err = cli(capsys, *argv)
        line = one_line(err)
        assert code == 2 and image.name in line and "pixels" in line, (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == [image.name]


def test_the_pixel_bound_admits_the_largest_sensors():
    """A 150-megapixel medium-format sensor (14204 x 10652) is a real camera; a gigapixel is not a frame."""
    assert 14204 * 10652 <= MAX_PIXELS < 1_000_000_000


# -- sizes on every entry point ----------------------------------------------------------------------------


@pytest.mark.parametrize("argv, words", [
    (["estimate", "bernoulli", TARGET, "-s", "1000"], "-s must be"),
    (["estimate", "bernoulli", TARGET, "--support", "100001"], "--support must be"),
    (["estimate", "bernoulli", TARGET, "--grid", "100000x1"], "--grid: N and M from 1 to 32"),
    (["estimate", "bernoulli", TARGET, "-s", "99999999999999999999999"], "-s must be"),
    (["capture", "--aperture", "5.6", "--simulate", "--workers", "100000"], "--workers"),
    (["capture", "--aperture", "5.6", "--simulate", "--backlog", "100000000"], "--backlog"),
    (["serve", "--workers", "100000"], "--workers"),
    (["demo", "--workers", "100000"], "--workers"),
])
def test_sizes_out_of_bounds_are_one_line_errors(tmp_path, capsys, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    code, out, err = cli(capsys, *argv, *(["--catalogue", tmp_path / "c.sqlite", "--socket", tmp_path / "none.sock"]
                                          if argv[0] in ("capture", "serve") else []))
    assert code == 2 and words in one_line(err)
    assert list(tmp_path.iterdir()) == []


def test_bounds_are_stated_in_the_vocabulary():
    assert 1 <= WORKERS_MAX <= 256 and 1 <= BACKLOG_MAX <= 10_000 and PLAN_STEPS_MAX >= 10_000


def huge_plan() -> str:
    """About 20 kB of plan that expands to 4 x 1000 x 1000 x 3 = 12 million steps."""
    values = "[" + ", ".join(f"{i * 0.01:.2f}" for i in range(1000)) + "]"
    return ('[rig]\nsimulate = true\n[target]\nkind = "bernoulli"\n[capture]\napertures = [4, 5.6, 8, 11]\n'
            f'x = [1300]\ny = {values}\nz = {values}\nchannels = ["g1"]\nrepeats = 3\n')


def test_a_plan_that_expands_to_millions_of_steps_is_refused_quickly(tmp_path, capsys):
    text = huge_plan()
    assert len(text) < 40_000
    problems = check_text(text)
    assert any(f"{12_000_000:,}" in p and "steps" in p for p in problems), problems
    plan = tmp_path / "huge.toml"
    plan.write_text(text)
    for argv in (["plan", "check", plan], ["run", plan, "--catalogue", tmp_path / "c.sqlite",
                                           "--socket", tmp_path / "none.sock"]):
        done = subprocess.run([sys.executable, "-m", "psfd", *map(str, argv)], capture_output=True, text=True,
                              timeout=60)  # a bound, not a benchmark: 12 million steps took a minute to expand
        assert done.returncode == 2 and "steps" in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["huge.toml"]


# -- clear messages ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("gain", [3, 10])
def test_an_over_exposed_target_is_reported_as_saturated(tmp_path, capsys, gain):
    """3x the exposure clips the whites on the target; 10x clips so much that the target cannot be found:
    either way the cause, saturation, is named (not a detection failure), and the file once."""
    image = cv2.imread(str(TARGET), cv2.IMREAD_UNCHANGED).astype(np.float64)
    over = tmp_path / "over.pgm"
    cv2.imwrite(str(over), np.clip(image * gain, 0, 255).astype(np.uint8))
    code, out, err = cli(capsys, "estimate", "bernoulli", over)
    line = one_line(err)
    assert code == 3 and "saturated" in line and "exposure" in line, line
    assert line.count("over.pgm") == 1


def test_a_file_where_a_folder_should_be_is_named(tmp_path, capsys):
    (tmp_path / "notes").write_text("mine")
    plan = tmp_path / "plan.toml"
    plan.write_text(small_plan())
    for argv in (["run", plan, "--catalogue", tmp_path / "notes" / "cat.sqlite"],
                 ["run", plan, "--catalogue", tmp_path / "notes" / "cat.sqlite", "--frames", tmp_path / "frames"],
                 ["run", plan, "--catalogue", tmp_path / "c.sqlite", "--frames", tmp_path / "notes"],
                 ["run", plan, "--catalogue", tmp_path / "c.sqlite", "--frames", tmp_path / "notes" / "frames"]):
        code, out, err = cli(capsys, *argv, "--socket", tmp_path / "none.sock")
        line = one_line(err)
        assert code == 2 and "File exists" not in line and "Not a directory" not in line, line
        assert f"{tmp_path / 'notes'} is a file, not a folder" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes", "plan.toml"]


# -- exit codes --------------------------------------------------------------------------------------------


def _small_catalogue(tmp_path: Path) -> Path:
    from psfd.drivers.base import CameraInfo
    from psfd.estimator.kernels import PSF

    path = tmp_path / "cat.sqlite"
    kernel = np.zeros((17, 17))
    kernel[8, 8] = 1.0
    with Catalogue(path) as cat:
        rig = cat.add_rig(CameraInfo("Canon EOS 400D", "0420", "EF 50mm f/1.8", 50.0))
        run = cat.start_run("plan.toml", "plan", rig, [("k", {})])
        psfs = [(PSF(kernel, 4, "bernoulli", "g1", ["x.dng"], (x / 10, 0.5), (0, 0, 8, 8)), {"aperture": 5.6})
                for x in range(10)]
        cat.commit_step(run, "k", [], psfs)
    return path


@pytest.mark.parametrize("command", ["query", "export", "report"])
def test_nothing_matched_is_exit_1_for_every_reader(tmp_path, capsys, command):
    db = _small_catalogue(tmp_path)
    extra = {"query": [], "export": ["--out", tmp_path / "out"], "report": ["--out", tmp_path / "r.png"]}[command]
    code, out, err = cli(capsys, command, "--catalogue", db, "--camera", "Nikon", *extra)
    assert code == 1 and "no PSF matches" in one_line(err) and out == ""
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("cat.sqlite")) == []


def test_a_closed_stdout_is_not_an_error(tmp_path):
    """`psfd query | head -1`: the reader went away; psfd stops quietly with 0, as head does."""
    db = _small_catalogue(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "psfd", "query", "--catalogue", str(db), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0 and err == ""
    shell = subprocess.run(f"'{sys.executable}' -m psfd query --catalogue '{db}' | head -1", shell=True,
                           capture_output=True, text=True, timeout=120, executable="/bin/bash")
    assert shell.stderr == "" and shell.stdout.startswith("id")


def _wait_for_running(db: Path, proc: subprocess.Popen, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if db.exists():
            try:
                with Catalogue(db, readonly=True) as cat:
                    runs = cat.runs()
                    if runs and any(s["state"] == "running" for s in cat.steps(runs[0]["id"])):
                        return
            except Exception:  # noqa: BLE001 - the catalogue is being created
                pass
        time.sleep(0.1)
    raise AssertionError("the run never started")


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["ctrl-c", "sigterm"])
def test_interrupting_a_run_exits_128_plus_the_signal_and_leaves_it_resumable(tmp_path, sig, code):
    plan = tmp_path / "plan.toml"
    plan.write_text(small_plan())
    db = tmp_path / "cat.sqlite"
    proc = subprocess.Popen([sys.executable, "-m", "psfd", "run", str(plan), "--catalogue", str(db), "--socket",
                             str(tmp_path / "none.sock"), "--workers", "1"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    _wait_for_running(db, proc)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == code, err
    assert "paused" in err and "--resume" in err and "Traceback" not in err
    with Catalogue(db, readonly=True) as cat:
        assert cat.runs()[0]["state"] == "paused"


def test_sigterm_of_another_command_exits_143_in_one_line(tmp_path):
    """SIGTERM while `psfd status` waits for a service that accepted but does not answer."""
    sock = tmp_path / "slow.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(sock))
    server.listen(1)
    server.settimeout(120)
    proc = subprocess.Popen([sys.executable, "-m", "psfd", "status", "--socket", str(sock)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    conn, _ = server.accept()
    conn.recv(100)  # the request arrived: psfd now waits for the answer
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and err == "psfd: terminated\n", err
    conn.close()
    server.close()


def test_the_readme_has_the_one_table_of_exit_codes():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    from psfd import errors

    for code, words in ((0, "done"), (1, "nothing matched"), (2, "bad input"), (3, "cannot support"),
                        (4, "camera or rail"), (5, "catalogue or service"), (130, "interrupted"), (143, "SIGTERM")):
        assert any(line.startswith(f"| {code} ") and words in line for line in readme.splitlines()), code
    assert {c.exit_code for c in vars(errors).values()
            if isinstance(c, type) and issubclass(c, errors.PsfdError)} == {1, 2, 3, 4, 5, 130}
