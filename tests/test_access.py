"""Who may do what: sockets that refuse, many clients at once, readers without write access, other users' files.

Permissions are real: as root (where file modes do not stop the process) the reader runs in a
subprocess that drops to the ``nobody`` user with os.setuid after loading psfd; as another user,
the catalogue's folder and file are made read-only with chmod, which binds that user too.
"""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from psfd.catalogue import Catalogue
from psfd.cli import main
from psfd.daemon import client
from psfd.daemon.plan import parse_plan
from psfd.daemon.runner import Control, Runner
from psfd.drivers import open_rig
from psfd.errors import BadInputError, ServiceError
from psfd.vocabulary import REQUEST_DEPTH_MAX

from test_runner import small_plan
from test_service import Notifications, killed_service, raw_request, served  # noqa: F401 - fixture

ROOT = os.geteuid() == 0
NOBODY = 65534
ONE_STEP = small_plan().replace("apertures = [4, 11]", "apertures = [4]").split("y = [")[0] + 'channels = ["g1"]\n'


def cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def shared(tmp_path):
    """A folder others can enter but not write (0755), outside pytest's private (0700) tmp_path."""
    folder = Path(tempfile.mkdtemp(prefix="psfd-shared-"))
    folder.chmod(0o755)
    yield folder
    for path in sorted(folder.rglob("*"), reverse=True):
        path.chmod(0o700 if path.is_dir() else 0o600)
    subprocess.run(["rm", "-rf", str(folder)], check=False)


# -- 2. a socket that exists but refuses ---------------------------------------------------------------


def test_a_socket_nobody_listens_on_is_an_error_not_a_local_run(tmp_path, capsys):
    sock = tmp_path / "control.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sock))  # exists, never listens: connect is refused; no service's lock beside it to ask
    plan = tmp_path / "plan.toml"
    plan.write_text(ONE_STEP)
    db = tmp_path / "cat.sqlite"
    t0 = time.monotonic()
    code, out, err = cli(capsys, "run", plan, "--catalogue", db, "--socket", sock)
    assert code == 5 and len(err.strip().splitlines()) == 1 and str(sock) in err, err
    assert "refused" in err
    assert time.monotonic() - t0 < 30  # retried briefly, not for ever
    assert not db.exists()  # the plan was not run here behind the service's back
    stale.close()


def test_the_socket_of_a_killed_service_that_the_user_may_not_remove_is_named_and_passed_by(shared):
    """A user who may use the service but not write its socket folder (group psfd, /run/psfd is 0750) finds the
    socket a killed service left: the command says so in one line, that it could not remove it, and goes on
    without the service. The service's own user then removes it by starting the service again, or any command."""
    if not ROOT:
        pytest.skip("needs root to act as another user")
    sock, db = shared / "run" / "control.sock", shared / "cat.sqlite"
    sock.parent.mkdir(mode=0o755)
    with open(os.devnull, "w") as log:
        killed_service(sock, db, log)
    sock.chmod(0o666)  # nobody stands for a member of the socket's group: may connect, may not write the folder
    lock = client.lock_path(sock)
    assert stat.S_IMODE(lock.stat().st_mode) == 0o640
    lock.chmod(0o644)  # and may read the lock, as the group may
    status = _as_nobody(["status", "--socket", str(sock), "--catalogue", str(db)],
                        warm=["status", "--socket", str(shared / "none.sock"), "--catalogue", str(db)])
    assert status.returncode == 0 and status.stdout.startswith(f"no service at {sock}"), status.stderr
    assert status.stderr.splitlines() == [f"psfd: warning: {sock}: the socket of a psfd serve that ended without "
                                          "removing it; not removed (Permission denied), going on without the service"]
    assert stat.S_ISSOCK(os.lstat(sock).st_mode)
    mine = subprocess.run([sys.executable, "-m", "psfd", "status", "--socket", str(sock), "--catalogue", str(db)],
                          capture_output=True, text=True, timeout=60)
    assert mine.returncode == 0 and "ended without removing it; removed," in mine.stderr and not sock.exists()


def test_a_full_backlog_is_retried_then_an_error(tmp_path, capsys):
    sock = tmp_path / "busy.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(sock))
    server.listen(0)  # never accepts: the queue fills at once
    parked = []
    for _ in range(8):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.setblocking(False)
        try:
            s.connect(str(sock))
        except BlockingIOError:
            s.close()
            break
        parked.append(s)
    db = tmp_path / "cat.sqlite"
    code, out, err = cli(capsys, "capture", "--aperture", "4", "--simulate", "--catalogue", db, "--socket", sock)
    assert code == 5 and "busy" in err and len(err.strip().splitlines()) == 1, err
    assert not db.exists()
    for s in parked + [server]:
        s.close()


def _as_nobody(argv: list[str], warm: list[str] | None = None) -> subprocess.CompletedProcess:
    """``psfd ARGV`` in a subprocess that runs as user nobody (root) or as this user (otherwise).

    As root, psfd and what it imports are loaded first (``warm``: a command run before dropping
    privileges, on another catalogue), because the interpreter's own files may not be readable by nobody.
    """
    code = (
        "import os, sys\n"
        "from psfd.cli import main\n"
        "import psfd.catalogue, psfd.cli.output, psfd.daemon.plan, psfd.daemon.runner, psfd.drivers.sim, shlex\n"
        f"warm = {warm!r}\n"
        "if warm:\n"
        "    import contextlib, io\n"
        "    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):\n"
        "        main(warm)\n"
        f"if os.geteuid() == 0:\n"
        f"    os.setgroups([]); os.setgid({NOBODY}); os.setuid({NOBODY})\n"
        f"sys.exit(main({argv!r}))\n"
    )
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd="/")


def test_a_socket_that_refuses_the_caller_is_an_error(served, shared):  # noqa: F811
    """The service's socket is 0660: a user outside its group is refused, and told so, never run locally."""
    if not ROOT:
        pytest.skip("needs root to act as another user")
    proc, sock, db, notes = served
    (shared / "plan.toml").write_text(ONE_STEP)
    mine = shared / "mine.sqlite"
    done = _as_nobody(["run", str(shared / "plan.toml"), "--socket", str(sock), "--catalogue", str(mine)],
                      warm=["plan", "check", str(shared / "plan.toml")])
    assert done.returncode == 5, done.stderr
    assert "Permission denied" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not mine.exists()


# -- 2. many clients at once -----------------------------------------------------------------------------


def test_a_hundred_simultaneous_clients_all_get_an_answer(served):  # noqa: F811
    proc, sock, db, notes = served
    n = 100
    start = threading.Barrier(n)
    answers, errors = [], []

    def ask():
        start.wait()
        try:
            answers.append(client.request(sock, {"cmd": "status"}))
        except Exception as exc:  # noqa: BLE001 - counted below
            errors.append(repr(exc))

    threads = [threading.Thread(target=ask) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert errors == [] and len(answers) == n
    assert all(a["ok"] and a["state"] == "idle" for a in answers)
    assert proc.poll() is None


def test_deeply_nested_json_gets_an_answer_and_the_service_lives(served):  # noqa: F811
    proc, sock, db, notes = served
    answer = raw_request(sock, b"[" * 200_000 + b"]" * 200_000 + b"\n")
    assert answer["ok"] is False and "nest" in answer["error"]
    deep = (b"[" * REQUEST_DEPTH_MAX) + b"1" + (b"]" * REQUEST_DEPTH_MAX)
    answer = raw_request(sock, b'{"cmd": "status", "x": ' + deep + b"}\n")
    assert answer["ok"] is False and "nest" in answer["error"]
    answer = raw_request(sock, b'{"cmd": "status", "x": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}\n')
    assert answer["ok"] is True  # brackets inside a string are text
    assert client.request(sock, {"cmd": "status"})["state"] == "idle" and proc.poll() is None


def test_an_over_long_request_line_gets_an_answer_and_the_service_lives(served):  # noqa: F811
    """A line past the request bound is refused after the bound is read, not buffered whole."""
    proc, sock, db, notes = served
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(30)
        s.connect(str(sock))
        line = b'{"cmd": "status", "x": "' + b"a" * (2 * client.MAX_REQUEST) + b'"}\n'
        sender = threading.Thread(target=_send, args=(s, line))
        sender.start()
        answer = json.loads(s.makefile("rb").readline())
        sender.join(timeout=30)
    assert answer["ok"] is False and "longer than" in answer["error"] and answer["exit_code"] == 2
    assert client.request(sock, {"cmd": "status"})["state"] == "idle" and proc.poll() is None


def _send(s: socket.socket, data: bytes) -> None:
    """Send what the peer takes: the service stops reading (and closes) once the line is past the bound."""
    try:
        s.sendall(data)
    except OSError:
        pass


# -- the service's own files and socket folder ------------------------------------------------------------


@pytest.mark.parametrize("problem", ["world-writable", "another user's"])
def test_the_service_refuses_an_unsafe_socket_folder(tmp_path, problem):
    folder = tmp_path / "run"
    folder.mkdir()
    if problem == "world-writable":
        folder.chmod(0o777)
    else:
        if not ROOT:
            pytest.skip("needs root to give the folder to another user")
        os.chown(folder, NOBODY, NOBODY)
        folder.chmod(0o755)
    done = subprocess.run([sys.executable, "-m", "psfd", "serve", "--socket", str(folder / "control.sock"),
                           "--catalogue", str(tmp_path / "cat.sqlite")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 5 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert str(folder) in done.stderr and ("writable" in done.stderr or "belongs to" in done.stderr)
    assert not (folder / "control.sock").exists()


def test_the_same_refusal_has_the_same_exit_code_through_the_service(served, tmp_path, capsys):  # noqa: F811
    proc, sock, db, notes = served
    plan = tmp_path / "plan.toml"
    plan.write_text(ONE_STEP)
    local = cli(capsys, "run", plan, "--resume", "--catalogue", tmp_path / "mine.sqlite", "--socket",
                tmp_path / "none.sock")
    remote = cli(capsys, "run", plan, "--resume", "--socket", sock)
    assert local[0] == remote[0] == BadInputError.exit_code, (local, remote)
    assert "no unfinished run" in local[2] and "no unfinished run" in remote[2]
    with pytest.raises(BadInputError):  # the client raises the service's own error type
        client.request(sock, {"cmd": "submit", "plan": plan.read_text(), "path": str(plan), "resume": True})
    with pytest.raises(ServiceError):
        client.request(sock, {"cmd": "pause"})


def test_status_through_the_service_mentions_interrupted_runs(tmp_path):
    db = tmp_path / "cat.sqlite"
    plan = parse_plan(ONE_STEP, "one.toml")
    control = Control()
    control.request("pause")
    camera, rail = open_rig(plan.rig_config())
    with Catalogue(db) as cat:
        run = Runner(cat, tmp_path / "cat-frames", workers=1, progress=None, control=control).run(plan, camera, rail)
        cat.finish_run(run.run_id, "running")  # killed: journalled running, nobody holds its store
    notes = Notifications(tmp_path / "notify.sock")
    sock = tmp_path / "run" / "control.sock"
    env = {**os.environ, "NOTIFY_SOCKET": str(notes.path)}
    proc = subprocess.Popen([sys.executable, "-m", "psfd", "serve", "--socket", str(sock), "--catalogue", str(db),
                             "--workers", "1"], env=env, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        notes.wait_for("READY=1")
        status = subprocess.run([sys.executable, "-m", "psfd", "status", "--socket", str(sock)],
                                capture_output=True, text=True, timeout=60)
        assert status.returncode == 0, status.stderr
        assert "interrupted" in status.stdout and "one.toml" in status.stdout and "--resume" in status.stdout
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        notes.sock.close()


# -- 3. readers without write access ----------------------------------------------------------------------


def _catalogue_with_a_run(folder: Path) -> Path:
    db = folder / "cat.sqlite"
    plan = parse_plan(ONE_STEP, "one.toml")
    camera, rail = open_rig(plan.rig_config())
    with Catalogue(db) as cat:
        assert Runner(cat, folder / "cat-frames", workers=1, progress=None).run(plan, camera, rail).state == "done"
    return db


def _read_only(folder: Path, db: Path) -> None:
    """Nobody but root may write: the folder (where SQLite would create -wal and -shm) and the files in it."""
    for path in folder.iterdir():
        if path.is_file():
            path.chmod(0o444)
    folder.chmod(0o555)


def test_a_reader_without_write_access_queries_an_idle_catalogue(shared):
    db = _catalogue_with_a_run(shared)
    scratch = _catalogue_with_a_run(Path(tempfile.mkdtemp(dir=shared)))
    _read_only(shared, db)
    before = sorted(p.name for p in shared.iterdir())
    done = _as_nobody(["query", "--catalogue", str(db)], warm=["query", "--catalogue", str(scratch)])
    assert done.returncode == 0, done.stderr
    assert "bernoulli" in done.stdout and done.stderr == ""
    status = _as_nobody(["status", "--catalogue", str(db), "--socket", str(shared / "none.sock")],
                        warm=["status", "--catalogue", str(scratch), "--socket", str(shared / "none.sock")])
    assert status.returncode == 0 and " done " in status.stdout, status.stderr
    assert sorted(p.name for p in shared.iterdir()) == before


def test_a_reader_without_write_access_queries_while_a_run_writes(shared):
    """While a run commits steps, a reader that may not write anything still reads, and never blocks it."""
    if not ROOT:
        pytest.skip("the writer must be able to write where the reader cannot: needs root to be two users")
    db = _catalogue_with_a_run(shared)
    scratch = _catalogue_with_a_run(Path(tempfile.mkdtemp(dir=shared)))
    for path in shared.iterdir():
        if path.is_file():
            path.chmod(0o644)
    # 8 steps: the run lasts several of the reader's queries (each a new process) on a loaded machine too
    (shared / "plan.toml").write_text(small_plan().replace("apertures = [4, 11]", "apertures = [4, 5.6, 8, 11]"))
    writer = subprocess.Popen([sys.executable, "-m", "psfd", "run", str(shared / "plan.toml"), "--catalogue", str(db),
                               "--socket", str(shared / "none.sock"), "--workers", "1", "--backlog", "1"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    seen = set()
    try:
        deadline = time.monotonic() + 300
        while writer.poll() is None and time.monotonic() < deadline:
            done = _as_nobody(["query", "--catalogue", str(db), "--json"], warm=["query", "--catalogue", str(scratch)])
            assert done.returncode == 0, done.stderr
            seen.add(len(done.stdout.splitlines()))
        out, err = writer.communicate(timeout=300)
    finally:
        if writer.poll() is None:
            writer.kill()
    assert writer.returncode == 0, err
    assert len(seen) >= 2 and min(seen) >= 1  # read the catalogue as it grew, from 1 PSF up
    final = _as_nobody(["query", "--catalogue", str(db), "--json"], warm=["query", "--catalogue", str(scratch)])
    assert len(final.stdout.splitlines()) == 1 + 8


def test_a_reader_holding_a_snapshot_does_not_block_the_writer(tmp_path):
    db = _catalogue_with_a_run(tmp_path)
    with Catalogue(db, readonly=True) as reader, Catalogue(db, timeout=0.5) as writer:
        with reader._read():  # a long read transaction: one consistent snapshot
            rows = len(reader.query().rows)
            run = writer.start_run("p", "t", writer.add_rig(open_rig({"simulate": True})[0].info()), [("k", {})])
            writer.finish_run(run, "cancelled")  # committed while the reader reads
            assert len(reader.query().rows) == rows
        assert [r["id"] for r in reader.runs()][0] == run


# -- 8. files of the service's catalogue keep their owner ----------------------------------------------------


def test_root_cannot_leave_its_files_in_another_users_catalogue(tmp_path, capsys):
    if not ROOT:
        pytest.skip("needs root to own files as another user")
    db = _catalogue_with_a_run(tmp_path)
    frames = tmp_path / "cat-frames"
    for path in [tmp_path, *tmp_path.rglob("*")]:
        os.chown(path, NOBODY, NOBODY)
    code, out, err = cli(capsys, "capture", "--aperture", "8", "--simulate", "--channels", "g1", "--catalogue", db,
                         "--socket", tmp_path / "none.sock", "--workers", "1")
    assert code == 5 and len(err.strip().splitlines()) == 1, err
    assert "belongs to" in err and "nobody" in err
    owners = {p.stat().st_uid for p in [tmp_path, *tmp_path.rglob("*")]}
    assert owners == {NOBODY}  # nothing of root's left in the service's folders
    assert len(list(frames.glob("??/*"))) == 1
    with Catalogue(db, readonly=True) as cat:
        assert len(cat.runs()) == 1
