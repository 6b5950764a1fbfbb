"""`psfd serve`: control socket, systemd notifications, bad requests, SIGTERM, the unit file."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from psfd.catalogue import Catalogue
from psfd.daemon import client
from psfd.daemon.plan import parse_plan
from psfd.daemon.service import Service, hold_lock
from psfd.daemon.store import queue_path, store_lock
from psfd.drivers.base import CameraInfo
from psfd.errors import BadInputError, ServiceError

from plans import one_channel_plan
from test_runner import check_complete, small_plan, stored_files

ROOT = Path(__file__).resolve().parents[1]


class Notifications:
    """A stand-in for systemd's $NOTIFY_SOCKET: a thread collects the datagrams the service sends."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.path, self.messages = path, []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        while True:
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except OSError:
                return

    def wait_for(self, needle: str, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for message in list(self.messages):
                if needle in message:
                    return message
            time.sleep(0.05)
        raise AssertionError(f"no {needle!r} notification; got {self.messages}")


@pytest.fixture
def served(tmp_path):
    """A running `psfd serve` with its notify socket, control socket and catalogue in tmp_path."""
    notes = Notifications(tmp_path / "notify.sock")
    sock = tmp_path / "run" / "control.sock"
    db = tmp_path / "cat.sqlite"
    env = {**os.environ, "NOTIFY_SOCKET": str(notes.path), "WATCHDOG_USEC": "1000000"}
    env.pop("WATCHDOG_PID", None)
    log = open(tmp_path / "serve.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "psfd", "serve", "--socket", str(sock), "--catalogue", str(db),
                             "--workers", "1"], env=env, stderr=log, start_new_session=True)
    try:
        notes.wait_for("READY=1")
        yield proc, sock, db, notes
    finally:
        end_group(proc)
        notes.sock.close()
        log.close()


def end_group(proc: subprocess.Popen) -> None:
    """Kill a service a test started (in a session of its own) with its whole group, if it still runs."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def raw_request(sock: Path, line: bytes) -> dict:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(str(sock))
        s.sendall(line)
        return json.loads(s.makefile("rb").readline())


def test_socket_is_0660_and_bad_requests_leave_the_service_running(served, tmp_path):
    proc, sock, db, notes = served
    assert stat.S_IMODE(os.stat(sock).st_mode) == 0o660
    assert stat.S_ISSOCK(os.stat(sock).st_mode)
    notes.wait_for("WATCHDOG=1")  # WATCHDOG_USEC=1 s: pings every half second
    assert "error" in raw_request(sock, b"this is not json\n") and proc.poll() is None
    answer = raw_request(sock, b'{"cmd": "reboot"}\n')
    assert answer["ok"] is False and "unknown command 'reboot'" in answer["error"]
    answer = raw_request(sock, b'[1, 2]\n')
    assert answer == {"ok": False, "error": 'request must be a JSON object with "cmd"', "error_type": "BadInputError",
                      "exit_code": 2}
    answer = raw_request(sock, json.dumps({"cmd": "submit", "plan": "[target]\nkind = 'x'\n"}).encode() + b"\n")
    assert answer["ok"] is False and len(answer["problems"]) >= 2
    assert any("kind must be one of" in p for p in answer["problems"])
    with pytest.raises(ServiceError, match="no run is in progress"):
        client.request(sock, {"cmd": "pause"})
    with pytest.raises(ServiceError, match="no paused run"):
        client.request(sock, {"cmd": "resume"})
    assert client.request(sock, {"cmd": "status"})["state"] == "idle"
    # `psfd status` asks the service when its socket answers
    cli = subprocess.run([sys.executable, "-m", "psfd", "status", "--socket", str(sock)],
                         capture_output=True, text=True)
    assert cli.returncode == 0 and "idle" in cli.stdout
    cli = subprocess.run([sys.executable, "-m", "psfd", "status", "--json", "--socket", str(sock)],
                         capture_output=True, text=True)
    status = json.loads(cli.stdout)  # the same shape as without the service (docs/formats.md)
    assert set(status) == {"service", "catalogue", "runs"} and status["runs"] == []
    assert set(status["service"]) == {"socket", "state", "queued", "held", "held_by", "current", "last",
                                      "paused_plan", "unfinished"}
    assert status["service"]["state"] == "idle" and status["service"]["socket"] == str(sock)
    assert proc.poll() is None
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 0
    notes.wait_for("STOPPING=1")
    assert not sock.exists()
    # its log (stderr): start, refusals with their reason, the signal and the stop, each one line
    log = (tmp_path / "serve.log").read_text().splitlines()
    assert any(f"psfd: info: psfd service listening on {sock}" in line for line in log)
    assert any("psfd: warning: pause refused: no run is in progress" in line for line in log)
    assert any("psfd: info: SIGTERM: stopping the service after the current frame" in line for line in log)
    assert log[-1].endswith("psfd: info: psfd service stopped")
    assert all(re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d psfd: ", line) for line in log)  # timestamped


def wait_status(sock: Path, predicate, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = client.request(sock, {"cmd": "status"})
        if predicate(status):
            return status
        time.sleep(0.2)
    raise AssertionError(f"status never matched; last {status}")


def test_pause_resume_then_sigterm_mid_run_and_resume_from_the_cli(served, tmp_path):
    proc, sock, db, notes = served
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    answer = client.request(sock, {"cmd": "submit", "plan": plan.text, "path": str(plan_path)})
    assert answer["queued"] == 1
    wait_status(sock, lambda s: s["current"] and s["current"]["step"])
    assert client.request(sock, {"cmd": "pause"})["requested"] == "pause"
    status = wait_status(sock, lambda s: s["state"] == "paused")
    assert status["last"]["state"] == "paused" and status["last"]["steps_done"] < 4
    # submitting the paused plan afresh is refused at once (no PSF stored twice), as the bad input it is ...
    with pytest.raises(BadInputError, match=r"is paused .*add --resume to continue it, or --new"):
        client.request(sock, {"cmd": "submit", "plan": plan.text, "path": str(plan_path)})
    # ... with a comment added too: it is the same plan ...
    with pytest.raises(BadInputError,
                       match=r"is paused .*add --resume to continue it, or --new .*comments, layout or defaults"):
        client.request(sock, {"cmd": "submit", "plan": plan.text + "\n# lens cap removed\n", "path": str(plan_path)})
    # ... and resuming a plan that has no unfinished run (another aperture is another plan) is refused
    with pytest.raises(BadInputError, match="no unfinished run of plan other.toml to resume"):
        client.request(sock, {"cmd": "submit", "plan": plan.text.replace("[4, 11]", "[4, 8]"), "path": "other.toml",
                               "resume": True})
    assert client.request(sock, {"cmd": "resume"})["queued"] == 1
    notes.messages.clear()
    notes.wait_for("STATUS=running", timeout=60)
    proc.send_signal(signal.SIGTERM)  # finish the current frame, commit, pause, exit 0
    assert proc.wait(timeout=120) == 0
    with Catalogue(db) as cat:
        (run,) = cat.runs()
        summary = cat.run_summary(run["id"])
        assert run["state"] in ("paused", "done") and summary["running"] == 0  # nothing left half-done
    cli = subprocess.run([sys.executable, "-m", "psfd", "run", str(plan_path), "--resume", "--catalogue", str(db),
                          "--socket", str(sock), "--workers", "1"], capture_output=True, text=True, timeout=300)
    if run["state"] == "done":  # SIGTERM came after the last frame: nothing is left to resume
        assert cli.returncode == 2 and "no unfinished run" in cli.stderr, cli.stderr
    else:
        assert cli.returncode == 0, cli.stderr
    check_complete(db, db.with_name("cat-frames"), plan)


def test_status_of_a_resumed_run_counts_the_steps_done_before(served, tmp_path):
    """`status` of a run resumed through the service said "0/4 steps" as if it had started again: it counts
    the run's steps done before the pause, as `psfd run --resume` does (and so does systemd's STATUS line)."""
    proc, sock, db, notes = served
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(small_plan())
    client.submit(sock, small_plan(), str(plan_path))
    wait_status(sock, lambda s: s["current"] and s["current"]["done"] >= 1)
    client.request(sock, {"cmd": "pause"})
    wait_status(sock, lambda s: s["state"] == "paused")
    with Catalogue(db, readonly=True) as cat:
        (run,) = cat.runs()
        before = cat.run_summary(run["id"])["done"]
    if run["state"] == "done":
        pytest.skip("the pause came after the last step")
    notes.messages.clear()
    assert client.request(sock, {"cmd": "resume"})["queued"] == 1
    status = wait_status(sock, lambda s: s["current"] is not None or s["last"]["state"] != "paused", timeout=60)
    if status["current"] is not None:
        assert before >= 1 and status["current"]["done"] >= before and status["current"]["total"] == 4, status
    message = notes.wait_for("STATUS=running", timeout=60)
    assert int(message.split(": ", 1)[1].split("/", 1)[0]) >= before, message
    wait_status(sock, lambda s: s["current"] is None and s["last"]["state"] == "done", timeout=300)


def wait_until(ready, proc: subprocess.Popen, what: str, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise AssertionError(f"never {what} (service exit {proc.poll()})")
        time.sleep(0.01)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_to_the_whole_group_mid_estimate_commits_it_and_pauses(tmp_path, signum):
    """`systemctl stop` sends SIGTERM to every process of the unit (KillMode=control-group), the estimation
    workers too: the service still finishes the estimate in flight, commits it, pauses the run and exits 0,
    with no failed step and no traceback in its log. A hang-up (`psfd serve` started in an ssh session that
    dropped) does the same; before, it ended the service at once: the estimate lost, the run left
    interrupted, and the socket left behind, which every psfd command then took for a service restarting."""
    sock, db, log_path = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite", tmp_path / "serve.log"
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    (tmp_path / "hold").touch()  # the first estimate waits in its worker (tests/held_estimate.py)
    with open(log_path, "w") as log:
        proc = subprocess.Popen([sys.executable, str(ROOT / "tests" / "held_estimate.py"), "serve", "--socket",
                                 str(sock), "--catalogue", str(db), "--workers", "1"],
                                env={**os.environ, "PSFD_HOLD": str(tmp_path)}, stderr=log, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))  # not nohup
        try:
            wait_until(lambda: sock.exists() and client.service_up(sock), proc, "listening")
            client.request(sock, {"cmd": "submit", "plan": plan.text, "path": str(plan_path)})
            wait_until((tmp_path / "estimating").exists, proc, "estimating")
            os.killpg(proc.pid, signum)
            (tmp_path / "hold").unlink()
            assert proc.wait(timeout=120) == 0
        finally:
            end_group(proc)
    text = log_path.read_text()
    assert "Traceback" not in text and "failed" not in text, text
    assert f"{signal.Signals(signum).name}: stopping the service after the current frame" in text, text
    assert not sock.exists()
    with Catalogue(db) as cat:
        (run,) = cat.runs()
        states = {row["key"]: row["state"] for row in cat.steps(run["id"])}
    assert run["state"] == "paused" and states[plan.steps()[0].key] == "done", states  # the estimate in flight
    assert "failed" not in states.values() and "running" not in states.values(), states
    cli = subprocess.run([sys.executable, "-m", "psfd", "run", str(plan_path), "--resume", "--catalogue", str(db),
                          "--socket", str(sock), "--workers", "1"], capture_output=True, text=True, timeout=300)
    assert cli.returncode == 0, cli.stderr
    check_complete(db, db.with_name("cat-frames"), plan)


def test_cancel_closes_the_run(served, tmp_path):
    proc, sock, db, notes = served
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(small_plan())
    cli = subprocess.run([sys.executable, "-m", "psfd", "run", str(plan_path), "--socket", str(sock)],
                         capture_output=True, text=True, timeout=60)
    assert cli.returncode == 0 and "submitted" in cli.stdout  # `psfd run` hands the plan to the service
    assert f"follow it with: psfd status --socket {sock}" in cli.stdout
    wait_status(sock, lambda s: s["current"] is not None)
    client.request(sock, {"cmd": "cancel"})
    status = wait_status(sock, lambda s: s["last"] is not None)
    assert status["last"]["state"] == "cancelled" and status["state"] == "idle"
    with Catalogue(db) as cat:
        assert cat.runs()[0]["state"] == "cancelled" and cat.integrity_check() == []
    assert proc.poll() is None



def psfd_cli(*argv) -> subprocess.CompletedProcess:
    """The whole ``psfd ARGV...`` process."""
    return subprocess.run([sys.executable, "-m", "psfd", *map(str, argv)], capture_output=True, text=True,
                          timeout=300)


def test_pause_resume_and_cancel_from_the_command_line(served, tmp_path):
    """An operator had no command to pause the service's run (to get to the rig), to continue it or to cancel
    it: only JSON written to the control socket by hand. `psfd pause`, `resume` and `cancel` send them."""
    proc, sock, db, notes = served
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(small_plan())
    client.submit(sock, plan_path.read_text(), str(plan_path))
    wait_status(sock, lambda s: s["current"] and s["current"]["step"])
    paused = psfd_cli("pause", "--socket", sock)
    assert paused.returncode == 0, paused.stderr
    assert paused.stdout == (f"pause asked: the service at {sock} pauses its run after the current frame and holds "
                             f"its queue; continue with: psfd resume --socket {sock}\n")
    status = wait_status(sock, lambda s: s["current"] is None)
    if status["last"]["state"] == "done":
        pytest.skip("the pause came after the last step")
    assert status["state"] == "paused" and status["held"]
    resumed = psfd_cli("resume", "--socket", sock)
    assert resumed.returncode == 0, resumed.stderr
    assert resumed.stdout.startswith(f"resuming run {status['last']['run_id']} of {plan_path}"), resumed.stdout
    wait_status(sock, lambda s: s["current"] is not None or s["last"]["state"] == "done")
    cancelled = psfd_cli("cancel", "--socket", sock)
    status = wait_status(sock, lambda s: s["current"] is None)
    if status["last"]["state"] == "done":
        pytest.skip("the cancel came after the last step")
    assert cancelled.returncode == 0 and cancelled.stdout.startswith("cancel asked"), cancelled.stderr
    assert status["last"]["state"] == "cancelled"
    again = psfd_cli("cancel", "--socket", sock)
    assert (again.returncode, again.stderr) == (5, "psfd: error: no run is in progress or paused\n")


@pytest.mark.parametrize("word, hint", [("pause", "Ctrl-C"), ("cancel", "Ctrl-C"), ("resume", "--resume")])
def test_pause_resume_and_cancel_without_a_service_say_what_does_it(tmp_path, word, hint):
    sock = tmp_path / "none.sock"
    proc = psfd_cli(word, "--socket", sock)
    assert proc.returncode == 5 and proc.stdout == ""
    (line,) = proc.stderr.splitlines()
    assert line.startswith(f"psfd: error: no service at {sock}") and hint in line, line

def test_client_error_when_no_service(tmp_path):
    with pytest.raises(ServiceError, match="cannot reach the service"):
        client.request(tmp_path / "nothing.sock", {"cmd": "status"})
    assert not client.service_up(tmp_path / "nothing.sock")


def test_unit_file_verifies():
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed on this machine")
    psfd = shutil.which("psfd")
    if psfd is None:
        pytest.skip("the psfd console script is not on PATH (pip install -e .)")
    unit = (ROOT / "systemd" / "psfd.service").read_text()
    assert "Type=notify" in unit and "User=psfd" in unit and "DevicePolicy=closed" in unit
    assert "ExecStart=/opt/psfd/bin/psfd serve" in unit  # the virtual environment the README installs
    # verify checks that ExecStart exists: point it at this machine's console script
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"psfd-verify-{os.getpid()}"
    tmp.mkdir(exist_ok=True)
    (tmp / "psfd.service").write_text(unit.replace("/opt/psfd/bin/psfd", os.path.realpath(psfd)))
    out = subprocess.run(["systemd-analyze", "verify", str(tmp / "psfd.service")], capture_output=True, text=True)
    shutil.rmtree(tmp)
    assert out.returncode == 0, out.stderr
    assert "Unknown key" not in out.stderr and "Unknown section" not in out.stderr


def test_udev_rule_gives_the_psfd_group_camera_and_rail():
    rules = [line for line in (ROOT / "systemd" / "99-psfd.rules").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    assert any('SUBSYSTEM=="usb"' in r and 'GROUP="psfd"' in r and 'MODE="0660"' in r for r in rules)
    assert any('SUBSYSTEM=="tty"' in r and 'SYMLINK+="psfd-rail"' in r for r in rules)
    for rule in rules:  # every assignment key is one udev knows
        for part in (p.strip() for p in rule.split(", ")):
            key = part.split("=")[0].rstrip("+!:").split("{")[0]
            assert key in {"SUBSYSTEM", "ENV", "ATTRS", "ATTR", "GROUP", "MODE", "SYMLINK"}, part


def test_a_plan_submitted_twice_while_queued_is_measured_once(served, tmp_path):
    """Two plain submits of one plan while the service is busy with another both waited in the queue, and the
    service then measured every position of the plan twice (two runs): run locally, the second `psfd run` is
    refused while the first run is unfinished. The second submit is refused in one line, exit code 2, until
    the first has ended; `--new` still asks for another run on purpose."""
    proc, sock, db, notes = served
    busy, twice = tmp_path / "busy.toml", tmp_path / "twice.toml"
    busy.write_text(small_plan())
    twice.write_text(small_plan().replace("apertures = [4, 11]", "apertures = [8]"))
    client.submit(sock, busy.read_text(), str(busy))
    wait_status(sock, lambda s: s["current"] is not None)
    assert client.submit(sock, twice.read_text(), str(twice))["queued"] == 1
    again = subprocess.run([sys.executable, "-m", "psfd", "run", str(twice), "--socket", str(sock)],
                           capture_output=True, text=True, timeout=60)
    assert again.returncode == BadInputError.exit_code, again.stdout + again.stderr
    assert "already submitted" in again.stderr and len(again.stderr.strip().splitlines()) == 1, again.stderr
    assert client.submit(sock, twice.read_text(), str(twice), new=True)["queued"] == 2  # on purpose
    wait_status(sock, lambda s: s["current"] is None and s["queued"] == 0, timeout=300)
    with Catalogue(db, readonly=True) as cat:
        runs = [r for r in cat.runs() if r["plan_path"] == str(twice)]
    assert [r["state"] for r in runs] == ["done", "done"]  # the first submit and the --new one


# -- resume after a restart -----------------------------------------------------------------------------


def journal(db: Path, plan_text: str, path: str, state: str) -> int:
    """A run of the plan journalled with every step pending, left in ``state`` (``running``: as a kill leaves it)."""
    plan = parse_plan(plan_text, path)
    with Catalogue(db) as cat:
        rig = cat.add_rig(CameraInfo("psfd simulated camera", "SIM-0", "simulated 50 mm", 50.0))
        run = cat.start_run(path, plan.text, rig, [(step.key, step.payload()) for step in plan.steps()])
        if state != "running":
            cat.finish_run(run, state)
    return run


def test_resume_after_a_restart_continues_the_catalogues_paused_run(tmp_path):
    """`systemctl stop` pauses the run and ends the service; the service started again found no paused run
    (it kept the plan in memory) although the catalogue has it, its plan text and `status` listed it. Now
    `resume` continues it with its stored plan, says which run and plan, and status says paused meanwhile."""
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    sock, db, log_path = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite", tmp_path / "serve.log"
    argv = [sys.executable, "-m", "psfd", "serve", "--socket", str(sock), "--catalogue", str(db), "--workers", "1"]
    with open(log_path, "w") as log:
        proc = subprocess.Popen(argv, stderr=log, start_new_session=True)
        try:
            wait_until(lambda: sock.exists() and client.service_up(sock), proc, "listening")
            client.submit(sock, plan.text, str(plan_path))
            wait_status(sock, lambda s: s["current"] and s["current"]["step"])
            client.request(sock, {"cmd": "pause"})
            wait_status(sock, lambda s: s["state"] == "paused")
            proc.send_signal(signal.SIGTERM)  # systemctl stop
            assert proc.wait(timeout=60) == 0
            plan_path.unlink()  # the service needs its catalogue only, not the plan file
            proc = subprocess.Popen(argv, stderr=log, start_new_session=True)  # systemctl start
            wait_until(lambda: sock.exists() and client.service_up(sock), proc, "listening again")
            status = client.request(sock, {"cmd": "status"})
            assert (status["state"], status["paused_plan"]) == ("paused", str(plan_path)), status
            assert [r["id"] for r in status["unfinished"]] == [1]
            answer = client.request(sock, {"cmd": "resume"})
            assert (answer["run_id"], answer["plan"], answer["queued"]) == (1, str(plan_path), 1), answer
            status = wait_status(sock, lambda s: s["last"] is not None)
            assert status["last"]["state"] == "done" and status["last"]["run_id"] == 1, status
            assert (status["state"], status["paused_plan"], status["unfinished"]) == ("idle", None, [])
            with pytest.raises(ServiceError, match="no paused run to resume"):
                client.request(sock, {"cmd": "resume"})
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(timeout=60) == 0
        finally:
            end_group(proc)
    text = log_path.read_text()
    assert f"resume asked on the control socket: run 1 of {plan_path} (paused, " in text, text
    with Catalogue(db, readonly=True) as cat:
        assert [r["state"] for r in cat.runs()] == ["done"]  # run 1 went on: no second run
    check_complete(db, db.with_name("cat-frames"), plan)


def test_resume_takes_the_newest_unfinished_run_says_so_and_skips_a_live_one(tmp_path):
    """Several unfinished runs of different plans: `resume` continues the newest paused or interrupted one,
    names it and the others; a run that another process is shooting is never it; none left: the error."""
    db, frames = tmp_path / "cat.sqlite", tmp_path / "cat-frames"
    texts = {name: small_plan().replace("apertures = [4, 11]", f"apertures = [{a}]")
             for name, a in (("a.toml", 4), ("b.toml", 8), ("c.toml", 11))}
    first = journal(db, texts["a.toml"], "a.toml", "paused")
    second = journal(db, texts["b.toml"], "b.toml", "running")  # killed: interrupted
    service = Service(db, frames, tmp_path / "control.sock")

    def ask(cmd: str) -> dict:
        return service.handle_line(json.dumps({"cmd": cmd}).encode() + b"\n")

    status = ask("status")
    assert (status["state"], status["paused_plan"]) == ("paused", "b.toml"), status
    answer = ask("resume")
    assert answer["ok"] and (answer["run_id"], answer["plan"]) == (second, "b.toml"), answer
    assert f"run {first} of a.toml" in answer["note"] and "newest" in answer["note"], answer
    # the queued job is the stored plan, to be resumed (the runner thread is not started here)
    job = service.jobs.get_nowait()
    assert job.resume and job.plan.text == texts["b.toml"] and job.plan.path == "b.toml"
    service.waiting.clear()
    service.queued = 0

    with Catalogue(db) as cat:
        cat.finish_run(second, "done")
    live = journal(db, texts["c.toml"], "c.toml", "running")
    with store_lock(frames):  # run `live` is being shot by another process: not resumable from here
        status = ask("status")
        assert status["paused_plan"] == "a.toml" and live not in [r["id"] for r in status["unfinished"]]
        answer = ask("resume")
        assert answer["ok"] and (answer["run_id"], answer["plan"]) == (first, "a.toml"), answer
        assert "note" not in answer, answer
    service.jobs.get_nowait()
    service.waiting.clear()

    with Catalogue(db) as cat:
        cat.finish_run(first, "cancelled")
        cat.finish_run(live, "cancelled")
    assert ask("status")["state"] == "idle"
    answer = ask("resume")
    assert not answer["ok"] and answer["error"] == "no paused run to resume", answer


def test_cancel_with_no_run_in_progress_closes_only_a_paused_run_nobody_is_resuming(tmp_path):
    """`cancel` closes the run `resume` would continue, and only when it paused cleanly: an interrupted one
    (killed, maybe with frames stored and not committed) is refused, as is one queued to resume."""
    db, frames = tmp_path / "cat.sqlite", tmp_path / "cat-frames"
    texts = {name: small_plan().replace("apertures = [4, 11]", f"apertures = [{a}]")
             for name, a in (("a.toml", 4), ("b.toml", 8))}
    paused = journal(db, texts["a.toml"], "a.toml", "paused")
    service = Service(db, frames, tmp_path / "control.sock")

    def ask(cmd: str) -> dict:
        return service.handle_line(json.dumps({"cmd": cmd}).encode() + b"\n")

    assert ask("resume")["run_id"] == paused  # queued (the runner thread is not started here)
    answer = ask("cancel")
    assert not answer["ok"] and answer["error"] == f"run {paused} is queued to resume: cancel it once it runs"
    service.jobs.get_nowait()
    service.waiting.clear()
    service.queued = 0
    interrupted = journal(db, texts["b.toml"], "b.toml", "running")  # killed: the newest unfinished run
    answer = ask("cancel")
    assert not answer["ok"] and answer["error"].startswith(f"run {interrupted} of b.toml was interrupted"), answer
    with Catalogue(db) as cat:
        cat.finish_run(interrupted, "failed")
    answer = ask("cancel")
    assert answer["ok"] and (answer["run_id"], answer["plan"], answer["held"]) == (paused, "a.toml", False), answer
    with Catalogue(db, readonly=True) as cat:
        assert cat.run(paused)["state"] == "cancelled"
    answer = ask("cancel")
    assert not answer["ok"] and answer["error"] == "no run is in progress or paused", answer


def paused_with_one_queued(sock: Path, tmp_path: Path) -> tuple[Path, Path, dict]:
    """Plans ``first`` and ``second`` submitted to the service at ``sock``, and a pause asked once ``first``
    shoots (``second`` queued): the two plans and the status once ``first`` no longer runs."""
    first, second = tmp_path / "first.toml", tmp_path / "second.toml"
    first.write_text(small_plan())
    second.write_text(small_plan().replace("apertures = [4, 11]", "apertures = [8]"))
    client.submit(sock, first.read_text(), str(first))
    wait_status(sock, lambda s: s["current"] and s["current"]["step"])
    assert client.submit(sock, second.read_text(), str(second))["queued"] == 1
    assert client.request(sock, {"cmd": "pause"})["requested"] == "pause"
    status = wait_status(sock, lambda s: s["current"] is None or s["current"]["plan"] != str(first))
    return first, second, status


def test_a_pause_holds_the_queue_until_resume_which_continues_the_paused_run_first(served, tmp_path):
    """The service went straight on to the next queued plan when a pause stopped the run (the rail moving off
    to the next plan's first position while the operator, who had asked for the pause, had hands in the
    rig). A pause holds the queue: nothing starts until `resume`, which continues the paused run before the
    queued plan; status says the queue is held."""
    proc, sock, db, notes = served
    first, second, _ = paused_with_one_queued(sock, tmp_path)
    time.sleep(1.0)  # time for the runner to take the next job, were it not held
    status = client.request(sock, {"cmd": "status"})
    with Catalogue(db, readonly=True) as cat:
        runs = [(r["plan_path"], r["state"]) for r in sorted(cat.runs(), key=lambda r: r["id"])]
    if runs == [(str(first), "done")]:
        pytest.skip("the pause came after the last step")
    assert runs == [(str(first), "paused")], runs  # the second plan has not started: nothing moved
    assert (status["state"], status["current"], status["queued"], status["held"]) == ("paused", None, 1, True), status
    cli = subprocess.run([sys.executable, "-m", "psfd", "status", "--socket", str(sock)], capture_output=True,
                         text=True)
    assert "1 queued, held by a pause until `resume`" in cli.stdout, cli.stdout
    answer = client.request(sock, {"cmd": "resume"})
    assert answer["plan"] == str(first), answer
    wait_status(sock, lambda s: s["current"] is None and s["queued"] == 0 and not s["held"], timeout=300)
    with Catalogue(db, readonly=True) as cat:
        runs = [(r["plan_path"], r["state"]) for r in sorted(cat.runs(), key=lambda r: r["id"])]
    assert runs == [(str(first), "done"), (str(second), "done")], runs
    log = (tmp_path / "serve.log").read_text()
    assert log.index(f"starting {first} (resuming)") < log.index(f"starting {second}"), log


def test_cancel_of_the_paused_run_closes_it_and_lets_the_held_queue_go_on(served, tmp_path):
    """An operator who paused the run (hands in the rig) and then gave it up had no way to say so: `cancel`
    answered "no run is in progress", and the queue stayed held until `resume` (which shoots the run given up)
    or another submit. `cancel` now closes the paused run as cancelled and lets the queue go on."""
    proc, sock, db, notes = served
    first, second, status = paused_with_one_queued(sock, tmp_path)
    with Catalogue(db, readonly=True) as cat:
        (run,) = [r for r in cat.runs() if r["plan_path"] == str(first)]
    if run["state"] == "done":
        pytest.skip("the pause came after the last step")
    assert status["held"] and status["queued"] == 1, status
    cancelled = psfd_cli("cancel", "--socket", sock)
    assert cancelled.returncode == 0, cancelled.stderr
    assert cancelled.stdout.startswith(f"cancelled run {run['id']} of {first} (paused, "), cancelled.stdout
    assert "the held queue goes on" in cancelled.stdout, cancelled.stdout
    wait_status(sock, lambda s: s["current"] is None and s["queued"] == 0 and not s["held"], timeout=300)
    with Catalogue(db, readonly=True) as cat:
        runs = [(r["plan_path"], r["state"]) for r in sorted(cat.runs(), key=lambda r: r["id"])]
    assert runs == [(str(first), "cancelled"), (str(second), "done")], runs
    again = psfd_cli("cancel", "--socket", sock)
    assert (again.returncode, again.stderr) == (5, "psfd: error: no run is in progress or paused\n")
    assert proc.poll() is None


# -- a service killed hard leaves its socket behind ---------------------------------------------------------


def killed_service(sock: Path, db: Path, log) -> None:
    """A real `psfd serve` on ``sock``, up and answering, then SIGKILLed (the OOM killer, `kill -9`): it
    can neither remove its socket nor do anything else."""
    proc = subprocess.Popen([sys.executable, "-m", "psfd", "serve", "--socket", str(sock), "--catalogue", str(db),
                             "--workers", "1"], stderr=log, start_new_session=True)
    try:
        wait_until(lambda: sock.exists() and client.service_up(sock), proc, "listening")
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=60) == -signal.SIGKILL
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert stat.S_ISSOCK(os.lstat(sock).st_mode)  # left behind, as a power loss or the OOM killer leaves it


def test_commands_after_a_killed_service_go_on_without_it(tmp_path):
    """A service killed hard (SIGKILL, out of memory) leaves its socket; every later command took it for a
    service restarting, waited for it ('connection was refused for 5 s') and refused, until someone removed
    the socket by hand. The lock the service held beside it was released by the kernel: the command says in
    one line that it found and removed the socket of a service that ended, and goes on as with no service."""
    sock, db = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite"
    plan = tmp_path / "plan.toml"
    plan.write_text(one_channel_plan("simulate = true"))
    with open(tmp_path / "serve.log", "w") as log:
        killed_service(sock, db, log)
        status = psfd_cli("status", "--socket", sock, "--catalogue", db)
        assert status.returncode == 0, status.stderr
        assert status.stdout.startswith(f"no service at {sock}"), status.stdout
        assert "refused" not in status.stderr and len(status.stderr.splitlines()) == 1, status.stderr
        assert f"{sock}: the socket of a psfd serve that ended without removing it; removed" in status.stderr
        assert not sock.exists()
        killed_service(sock, db, log)
        run = psfd_cli("run", plan, "--socket", sock, "--catalogue", db, "--workers", "1")
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("run 1 done: 1 step, 1 frame, 1 PSF"), run.stdout  # here, not submitted
    assert "refused" not in run.stderr and "ended without removing it; removed" in run.stderr, run.stderr
    check_complete(db, db.with_name("cat-frames"), parse_plan(plan.read_text(), str(plan)))


def test_serve_over_the_socket_of_a_killed_service_comes_up(tmp_path):
    sock, db = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite"
    with open(tmp_path / "serve.log", "w") as log:
        killed_service(sock, db, log)
        proc = subprocess.Popen([sys.executable, "-m", "psfd", "serve", "--socket", str(sock), "--catalogue", str(db),
                                 "--workers", "1"], stderr=log, start_new_session=True)
        try:
            wait_until(lambda: sock.exists() and client.service_up(sock), proc, "listening over the stale socket")
            status = psfd_cli("status", "--socket", sock)
            assert status.returncode == 0 and status.stdout.startswith(f"service at {sock}: idle"), status
            assert status.stderr == ""
            second = psfd_cli("serve", "--socket", sock, "--catalogue", db)  # this one is alive: left alone
            assert second.returncode == ServiceError.exit_code, second.stderr
            assert second.stderr.endswith(f"psfd: error: a service is already listening on {sock}\n"), second.stderr
            assert client.service_up(sock) and proc.poll() is None
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(timeout=60) == 0
        finally:
            end_group(proc)
    assert not sock.exists()


def test_a_service_still_starting_is_waited_for_and_never_removed(tmp_path):
    """Between taking its lock and listening, a starting service's socket refuses connections: the commands
    wait for it and refuse as before (exit 5), and leave it in place; a second `psfd serve` leaves it too
    (it removed any socket that refused, the starting service's as well). Once the lock is free, it is the
    socket of a service that ended."""
    sock, db = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite"
    sock.parent.mkdir(mode=0o750)
    plan = tmp_path / "plan.toml"
    plan.write_text(one_channel_plan("simulate = true"))
    lock = hold_lock(sock)  # what `psfd serve` holds from before it binds until it has ended
    starting = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    starting.bind(str(sock))  # bound, not listening yet
    inode = os.lstat(sock).st_ino
    try:
        for argv in (["status"], ["run", plan, "--workers", "1"]):
            cli = psfd_cli(*argv, "--socket", sock, "--catalogue", db)
            assert cli.returncode == ServiceError.exit_code, cli.stdout + cli.stderr
            assert (f"the control socket {sock} exists but its connection was refused for 5 s while its service "
                    f"holds {sock}.lock: it is starting or stopping; try again") in cli.stderr, cli.stderr
            assert len(cli.stderr.splitlines()) == 1 and cli.stdout == "", cli.stderr
            assert os.lstat(sock).st_ino == inode and not db.exists()  # left in place, nothing run here
        second = psfd_cli("serve", "--socket", sock, "--catalogue", db)
        assert second.returncode == ServiceError.exit_code and len(second.stderr.splitlines()) == 1, second.stderr
        assert f"another psfd serve holds {sock}" in second.stderr, second.stderr
        assert os.lstat(sock).st_ino == inode
    finally:
        os.close(lock)  # the starting service died before it listened
        starting.close()
    status = psfd_cli("status", "--socket", sock, "--catalogue", db)
    assert status.returncode == 0 and "ended without removing it; removed" in status.stderr, status.stderr
    assert not sock.exists()


# -- the queue outlives the service ----------------------------------------------------------------------


def started_service(sock: Path, db: Path, log) -> subprocess.Popen:
    """A real `psfd serve` on ``sock`` and ``db``, in a session of its own, once it answers."""
    proc = subprocess.Popen([sys.executable, "-m", "psfd", "serve", "--socket", str(sock), "--catalogue", str(db),
                             "--workers", "1"], stderr=log, start_new_session=True)
    wait_until(lambda: sock.exists() and client.service_up(sock), proc, "listening")
    return proc


@pytest.mark.parametrize("how", ["stopped", "killed"])
def test_plans_queued_when_the_service_ends_are_queued_again_and_held_until_resume(tmp_path, how):
    """A service stopped (`systemctl restart`: SIGTERM) or killed (a power cut, the OOM killer: SIGKILL to its
    whole group) while plans waited in its queue forgot them: the run it was shooting could be resumed, the
    overnight list behind it was gone without a word. The queued plans are now kept beside the catalogue and
    queued again by the next service, held until `resume` (nothing moves the rail before an operator says so),
    which continues the stopped run first; each plan is measured once."""
    sock, db = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite"
    plans = [tmp_path / f"{name}.toml" for name in ("first", "second", "third")]
    for path, apertures in zip(plans, ("[4, 11]", "[8]", "[5.6]")):
        path.write_text(small_plan().replace("apertures = [4, 11]", f"apertures = {apertures}"))
    first, second, third = plans
    with open(tmp_path / "serve.log", "w") as log:
        proc = started_service(sock, db, log)
        try:
            client.submit(sock, first.read_text(), str(first))
            wait_status(sock, lambda s: s["current"] and s["current"]["step"])
            for path in (second, third):
                client.submit(sock, path.read_text(), str(path))
            kept = json.loads(queue_path(db).read_text())
            assert [(e["path"], e["resume"], e["new"]) for e in kept] == [(str(second), False, False),
                                                                          (str(third), False, False)], kept
            if how == "stopped":
                proc.send_signal(signal.SIGTERM)
                assert proc.wait(timeout=120) == 0
            else:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        finally:
            end_group(proc)
        shown = psfd_cli("status", "--socket", sock, "--catalogue", db)  # the operator finds the service down
        assert (f"2 plans queued when the service ended ({second}, {third}): `psfd serve` queues them again, "
                "held until `psfd resume`") in shown.stdout, shown.stdout
        proc = started_service(sock, db, log)
        try:
            time.sleep(1.0)  # time for the runner to take a job, were the queue not held
            status = client.request(sock, {"cmd": "status"})
            assert (status["current"], status["queued"], status["held"], status["held_by"]) == (
                None, 2, True, "restart"), status
            with Catalogue(db, readonly=True) as cat:
                assert [r["plan_path"] for r in cat.runs()] == [str(first)]  # nothing else started
            shown = psfd_cli("status", "--socket", sock)
            assert "2 queued, held by the service's restart until `resume`" in shown.stdout, shown.stdout
            resumed = client.request(sock, {"cmd": "resume"})
            wait_status(sock, lambda s: s["current"] is None and s["queued"] == 0 and not s["held"], timeout=300)
        finally:
            end_group(proc)
    with Catalogue(db, readonly=True) as cat:
        runs = [(r["plan_path"], r["state"]) for r in sorted(cat.runs(), key=lambda r: r["id"])]
    assert runs == [(str(first), "done"), (str(second), "done"), (str(third), "done")], runs
    frames = db.with_name("cat-frames")
    for path in plans:
        check_complete_run(db, parse_plan(path.read_text(), str(path)))
    with Catalogue(db, readonly=True) as cat:
        assert stored_files(frames) == cat.frame_hashes()  # no frame lost or left over by the kill
    assert not queue_path(db).exists()  # all started: nothing kept
    text = (tmp_path / "serve.log").read_text()
    assert f"2 plans queued before the service stopped are queued again ({second}, {third})" in text, text
    if "plan" in resumed:  # the stop left the first run unfinished: `resume` continued it before the queue
        assert resumed["plan"] == str(first), resumed
        assert text.index(f"starting {first} (resuming)") < text.index(f"starting {second}"), text


def check_complete_run(db: Path, plan) -> None:
    """Every step of ``plan`` done once with its PSF (the catalogue holds other plans' PSFs too)."""
    with Catalogue(db, readonly=True) as cat:
        assert cat.integrity_check() == []
        run_ids = [r["id"] for r in cat.runs() if r["plan_path"] == plan.path]
        steps = sorted(r["step"] for r in cat.query().rows if r["run_id"] in run_ids)
    assert steps == sorted(step.key for step in plan.steps())


def test_a_queue_file_that_cannot_be_read_is_set_aside_and_the_service_starts(tmp_path):
    """A kept queue damaged (a disk error, an edit by hand) must not keep the service down: it starts with an
    empty queue, says so in its log and sets the file aside for the operator."""
    sock, db = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite"
    queue_path(db).write_text('[{"plan": "[rig]\n", "path": "cut.toml"')  # cut short
    with open(tmp_path / "serve.log", "w") as log:
        proc = started_service(sock, db, log)
        try:
            status = client.request(sock, {"cmd": "status"})
            assert (status["queued"], status["held"], status["held_by"]) == (0, False, None), status
        finally:
            end_group(proc)
    aside = queue_path(db).with_name(queue_path(db).name + ".unreadable")
    assert aside.read_text().startswith('[{"plan"') and not queue_path(db).exists()
    assert f"the queue kept in {queue_path(db)} cannot be read" in (tmp_path / "serve.log").read_text()


def test_cancel_queued_drops_the_kept_plans_and_nothing_moves(tmp_path):
    """A stop no longer forgets the queue, so dropping plans queued by mistake needs a word of its own:
    `psfd cancel --queued` drops every plan queued and not started (here two kept by a service before this
    one, held), and none of them ever starts."""
    sock, db = tmp_path / "run" / "control.sock", tmp_path / "cat.sqlite"
    plans = [tmp_path / "a.toml", tmp_path / "b.toml"]
    for path, apertures in zip(plans, ("[8]", "[5.6]")):
        path.write_text(small_plan().replace("apertures = [4, 11]", f"apertures = {apertures}"))
    queue_path(db).write_text(json.dumps([{"plan": p.read_text(), "path": str(p), "resume": False, "new": False}
                                          for p in plans]))
    with open(tmp_path / "serve.log", "w") as log:
        proc = started_service(sock, db, log)
        try:
            status = client.request(sock, {"cmd": "status"})
            assert (status["queued"], status["held"], status["held_by"]) == (2, True, "restart"), status
            dropped = psfd_cli("cancel", "--queued", "--socket", sock)
            assert (dropped.returncode, dropped.stdout) == (0, f"dropped 2 queued plans: {plans[0]}, {plans[1]}\n")
            time.sleep(1.0)  # time for the runner to start a dropped plan, were it not skipped
            status = client.request(sock, {"cmd": "status"})
            assert (status["current"], status["queued"], status["held"]) == (None, 0, False), status
            again = psfd_cli("cancel", "--queued", "--socket", sock)
            assert (again.returncode, again.stderr) == (5, "psfd: error: no plan is queued\n")
        finally:
            end_group(proc)
    assert not queue_path(db).exists()
    with Catalogue(db, readonly=True) as cat:
        assert cat.runs() == []
