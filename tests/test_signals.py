"""Ctrl-C, SIGTERM and SIGKILL at chosen moments of real commands, and waits for locks.

Each case runs ``python -m endomeasure ...`` as a process of its own (in a new process
group, as a terminal's foreground job would be), waits for a moment that the process
itself shows through ``/proc`` (cv2 loaded: it reads images; its lock file open: it
edits; its pool workers busy; its CPU time: it calibrates), sends the signal, and checks
the contract (``docs/robustness.md``): exit 130 for SIGINT and 143 for SIGTERM, exactly
one line on stderr and no traceback, the session as it was or with all of the command's
changes, no temporary file beside it, and no process of the group left alive.

Linux only (``/proc``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from tests.processes import alive_in_group, children, cpu_seconds, proc_stat

from endomeasure import interrupts
from endomeasure.io.outputs import SESSION_TMP_SUFFIX
from endomeasure.io.session import open_session

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_sessions" / "calib"
BOARD = "chessboard:8x6:0.5"
"""The board of the first twelve sample calibration images (calib_000 ... calib_011)."""
N_IMAGES = 24
N_BOARD_IMAGES = 8
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src")}  # this checkout, not an installed one
MOMENT_TIMEOUT_S = 60.0
"""Longest wait for a moment to come (a loaded machine is slow, never this slow)."""
GROUP_GONE_S = 5.0
"""How long the processes of an interrupted command may take to be gone (they take ms)."""
CALIBRATING_CPU_S = 1.5
"""CPU time after which ``calibrate`` is fitting (its imports and reads take well under)."""


# ------------------------------------------------------------------------- the world


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Folders of sample images and a session with detections (for calibrate)."""
    root = tmp_path_factory.mktemp("signals")
    images, board_images = root / "images", root / "board"
    images.mkdir()
    board_images.mkdir()
    for i in range(N_IMAGES):
        shutil.copyfile(SAMPLES / f"calib_{i:03d}.png", images / f"calib_{i:03d}.png")
    for i in range(N_BOARD_IMAGES):
        shutil.copyfile(SAMPLES / f"calib_{i:03d}.png", board_images / f"calib_{i:03d}.png")
    detected = root / "detected.h5"
    done = _run("detect", str(detected), str(board_images), "--board", BOARD, "--workers", "2")
    assert done.returncode == 0, done.stderr
    return {"root": root, "images": images, "board_images": board_images, "detected": detected}


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "endomeasure", *args],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=300,
    )


def _start(*args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "endomeasure", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
        start_new_session=True,  # its own process group: the pid is the group id
        **kwargs,
    )


# ------------------------------------------------------------------- what /proc shows


def _open_files(pid: int) -> list[str]:
    out = []
    try:
        entries = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return out
    for fd in entries:
        try:
            out.append(os.readlink(f"/proc/{pid}/fd/{fd}"))
        except OSError:
            pass
    return out


def _has_loaded(pid: int, library: str) -> bool:
    try:
        return library in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


def _wait_for(proc: subprocess.Popen, moment, what: str) -> None:
    """Poll until ``moment()`` is true; fail if the command ends first."""
    deadline = time.monotonic() + MOMENT_TIMEOUT_S
    while not moment():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"the command ended (exit {proc.returncode}) before {what}: {err}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"no moment {what} within {MOMENT_TIMEOUT_S} s")
        time.sleep(0.002)


# ------------------------------------------------------------------------ the contract


def _sha(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else None


def _temp_files(session: Path) -> list[str]:
    return sorted(
        p.name
        for p in session.parent.iterdir()
        if p.name.startswith(f".{session.name}.") and p.name.endswith(SESSION_TMP_SUFFIX)
    )


def _wait_group_gone(pgid: int) -> list[int]:
    deadline = time.monotonic() + GROUP_GONE_S
    while (alive := alive_in_group(pgid)) and time.monotonic() < deadline:
        time.sleep(0.02)
    return alive


def check_interrupted(proc, signum, session: Path, before: str | None, is_new) -> str:
    """The contract after a signal: returns 'old' or 'new' (the session's state)."""
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, (proc.returncode, err)
    lines = err.splitlines()
    assert len(lines) == 1, err
    name = signal.Signals(signum).name
    assert lines[0].startswith(f"error: interrupted by {name}"), err
    assert "Traceback" not in err and "bug" not in err
    assert out == "", out
    assert _wait_group_gone(proc.pid) == []
    assert _temp_files(session) == []
    if _sha(session) == before:
        return "old"
    assert is_new(session), "the session is neither the old one nor the new one"
    return "new"


def _image_names(session: Path) -> set[str]:
    with open_session(session) as s:
        return set(s.image_names())


# ------------------------------------------------------------ the interrupts module


def _raise_soon(signum=signal.SIGINT) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(0.5)  # the handler runs here (the sleep is cut short)


def test_deferred_holds_the_signal_back_until_the_step_is_done():
    steps = []
    with interrupts.handling():
        interrupts.arm()
        with pytest.raises(interrupts.Interrupted) as caught:
            with interrupts.deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
                steps.append("done")
    assert steps == ["done"]
    assert caught.value.exit_code == 143


def test_an_interrupt_that_code_swallowed_stops_the_next_write():
    with interrupts.handling():
        interrupts.arm()
        try:
            _raise_soon()
        except BaseException:  # what a careless library does
            pass
        with pytest.raises(interrupts.Interrupted):
            with interrupts.deferred():
                pytest.fail("the write went ahead after an interrupt")
        assert interrupts.received().exit_code == 130


class _RaisesInItsDestructor:
    def __del__(self):
        _raise_soon()  # Python drops it: "Exception ignored in ..."


def test_an_interrupt_python_had_to_drop_is_raised_again():
    with interrupts.handling():
        interrupts.arm()
        with pytest.raises(interrupts.Interrupted):
            item = _RaisesInItsDestructor()
            del item
            time.sleep(2.0)  # raised again within milliseconds
            pytest.fail("the interrupt was lost in the destructor")


def test_an_interrupt_is_not_raised_inside_h5py_but_right_after_it_returns():
    # a stand-in for h5py's Python code that HDF5 calls back (its module name is what counts)
    library = {"__name__": "h5py._conv_stand_in"}
    exec(
        textwrap.dedent(
            """
            def convert(signal_now):
                signal_now()
                total = 0
                for i in range(200_000):  # the handler runs between these bytecodes
                    total += i
                return total
            """
        ),
        library,
    )
    with interrupts.handling():
        interrupts.arm()
        returned = []
        with pytest.raises(interrupts.Interrupted) as caught:
            returned.append(library["convert"](lambda: os.kill(os.getpid(), signal.SIGTERM)))
            time.sleep(2.0)  # raised again within milliseconds
            pytest.fail("the interrupt held back in h5py was lost")
        assert returned == [sum(range(200_000))]  # h5py's code ran to its end
        assert caught.value.signum == signal.SIGTERM


def test_only_the_first_signal_raises_and_a_decided_outcome_ignores_them():
    with interrupts.handling():
        interrupts.arm()
        with pytest.raises(interrupts.Interrupted) as first:
            _raise_soon(signal.SIGINT)
        _raise_soon(signal.SIGTERM)  # ignored: the first one's clean-up runs
        assert first.value.signum == signal.SIGINT
    with interrupts.handling():
        interrupts.arm()
        interrupts.disarm()
        _raise_soon(signal.SIGINT)  # only remembered
        assert interrupts.received().signum == signal.SIGINT


# ------------------------------------------------------------------------- add-images


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_add_images_reads_leaves_no_session(world, tmp_path, signum):
    session = tmp_path / "new.h5"
    proc = _start("add-images", str(session), str(world["images"]))
    _wait_for(proc, lambda: _has_loaded(proc.pid, "cv2"), "it reads images")
    os.killpg(proc.pid, signum)
    expected = {f"calib_{i:03d}" for i in range(N_IMAGES)}
    state = check_interrupted(proc, signum, session, None, lambda s: _image_names(s) == expected)
    assert state == "old"  # a new session is only written after every image was read
    assert not session.exists()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_add_images_edits_gives_the_old_or_the_new_session(world, tmp_path, signum):
    session = tmp_path / "s.h5"
    first = tmp_path / "first"
    first.mkdir()
    shutil.copyfile(world["images"] / "calib_000.png", first / "calib_000.png")
    assert _run("add-images", str(session), str(first)).returncode == 0
    before = _sha(session)
    lock = str(session) + ".lock"
    proc = _start("add-images", str(session), str(world["images"]))
    _wait_for(proc, lambda: lock in _open_files(proc.pid), "it holds the session's lock")
    os.killpg(proc.pid, signum)
    expected = {f"calib_{i:03d}" for i in range(N_IMAGES)}
    state = check_interrupted(proc, signum, session, before, lambda s: _image_names(s) == expected)
    if state == "old":
        assert _image_names(session) == {"calib_000"}


# ----------------------------------------------------------------------------- detect


def _workers_busy(pid: int) -> bool:
    workers = children(pid)
    return len(workers) >= 2 and all(cpu_seconds(w) > 0.2 for w in workers)


def _detected(session: Path) -> bool:
    with open_session(session) as s:
        return len(s.image_names()) == N_BOARD_IMAGES and bool(s.detections())


@pytest.mark.parametrize(
    ("signum", "to_group"),
    [(signal.SIGINT, True), (signal.SIGTERM, True), (signal.SIGTERM, False)],
    ids=["ctrl-c", "sigterm-group", "sigterm-parent-only"],
)
def test_a_signal_while_detect_works_ends_its_workers(world, tmp_path, signum, to_group):
    session = tmp_path / "d.h5"
    proc = _start(
        "detect", str(session), str(world["board_images"]), "--board", BOARD, "--workers", "2"
    )
    _wait_for(proc, lambda: _workers_busy(proc.pid), "its workers detect")
    workers = children(proc.pid)
    started = time.monotonic()
    if to_group:
        os.killpg(proc.pid, signum)
    else:
        os.kill(proc.pid, signum)
    assert check_interrupted(proc, signum, session, None, _detected) == "old"
    assert time.monotonic() - started < GROUP_GONE_S  # not after the running tasks
    assert [w for w in workers if proc_stat(w) is not None and proc_stat(w)[0] != "Z"] == []


def test_workers_die_when_detect_is_killed(world, tmp_path):
    session = tmp_path / "d.h5"
    proc = _start(
        "detect", str(session), str(world["board_images"]), "--board", BOARD, "--workers", "2"
    )
    _wait_for(proc, lambda: _workers_busy(proc.pid), "its workers detect")
    proc.kill()  # SIGKILL: no handler runs, the kernel ends the workers (PR_SET_PDEATHSIG)
    proc.communicate(timeout=60)
    assert _wait_group_gone(proc.pid) == []
    assert not session.exists()


# -------------------------------------------------------------------------- calibrate


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_calibrate_fits_leaves_the_session(world, tmp_path, signum):
    session = tmp_path / "c.h5"
    shutil.copyfile(world["detected"], session)
    before = _sha(session)
    proc = _start("calibrate", str(session))
    _wait_for(proc, lambda: cpu_seconds(proc.pid) > CALIBRATING_CPU_S, "it fits")
    os.killpg(proc.pid, signum)
    assert check_interrupted(proc, signum, session, before, lambda s: False) == "old"


def test_a_second_signal_does_not_cut_the_clean_up_short(world, tmp_path):
    session = tmp_path / "d.h5"
    proc = _start(
        "detect", str(session), str(world["board_images"]), "--board", BOARD, "--workers", "2"
    )
    _wait_for(proc, lambda: _workers_busy(proc.pid), "its workers detect")
    os.killpg(proc.pid, signal.SIGINT)
    time.sleep(0.005)
    os.killpg(proc.pid, signal.SIGTERM)  # the impatient user: ignored, the first one wins
    assert check_interrupted(proc, signal.SIGINT, session, None, _detected) == "old"


# ------------------------------------------------------------------------------ locks

HOLDER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from endomeasure.io._lock import SessionLock

    with SessionLock(Path(sys.argv[1]), exclusive=True):
        print("held", flush=True)
        sys.stdin.read()  # until the test closes its stdin
    """
)


@pytest.fixture
def held_session(world, tmp_path):
    """A session whose exclusive lock another process holds until ``release()``."""
    session = tmp_path / "s.h5"
    first = tmp_path / "first"
    first.mkdir()
    shutil.copyfile(world["images"] / "calib_000.png", first / "calib_000.png")
    assert _run("add-images", str(session), str(first)).returncode == 0
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(session)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    assert holder.stdout.readline() == "held\n"

    def release() -> None:
        if holder.poll() is None:
            holder.stdin.close()
            holder.wait(timeout=30)

    yield session, holder, release
    release()


def test_a_writer_that_cannot_wait_names_the_holder(world, held_session):
    session, holder, _ = held_session
    before = _sha(session)
    started = time.monotonic()
    done = _run("add-images", str(session), str(world["board_images"]), "--wait", "0.5")
    waited = time.monotonic() - started
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("error: the session is locked by another endomeasure command")
    assert f"(PID {holder.pid} since " in lines[0]
    assert "--wait SECONDS" in lines[0]
    assert waited < 0.5 + 10.0  # the 0.5 s bound plus the start-up of a loaded machine
    assert _sha(session) == before


def test_a_waiting_writer_says_so_once_and_goes_on_when_the_lock_is_released(world, held_session):
    session, holder, release = held_session
    proc = subprocess.Popen(
        [sys.executable, "-m", "endomeasure", "add-images", str(session),
         str(world["board_images"]), "--wait", "60", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    note = proc.stderr.readline()  # after the grace of a second
    assert note.startswith(f"note: waiting for the lock on {session.name} held by PID {holder.pid}")
    assert "up to 60 s" in note
    release()
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert err == ""  # said once
    assert json.loads(out)["added"] == [f"calib_{i:03d}" for i in range(1, N_BOARD_IMAGES)]


def test_wait_zero_does_not_wait_and_a_negative_wait_is_refused(world, held_session):
    session, holder, _ = held_session
    done = _run("calibrate", str(session), "--wait", "0")
    assert done.returncode == 2 and f"PID {holder.pid}" in done.stderr
    assert "waited" not in done.stderr
    refused = _run("calibrate", str(session), "--wait", "-1")
    assert refused.returncode == 2
    assert refused.stderr.splitlines() == ["error: --wait must be 0 or more seconds, not -1.0"]


def _as_unprivileged_root(*args: str) -> subprocess.CompletedProcess:
    """The command as root without the capabilities that bypass file permissions (so
    another user's files are as closed to it as to any user)."""
    return subprocess.run(
        ["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--",
         sys.executable, "-m", "endomeasure", *args],
        capture_output=True, text=True, env=ENV, timeout=120,
    )  # fmt: skip


@pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("setpriv") is None, reason="needs root and setpriv"
)
def test_a_lock_file_of_another_user_is_used_or_named_with_its_permissions(world, tmp_path):
    session = tmp_path / "s.h5"
    first, rest = tmp_path / "first", tmp_path / "rest"
    first.mkdir()
    rest.mkdir()
    shutil.copyfile(world["images"] / "calib_000.png", first / "calib_000.png")
    shutil.copyfile(world["images"] / "calib_001.png", rest / "calib_001.png")
    assert _run("add-images", str(session), str(first)).returncode == 0
    lock = Path(str(session) + ".lock")
    os.chown(lock, 65534, 65534)  # another user's (nobody)
    lock.chmod(0o644)  # readable: the lock works without writing the holder's pid
    done = _as_unprivileged_root("add-images", str(session), str(rest))
    assert done.returncode == 0, done.stderr
    assert _image_names(session) == {"calib_000", "calib_001"}
    lock.chmod(0o600)  # not even readable
    before = _sha(session)
    done = _as_unprivileged_root("add-images", str(session), str(world["images"]))
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("error: cannot open the session's lock file (Permission denied;")
    assert "owner nobody, mode 0600" in lines[0] and f"[{lock}]" in lines[0]
    assert "let your user read and write it" in lines[0]
    assert _sha(session) == before
