"""A run's life cycle under failure: lost closes, refusals that write nothing, a full or read-only disk, kills.

Each test reproduces a way a lab loses or duplicates work, or is left stuck: a run killed after its
last commit, a refused command that still creates files, a disk that fills up or turns read-only
mid-run, and SIGKILL in every phase of a run.
"""

from __future__ import annotations

import errno
import hashlib
import os
import random
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from psfd.catalogue import SCHEMA_VERSION, Catalogue
from psfd.cli import main
from psfd.daemon.plan import parse_plan
from psfd.daemon.runner import Control, Runner
from psfd.daemon.store import frames_dir_for
from psfd.drivers import open_rig
from psfd.errors import EstimationError, StorageError

from test_runner import check_complete, small_plan, stored_files

HERE = Path(__file__).resolve().parent
ONE_STEP = small_plan().replace("apertures = [4, 11]", "apertures = [4]").split("y = [")[0] + 'channels = ["g1"]\n'
TWO_STEPS = small_plan().split("y = [")[0] + 'channels = ["g1"]\n'


def write_plan(folder: Path, text: str) -> Path:
    path = folder / "plan.toml"
    path.write_text(text)
    return path


def cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def states(db: Path) -> list[str]:
    with Catalogue(db, readonly=True) as cat:
        return [r["state"] for r in cat.runs()]


# -- 1. a run whose close was lost ---------------------------------------------------------------------


def test_resume_closes_a_run_killed_after_its_last_commit(tmp_path, capsys):
    """Every step committed, then the process died before the run was closed: the journal says running."""
    plan = write_plan(tmp_path, ONE_STEP)
    db, sock = tmp_path / "cat.sqlite", tmp_path / "none.sock"
    common = ["--catalogue", db, "--socket", sock, "--workers", "1"]
    assert cli(capsys, "run", plan, *common)[0] == 0
    with Catalogue(db) as cat:
        cat.finish_run(1, "running")  # what a kill between the last commit and the close leaves
    code, out, err = cli(capsys, "status", "--catalogue", db, "--socket", sock)
    assert " interrupted " in out
    code, out, err = cli(capsys, "run", plan, "--resume", *common)
    assert code == 0 and "run 1 done" in out, err
    assert states(db) == ["done"]
    code, out, err = cli(capsys, "status", "--catalogue", db, "--socket", sock)
    assert " done " in out and "interrupted" not in out
    # the plan is done, so a plain run starts afresh (a new run, as after any finished run)
    code, out, err = cli(capsys, "run", plan, *common)
    assert code == 0 and "run 2 done" in out, err
    assert states(db) == ["done", "done"]


def test_a_killed_capture_is_not_left_interrupted(tmp_path, capsys):
    """`psfd capture` cannot be resumed by hand: a close it lost is recovered by the next command that runs."""
    db, sock = tmp_path / "cat.sqlite", tmp_path / "none.sock"
    common = ["--catalogue", db, "--socket", sock, "--workers", "1"]
    assert cli(capsys, "capture", "--aperture", "4", "--simulate", "--channels", "g1", *common)[0] == 0
    with Catalogue(db) as cat:
        cat.finish_run(1, "running")  # killed after its commit
    assert cli(capsys, "capture", "--aperture", "8", "--simulate", "--channels", "g1", *common)[0] == 0
    assert states(db) == ["done", "done"]
    code, out, err = cli(capsys, "status", "--catalogue", db, "--socket", sock)
    assert "interrupted" not in out


@pytest.mark.parametrize("request_", ["pause", "cancel"])
def test_a_stop_that_comes_after_the_last_commit_leaves_the_run_done(tmp_path, request_):
    """Ctrl-C or `systemctl stop` once every step is committed: nothing is left to resume, so the run is done
    (not paused, which a plain `psfd run` would then refuse and only --new would get past)."""
    plan = parse_plan(TWO_STEPS, "two.toml")
    keys = [s.key for s in plan.steps()]
    control = Control()

    def on_step(key, state, reason):
        if state == "done" and key == keys[-1]:
            control.request(request_)

    camera, rail = open_rig(plan.rig_config())
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        result = Runner(cat, tmp_path / "frames", workers=1, progress=None, control=control,
                        on_step=on_step).run(plan, camera, rail)
        assert (result.state, result.steps_done) == ("done", 2), result.reason
        assert [r["state"] for r in cat.runs()] == ["done"]


# -- 5. refusing writes nothing -------------------------------------------------------------------------


def test_a_refused_frame_store_leaves_no_catalogue(tmp_path, capsys):
    plan = write_plan(tmp_path, ONE_STEP)
    (tmp_path / "a-file").write_text("mine")
    db = tmp_path / "cat.sqlite"
    code, out, err = cli(capsys, "run", plan, "--frames", tmp_path / "a-file", "--catalogue", db,
                         "--socket", tmp_path / "none.sock")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "a-file" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "plan.toml"]


def test_a_newer_catalogue_is_refused_untouched(tmp_path, capsys):
    db = tmp_path / "newer.sqlite"
    with sqlite3.connect(db) as conn:  # a catalogue of a newer psfd, in rollback-journal mode
        conn.execute("CREATE TABLE runs (id INTEGER PRIMARY KEY)")
        conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    conn.close()
    before = hashlib.sha256(db.read_bytes()).hexdigest()
    plan = write_plan(tmp_path, ONE_STEP)
    none = ["--socket", tmp_path / "none.sock"]
    for argv in (["query"], ["status", *none], ["run", plan, *none],
                 ["capture", "--aperture", "4", "--simulate", *none]):
        code, out, err = cli(capsys, *argv, "--catalogue", db)
        assert code == 5 and "newer" in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert hashlib.sha256(db.read_bytes()).hexdigest() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["newer.sqlite", "plan.toml"]  # no -wal, no frames
    with sqlite3.connect(db) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
    conn.close()


def test_resume_without_catalogue_creates_none(tmp_path, capsys):
    plan = write_plan(tmp_path, ONE_STEP)
    code, out, err = cli(capsys, "run", plan, "--resume", "--catalogue", tmp_path / "c.sqlite",
                         "--socket", tmp_path / "none.sock")
    assert code == 2 and "no unfinished run" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml"]


# -- 9. disk full and read-only file systems -------------------------------------------------------------


class FullDiskCamera:
    """The simulated camera whose download fails with ``code`` (ENOSPC, EROFS) from the ``after``-th capture on,
    as a camera driver's write of the RAW file into the store's folder would."""

    def __init__(self, camera, after: int, code: int) -> None:
        self.camera, self.left, self.code = camera, after, code

    def __getattr__(self, name):
        return getattr(self.camera, name)

    def capture(self, dest):
        if self.left == 0:
            (Path(dest) / "IMG_0001.DNG").write_bytes(b"half a frame")  # what a failed write leaves
            raise OSError(self.code, os.strerror(self.code), str(Path(dest) / "IMG_0001.DNG"))
        self.left -= 1
        return self.camera.capture(dest)


@pytest.mark.parametrize("code, words", [(errno.ENOSPC, "No space left on device"),
                                         (errno.EROFS, "Read-only file system")])
def test_a_frame_write_that_fails_for_lack_of_space_pauses_and_resume_continues(tmp_path, code, words):
    plan = parse_plan(small_plan(), "small.toml")
    db, frames = tmp_path / "cat.sqlite", tmp_path / "frames"
    camera, rail = open_rig(plan.rig_config())
    with Catalogue(db) as cat:
        result = Runner(cat, frames, workers=1, progress=None).run(plan, FullDiskCamera(camera, 2, code), rail)
        assert result.state == "paused" and isinstance(result.error, StorageError)
        assert result.error.exit_code == 5 and words in result.reason and "--resume" not in result.reason
        summary = cat.run_summary(result.run_id)
        assert (summary["done"], summary["failed"], summary["pending"]) == (2, 1, 1)
        (failed,) = cat.steps(result.run_id, ("failed",))
        assert words in failed["reason"]
        assert not list(frames.glob(".incoming-*"))  # the half-written download is gone
        camera, rail = open_rig(plan.rig_config())
        again = Runner(cat, frames, workers=1, progress=None).run(plan, camera, rail, resume=True)
        assert again.state == "done" and again.steps_done == 2
    check_complete(db, frames, plan)


def test_a_catalogue_commit_that_finds_the_disk_full_pauses_and_resume_continues(tmp_path):
    """SQLite's own limit on the file's size (max_page_count) makes its commit fail with SQLITE_FULL,
    as a full disk does: the step stays uncommitted, the run pauses, and resumes once there is room."""
    plan = parse_plan(small_plan(), "small.toml")
    db, frames = tmp_path / "cat.sqlite", tmp_path / "frames"
    control = Control()
    camera, rail = open_rig(plan.rig_config())
    with Catalogue(db) as cat:
        # one step committed, then stop: the catalogue's size is known
        runner = Runner(cat, frames, workers=1, progress=None, control=control,
                        on_step=lambda key, state, reason: state == "running" and control.request("pause"))
        first = runner.run(plan, camera, rail)
        assert first.state == "paused" and first.steps_done == 1
        pages = cat.db.execute("PRAGMA page_count").fetchone()[0]
        cat.db.execute(f"PRAGMA max_page_count = {pages + 1}")  # room for the journal, not for a step's PSFs
        camera, rail = open_rig(plan.rig_config())
        result = Runner(cat, frames, workers=1, progress=None).run(plan, camera, rail, resume=True)
        assert result.state == "paused" and isinstance(result.error, StorageError), result.reason
        assert "full" in result.reason
        assert cat.integrity_check() == []
        assert cat.run_summary(first.run_id)["done"] == 1  # nothing half-committed
        cat.db.execute("PRAGMA max_page_count = 1073741823")  # space is back
        camera, rail = open_rig(plan.rig_config())
        again = Runner(cat, frames, workers=1, progress=None).run(plan, camera, rail, resume=True)
        assert again.state == "done", again.reason
    check_complete(db, frames, plan)


@pytest.fixture
def small_disk(tmp_path):
    """A 4 MiB tmpfs (root only): a real file system that fills up and can be remounted read-only."""
    yield from _tmpfs(tmp_path, "4m")


@pytest.fixture
def tiny_disk(tmp_path):
    """A 64 KiB tmpfs (root only): too small for a new catalogue."""
    yield from _tmpfs(tmp_path, "64k")


def _tmpfs(tmp_path: Path, size: str):
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a size-limited tmpfs needs root")
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _psfd(*argv, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "psfd", *map(str, argv)], capture_output=True, text=True,
                          timeout=timeout)


def test_a_full_file_system_pauses_the_run_and_resume_continues_once_space_is_back(small_disk, tmp_path):
    plan_path = write_plan(tmp_path, small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    db = small_disk / "cat.sqlite"
    common = ["--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1"]
    # leave room for the catalogue and about two frames (a simulated frame is ~0.6 MB)
    filler = small_disk / "filler"
    free = shutil.disk_usage(small_disk).free
    with open(filler, "wb") as fh:
        fh.write(b"\0" * (free - 1_600_000))
    full = _psfd("run", plan_path, *common)
    assert full.returncode == 5, full.stderr
    last = full.stderr.strip().splitlines()[-1]
    assert "No space left on device" in last and "continue with: psfd run" in last and "--resume" in last
    with Catalogue(db, readonly=True) as cat:
        assert cat.integrity_check() == []
        assert 0 < cat.run_summary(1)["done"] < 4
    assert not list(frames_dir_for(db).glob(".incoming-*"))
    filler.unlink()  # space is back
    again = _psfd("run", plan_path, "--resume", *common)
    assert again.returncode == 0, again.stderr
    assert states(db) == ["done"]
    check_complete(db, frames_dir_for(db), plan)


def test_a_disk_too_full_for_a_new_catalogue_is_refused_in_one_line_and_leaves_nothing(tiny_disk, tmp_path):
    """A disk that fills up while a new catalogue is made: the run was refused in one line (exit 5), but an
    empty catalogue file (WAL header, no table) and frame store stayed, and `psfd query` then called the
    file 'empty, not a psfd catalogue'. Nothing is left, and a reader finds no catalogue."""
    plan_path = write_plan(tmp_path, ONE_STEP)
    db = tiny_disk / "lab" / "cat.sqlite"
    done = _psfd("run", plan_path, "--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1")
    assert done.returncode == 5, done.stderr
    assert done.stderr.splitlines() == [f"psfd: error: cannot write to {db}: database or disk is full"]
    assert list(tiny_disk.iterdir()) == []
    query = _psfd("query", "--catalogue", db)
    assert query.returncode == 5 and query.stderr.strip() == f"psfd: error: no catalogue at {db}", query.stderr


def test_a_read_only_file_system_is_refused_in_one_line_and_resume_continues(small_disk, tmp_path):
    plan_path = write_plan(tmp_path, TWO_STEPS)
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    db = small_disk / "cat.sqlite"
    common = ["--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1"]
    camera, rail = open_rig(plan.rig_config())
    control = Control()
    with Catalogue(db) as cat:  # one step done, then paused
        Runner(cat, frames_dir_for(db), workers=1, progress=None, control=control,
               on_step=lambda key, state, reason: state == "running" and control.request("pause")).run(plan, camera,
                                                                                                        rail)
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    try:
        refused = _psfd("run", plan_path, "--resume", *common)
        assert refused.returncode == 5 and len(refused.stderr.strip().splitlines()) == 1, refused.stderr
        assert "Read-only file system" in refused.stderr or "read-only" in refused.stderr
        readable = _psfd("query", "--catalogue", db)
        assert readable.returncode == 0, readable.stderr  # reading needs no write
    finally:
        subprocess.run(["mount", "-o", "remount,rw", str(small_disk)], check=True)
    again = _psfd("run", plan_path, "--resume", *common)
    assert again.returncode == 0, again.stderr
    check_complete(db, frames_dir_for(db), plan)


# -- 10. SIGKILL in every phase of a run ----------------------------------------------------------------

PHASES = ("capture", "pending", "store", "estimate", "commit", "last-commit", "close-down")


def killed_run(plan_path: Path, db: Path, phase: str, nth: int, resume: bool, tmp_path: Path) -> int:
    """`psfd run` in its own session, killed (the whole group, like a power cut) at the ``nth`` time it
    reaches ``phase`` (tests/kill_at.py); returns the exit status."""
    argv = [sys.executable, str(HERE / "kill_at.py"), f"{phase}:{nth}", "run", str(plan_path), "--catalogue",
            str(db), "--socket", str(tmp_path / "none.sock"), "--workers", "1", "--backlog", "1"]
    proc = subprocess.run(argv + ["--resume"] * resume, start_new_session=True, capture_output=True, text=True,
                          timeout=600)
    return proc.returncode


def kill_and_resume(tmp_path: Path, plan_text: str, phase: str, nth: int) -> None:
    plan_path = write_plan(tmp_path, plan_text)
    plan = parse_plan(plan_text, str(plan_path))
    db = tmp_path / "cat.sqlite"
    code = killed_run(plan_path, db, phase, nth, False, tmp_path)
    assert code == -signal.SIGKILL, f"{phase}:{nth} was not reached (exit {code})"
    with Catalogue(db, readonly=True) as cat:
        assert cat.integrity_check() == []
        state = cat.runs()[0]["state"]
    if state != "done":  # the kill came before the close
        resumed = _psfd("run", plan_path, "--resume", "--catalogue", db, "--socket", tmp_path / "none.sock",
                        "--workers", "1")
        assert resumed.returncode == 0, resumed.stderr
    status = _psfd("status", "--catalogue", db, "--socket", tmp_path / "none.sock")
    assert " done " in status.stdout and "interrupted" not in status.stdout, status.stdout
    assert states(db) == ["done"]
    check_complete(db, frames_dir_for(db), plan)


@pytest.mark.parametrize("phase", ["commit", "last-commit"])
def test_sigkill_in_a_phase_then_resume(tmp_path, phase):
    """The default suite's share of the sweep below: mid-commit and between the last commit and the close."""
    kill_and_resume(tmp_path, TWO_STEPS, phase, 2 if phase == "commit" else 1)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("phase", PHASES)
def test_sigkill_sweep_over_every_phase(tmp_path, phase, seed):
    """Every phase, at a reproducible random occurrence of it, then resume: every PSF once, the run done."""
    plan = small_plan()
    nth = 1 if phase in ("last-commit", "close-down") else random.Random(f"{phase}-{seed}").randint(1, 4)
    kill_and_resume(tmp_path, plan, phase, nth)


# -- 11. a plan edited after a stop ----------------------------------------------------------------------

# The audit's plan: 2 apertures x 3 lateral positions, 6 steps.
SIX_STEPS = re.sub(r"y = \[(.*), (.*)\]", r"y = [\1, 0.0, \2]\nz = [0]", small_plan())


def test_a_plan_edited_after_a_kill_is_still_its_plan_and_another_aperture_is_not(tmp_path):
    """A comment added to the plan of a killed run neither hides the run from --resume nor lets a plain run
    measure its positions a second time; a plan with another aperture is another plan."""
    plan_path = write_plan(tmp_path, SIX_STEPS)
    plan = parse_plan(SIX_STEPS, str(plan_path))
    assert len(plan.steps()) == 6
    db = tmp_path / "cat.sqlite"
    common = ("--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1")
    assert killed_run(plan_path, db, "commit", 4, False, tmp_path) == -signal.SIGKILL  # in step 4's commit
    commented = SIX_STEPS + "# note: lens cap removed\n"
    plan_path.write_text(commented)

    again = _psfd("run", plan_path, *common)
    assert again.returncode == 2 and len(again.stderr.strip().splitlines()) == 1, again.stderr
    assert f"run 1 of plan {plan_path} is interrupted (3/6 steps done): add --resume" in again.stderr
    assert "comments, layout or defaults written out" in again.stderr  # why an edited file is still the run's plan

    plan_path.write_text(commented.replace("apertures = [4, 11]", "apertures = [4, 8]"))
    other = _psfd("run", plan_path, "--resume", *common)
    assert other.returncode == 2 and len(other.stderr.strip().splitlines()) == 1, other.stderr
    assert f"no unfinished run of plan {plan_path} to resume: run 1 of it is interrupted (3/6 steps done)" \
           in other.stderr and "[capture] apertures" in other.stderr, other.stderr

    plan_path.write_text(commented)
    resumed = _psfd("run", plan_path, "--resume", *common)
    assert resumed.returncode == 0, resumed.stderr
    assert states(db) == ["done"]  # run 1 went on: no second run
    with Catalogue(db, readonly=True) as cat:
        assert cat.run(1)["plan_text"] == SIX_STEPS and len(cat.steps(1)) == 6  # its own text and steps
    check_complete(db, frames_dir_for(db), plan)  # every position exactly once


# -- 12. signals to the whole process group while an estimate is in a worker -----------------------------


def held_run(tmp_path: Path, plan_path: Path, db: Path, **popen) -> subprocess.Popen:
    """`psfd run` in its own session (as a terminal or systemd starts it), its first estimate held in its
    worker until the test removes ``tmp_path/hold`` (tests/held_estimate.py)."""
    (tmp_path / "hold").touch()
    argv = [sys.executable, str(HERE / "held_estimate.py"), "run", str(plan_path), "--catalogue", str(db),
            "--socket", str(tmp_path / "none.sock"), "--workers", "1"]
    # a hang-up ends it, as when a terminal starts it, also when the tests themselves run under nohup
    popen.setdefault("preexec_fn", lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))
    return subprocess.Popen(argv, env={**os.environ, "PSFD_HOLD": str(tmp_path)}, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)


def wait_for(proc: subprocess.Popen, ready, what: str):
    """The first true ``ready()``, polled while ``proc`` runs (two minutes at most)."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        value = ready()
        if value:
            return value
        time.sleep(0.01)
    proc.kill()
    raise AssertionError(f"never {what}: {proc.communicate()[1]}")


def step_states(db: Path) -> dict[str, str]:
    with Catalogue(db, readonly=True) as cat:
        return {row["key"]: row["state"] for row in cat.steps(cat.runs()[0]["id"])}


def held_pid(tmp_path: Path) -> int | None:
    """The pid of the worker whose estimate is held, once it is."""
    marker = tmp_path / "estimating"
    return int(marker.read_text()) if marker.exists() else None


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_to_the_whole_group_mid_estimate_pauses_the_run_cleanly(tmp_path, signum):
    """Ctrl-C (SIGINT to the terminal's process group), `systemctl stop` (SIGTERM to the control group) or a
    hang-up (SIGHUP to the terminal's group: an ssh session dropped, a terminal closed) reaches the
    estimation workers too: it must act as if sent to psfd alone (the estimate in flight finishes and is
    committed, the run pauses, exit 130, 143 or 129), never a traceback or a failed step. After a hang-up
    every write to the gone terminal fails, and psfd writes nothing more (before, the hang-up ended psfd and
    its worker at once, the run left interrupted)."""
    plan_path = write_plan(tmp_path, small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    db = tmp_path / "cat.sqlite"
    proc = held_run(tmp_path, plan_path, db)
    wait_for(proc, lambda: held_pid(tmp_path), "estimating")
    os.killpg(proc.pid, signum)
    (tmp_path / "hold").unlink()
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signum, err
    assert "Traceback" not in err and "failed" not in err, err
    name = signal.Signals(signum).name
    if signum == signal.SIGHUP:
        assert "paused" not in err, err  # what came after the hang-up went to /dev/null
    else:
        assert err.splitlines()[-1].startswith(f"run 1 paused (interrupted by {name}); continue with: psfd run"), err
    steps = step_states(db)
    assert steps[plan.steps()[0].key] == "done", steps  # the estimate in flight was committed
    assert "failed" not in steps.values() and "running" not in steps.values(), steps
    assert states(db) == ["paused"]
    resumed = _psfd("run", plan_path, "--resume", "--catalogue", db, "--socket", tmp_path / "none.sock",
                    "--workers", "1")
    assert resumed.returncode == 0, resumed.stderr
    check_complete(db, frames_dir_for(db), plan)


def test_a_run_started_with_nohup_goes_on_after_a_hang_up(tmp_path):
    """`nohup psfd run plan.toml &` asks to go on without a terminal: a hang-up then changes nothing."""
    plan_path = write_plan(tmp_path, small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    db = tmp_path / "cat.sqlite"
    proc = held_run(tmp_path, plan_path, db, preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    wait_for(proc, lambda: held_pid(tmp_path), "estimating")
    os.killpg(proc.pid, signal.SIGHUP)
    (tmp_path / "hold").unlink()
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert states(db) == ["done"]
    check_complete(db, frames_dir_for(db), plan)


def test_a_worker_killed_alone_fails_its_step_in_one_line_and_keeps_the_others(tmp_path):
    """A worker that dies (SIGKILL, the OOM killer) takes its estimate with it: that step fails in one line
    and the run pauses, resumable; the other steps already handed to the workers are still estimated."""
    plan_path = write_plan(tmp_path, small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    keys = [s.key for s in plan.steps()]
    db = tmp_path / "cat.sqlite"
    proc = held_run(tmp_path, plan_path, db)
    pid = wait_for(proc, lambda: held_pid(tmp_path), "estimating")
    # the third step is being shot: the second one's estimate waits in the pool behind the held one
    wait_for(proc, lambda: db.exists() and list(step_states(db).values()).count("running") >= 3, "shooting step 3")
    os.kill(pid, signal.SIGKILL)
    (tmp_path / "hold").unlink()
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == EstimationError.exit_code, err
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if "paused" in line]
    assert len(errors) == 1 and errors[0].startswith(f"run 1 paused (step {keys[0]}: the estimation process "), err
    steps = step_states(db)
    assert steps[keys[0]] == "failed" and steps[keys[1]] == "done", steps  # the one in the pool was kept
    assert list(steps.values()).count("failed") == 1 and "running" not in steps.values(), steps
    resumed = _psfd("run", plan_path, "--resume", "--catalogue", db, "--socket", tmp_path / "none.sock",
                    "--workers", "1")
    assert resumed.returncode == 0, resumed.stderr
    check_complete(db, frames_dir_for(db), plan)


# -- 13. two processes on one catalogue ------------------------------------------------------------------


def stopped(pid: int) -> bool:
    """Whether process ``pid`` is stopped (SIGSTOP: state T in /proc/PID/stat)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "T"
    except (OSError, IndexError):
        return False


def test_a_second_writer_of_a_catalogue_in_use_is_refused_and_the_first_loses_nothing(tmp_path):
    """The frame store's lock keeps two runs of one store apart, not two writers of one catalogue: a
    `psfd capture --out DIR` (or a run with another --frames) into the catalogue a `psfd run` was writing
    swept its own store and then forgot the whole catalogue's journal of frames being stored, the first
    run's included; killed after storing a frame, the first run left it in its store for ever (a file no
    catalogue row holds), and the capture's PSF was stored between the run's steps. A second writer is now
    refused in one line while the first holds the catalogue, and the first resumes to a complete store."""
    plan_path = write_plan(tmp_path, TWO_STEPS)
    plan = parse_plan(TWO_STEPS, str(plan_path))
    db = tmp_path / "cat.sqlite"
    sock = tmp_path / "none.sock"
    # the first run stops itself (and its workers) right after its first frame is stored, not yet committed
    first = subprocess.Popen([sys.executable, str(HERE / "kill_at.py"), "store:1:STOP", "run", str(plan_path),
                              "--catalogue", str(db), "--socket", str(sock), "--workers", "1"],
                             start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300
        while not stopped(first.pid):
            assert first.poll() is None and time.monotonic() < deadline, "the first run never stored a frame"
            time.sleep(0.1)
        capture = _psfd("capture", "--simulate", "--aperture", "4", "--channels", "g1", "--catalogue", db,
                        "--out", tmp_path / "other", "--socket", sock, "--workers", "1")
        again = _psfd("run", plan_path, "--resume", "--catalogue", db, "--frames", tmp_path / "other",
                      "--socket", sock, "--workers", "1")
        for second in (capture, again):
            assert second.returncode == 5, second.stderr
            assert second.stderr.splitlines() == [f"psfd: error: the catalogue {db} is in use by psfd process "
                                                  f"{first.pid} (one process writes a catalogue at a time): wait "
                                                  "for it to end, or stop it (Ctrl-C or SIGTERM pauses a run)"], \
                second.stderr
        assert not (tmp_path / "other").exists()
        # another catalogue on the first run's frame store: refused by the store, and no new catalogue stays
        elsewhere = _psfd("run", plan_path, "--catalogue", tmp_path / "lab" / "b.sqlite", "--frames",
                          frames_dir_for(db), "--socket", sock, "--workers", "1")
        assert elsewhere.returncode == 5, elsewhere.stderr
        assert elsewhere.stderr == f"psfd: error: the frame store {frames_dir_for(db)} is in use by another run\n"
        assert not (tmp_path / "lab").exists()
    finally:
        os.killpg(first.pid, signal.SIGKILL)  # a power cut: the stored frame is not committed
        first.wait()
    assert states(db) == ["running"]
    resumed = _psfd("run", plan_path, "--resume", "--catalogue", db, "--socket", sock, "--workers", "1")
    assert resumed.returncode == 0, resumed.stderr
    check_complete(db, frames_dir_for(db), plan)


# -- 14. a run killed while it created its catalogue -------------------------------------------------------


def test_a_catalogue_whose_creation_was_killed_is_created_by_the_next_run(tmp_path, capsys):
    """SQLite makes the catalogue's file when it opens it; a run killed (or a power cut) before the schema's
    first commit leaves an empty file, or one with WAL mode set and no table. Every command refused it
    ('is empty, not a psfd catalogue', exit 5), a new `psfd run` included, until someone deleted it by hand:
    it is a catalogue not made yet, which the next run makes and `status` shows as no catalogue; `query` and
    `export` said 'is empty, not a psfd catalogue' of it, and now say no catalogue too."""
    plan_path = write_plan(tmp_path, ONE_STEP)
    plan = parse_plan(ONE_STEP, str(plan_path))
    for name, wal in (("zero.sqlite", False), ("wal.sqlite", True)):
        db = tmp_path / name
        conn = sqlite3.connect(db)  # what Catalogue() had done when it was killed
        if wal:
            conn.execute("PRAGMA journal_mode = WAL")
        conn.close()
        common = ("--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1")
        code, out, err = cli(capsys, "status", *common[:4])
        assert code == 0 and "no catalogue at" in out, err
        for command in (["query"], ["export", "--out", tmp_path / "psfs"]):
            code, out, err = cli(capsys, *command, "--catalogue", db)
            assert code == 5 and err == f"psfd: error: no catalogue at {db}\n", err
        code, out, err = cli(capsys, "run", plan_path, "--resume", *common)
        assert code == 2 and "no unfinished run" in err, err  # nothing was journalled
        code, out, err = cli(capsys, "run", plan_path, *common)
        assert code == 0, err
        check_complete(db, frames_dir_for(db), plan)


# -- 15. SIGTERM or Ctrl-C before the first step -----------------------------------------------------------


def signalled_run(tmp_path: Path, plan_path: Path, db: Path, moment: str, signum: int,
                  resume: bool = False, sigint=signal.SIG_DFL) -> subprocess.CompletedProcess:
    """`psfd run` in its own session, sent ``signum`` (to its whole group, as `systemctl stop` or Ctrl-C do)
    at a ``moment`` of its start (tests/kill_at.py); Ctrl-C at its default (``sigint``), as from a terminal,
    also where the suite runs as a background job (SIGINT ignored there)."""
    argv = [sys.executable, str(HERE / "kill_at.py"), f"{moment}:1:{signal.Signals(signum).name[3:]}", "run",
            str(plan_path), "--catalogue", str(db), "--socket", str(tmp_path / "none.sock"), "--workers", "1"]
    return subprocess.run(argv + ["--resume"] * resume, start_new_session=True, capture_output=True, text=True,
                          timeout=600, preexec_fn=lambda: signal.signal(signal.SIGINT, sigint))


def stopped_word(signum: int) -> str:
    return "terminated" if signum == signal.SIGTERM else "interrupted"


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
@pytest.mark.parametrize("moment", ["plan", "rig"])
def test_a_stop_before_the_run_is_journalled_leaves_nothing(tmp_path, moment, signum):
    """In its first second `psfd run` reads the plan and opens the rig; a SIGTERM or Ctrl-C then journalled
    a run of no step done and paused it (a catalogue, a frame store, a paused run that a plain `psfd run`
    of the plan then refused). Nothing was measured: nothing is left, and the command says so."""
    plan_path = write_plan(tmp_path, ONE_STEP)
    done = signalled_run(tmp_path, plan_path, tmp_path / "cat.sqlite", moment, signum)
    assert done.returncode == 128 + signum, done.stderr
    assert "Traceback" not in done.stderr and done.stdout == "", done.stderr
    assert done.stderr.splitlines()[-1] == \
        f"psfd: {stopped_word(signum)} (before the run started: nothing was stored)", done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml"]


def test_a_stop_while_a_new_catalogue_is_opened_leaves_nothing(tmp_path):
    """The frame store is held and the catalogue made, but the run not journalled yet: "nothing was stored",
    and yet the new catalogue (with its -wal and -shm) and frame store stayed, to be taken for a lab's
    catalogue. Nothing is left, and the next plain `psfd run` measures the plan; an older catalogue a stop
    finds is kept as it was."""
    plan_path = write_plan(tmp_path, ONE_STEP)
    db = tmp_path / "lab" / "cat.sqlite"
    done = signalled_run(tmp_path, plan_path, db, "opening", signal.SIGTERM)
    assert done.returncode == 143, done.stderr
    assert done.stderr.splitlines()[-1] == "psfd: terminated (before the run started: nothing was stored)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml"]
    Catalogue(db).close()  # an empty catalogue of the lab's
    done = signalled_run(tmp_path, plan_path, db, "opening", signal.SIGTERM)
    assert done.returncode == 143, done.stderr
    assert states(db) == []
    again = _psfd("run", plan_path, "--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1")
    assert again.returncode == 0, again.stderr
    check_complete(db, frames_dir_for(db), parse_plan(ONE_STEP, str(plan_path)))


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_once_the_run_is_journalled_pauses_it_with_the_hint(tmp_path, signum):
    """From the moment the run is journalled a stop ends as it does mid-run: the run is paused, the last line
    says how to continue, exit 143 or 130. A resume stopped before it reopens the run leaves it as it was."""
    plan_path = write_plan(tmp_path, TWO_STEPS)
    plan = parse_plan(TWO_STEPS, str(plan_path))
    db = tmp_path / "cat.sqlite"
    name = signal.Signals(signum).name
    done = signalled_run(tmp_path, plan_path, db, "journal", signum)
    assert done.returncode == 128 + signum, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    last = done.stderr.splitlines()[-1]
    assert last.startswith(f"run 1 paused (interrupted by {name}); continue with: psfd run {plan_path} --resume"), \
        done.stderr
    assert states(db) == ["paused"]
    before = step_states(db)

    resume = signalled_run(tmp_path, plan_path, db, "rig", signum, resume=True)
    assert resume.returncode == 128 + signum, resume.stderr
    assert resume.stderr.splitlines()[-1] == (f"psfd: {stopped_word(signum)} (before the run went on: it is as it "
                                              f"was; continue with: {last.split('continue with: ')[1]})")
    assert states(db) == ["paused"] and step_states(db) == before

    resume = signalled_run(tmp_path, plan_path, db, "journal", signum, resume=True)  # reopened, then stopped
    assert resume.returncode == 128 + signum, resume.stderr
    assert resume.stderr.splitlines()[-1] == last
    assert states(db) == ["paused"] and step_states(db) == before

    resumed = _psfd("run", plan_path, "--resume", "--catalogue", db, "--socket", tmp_path / "none.sock",
                    "--workers", "1")
    assert resumed.returncode == 0, resumed.stderr
    assert states(db) == ["done"]
    check_complete(db, frames_dir_for(db), plan)


def test_ctrl_c_ignored_by_the_parent_stays_ignored_before_the_run_is_journalled(tmp_path):
    """A process started with SIGINT ignored (a background job of a shell) keeps it ignored, the Unix
    convention: a SIGINT while the plan is read changes nothing and the run is measured."""
    plan_path = write_plan(tmp_path, ONE_STEP)
    db = tmp_path / "cat.sqlite"
    done = signalled_run(tmp_path, plan_path, db, "plan", signal.SIGINT, sigint=signal.SIG_IGN)
    assert done.returncode == 0 and "run 1 done" in done.stdout, done.stderr
    check_complete(db, frames_dir_for(db), parse_plan(ONE_STEP, str(plan_path)))



def test_a_capture_into_another_store_keeps_the_journal_of_a_killed_runs_frames(tmp_path):
    """A run killed after storing a frame (journalled, not committed) leaves it for its next sweep. A `psfd
    capture --out DIR` into the same catalogue meanwhile swept its own store, found none of the journalled
    frames there, and forgot them all: the resumed run then kept the killed run's frame in its store for ever,
    a file no catalogue row holds. Each store's frames are forgotten only once swept from that store."""
    plan_path = write_plan(tmp_path, TWO_STEPS)
    plan = parse_plan(TWO_STEPS, str(plan_path))
    db, other = tmp_path / "cat.sqlite", tmp_path / "other"
    common = ("--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1")
    assert killed_run(plan_path, db, "store", 1, False, tmp_path) == -signal.SIGKILL
    orphan = stored_files(frames_dir_for(db))
    assert len(orphan) == 1
    capture = _psfd("capture", "--simulate", "--aperture", "8", "--channels", "g1", "--out", other, *common)
    assert capture.returncode == 0, capture.stderr
    resumed = _psfd("run", plan_path, "--resume", *common)
    assert resumed.returncode == 0, resumed.stderr
    with Catalogue(db, readonly=True) as cat:
        assert cat.integrity_check() == [] and cat.pending_frames() == set()
        hashes = cat.frame_hashes()
        assert sorted(r["step"] for r in cat.query().rows if r["run_id"] == 1) == sorted(s.key for s in plan.steps())
    assert stored_files(other) | stored_files(frames_dir_for(db)) == hashes  # no orphan in either store
    assert not orphan & stored_files(frames_dir_for(db))
