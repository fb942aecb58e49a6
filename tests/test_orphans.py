"""No orphaned process after ``streetcd run`` is killed (issue 19, item 5): a real run on the
small city, with its own temporary Prefect server (uvicorn) and a LocalCluster, killed once
all of them are up; nothing of its process tree may be left (streetcd.run.supervise)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from streetcd.run.supervise import run_supervised

# A Dask worker (or the LocalCluster's resource tracker) is a multiprocessing child.
SPAWNED = "multiprocessing.spawn"
# The command's exit code when killed by each signal: SIGKILL leaves the supervisor no say;
# the others reach the night, whose code (as a shell reports a death by signal N: 128 + N,
# 130 for Ctrl-C's "Aborted!") comes back unchanged, or 137 where the night took longer
# than supervise.GRACE_S to stop (a busy machine) and its group was killed.
EXPECTED_CODE = {signal.SIGKILL: -signal.SIGKILL, signal.SIGTERM: 143, signal.SIGINT: 130}


def _cmdline(proc: psutil.Process) -> str:
    try:
        return " ".join(proc.cmdline())
    except psutil.Error:  # gone meanwhile
        return ""


def _tree_when_up(proc: subprocess.Popen[bytes], log: Path) -> list[psutil.Process]:
    """The run's descendants once its Prefect server and a Dask worker both run."""
    deadline = time.monotonic() + 240
    while proc.poll() is None and time.monotonic() < deadline:
        tree = psutil.Process(proc.pid).children(recursive=True)
        lines = [_cmdline(p) for p in tree]
        if any("uvicorn" in c for c in lines) and sum(SPAWNED in c for c in lines) >= 2:
            return tree
        time.sleep(0.2)
    raise AssertionError(f"the run ended or took too long: {log.read_text()[-3000:]}")


def _gone(pid: int, timeout: float) -> bool:
    """Whether process ``pid`` is gone within ``timeout`` seconds."""
    try:
        _, alive = psutil.wait_procs([psutil.Process(pid)], timeout=timeout)
    except psutil.NoSuchProcess:
        return True
    return not alive


def _pgid(proc: psutil.Process) -> int | None:
    try:
        return os.getpgid(proc.pid)
    except ProcessLookupError:  # a short-lived process, gone meanwhile
        return None


@pytest.mark.slow  # ~30 s: the run starts its own Prefect server
@pytest.mark.parametrize("how", list(EXPECTED_CODE), ids=lambda s: s.name)
def test_a_killed_run_leaves_no_process_behind(small_city, tmp_path, how):
    cmd = [sys.executable, "-m", "streetcd.cli.main", "run", "--images", str(small_city.images)]
    cmd += ["--poses", str(small_city.poses), "--store", str(small_city.store)]
    cmd += ["--out", str(tmp_path / "out"), "--workers", "2", "--batch-size", "1"]
    # No PREFECT_API_URL: the run starts its own temporary server, as cron's would.
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env["PREFECT_HOME"] = str(tmp_path / "prefect-home")
    log = tmp_path / "run.log"
    tree: list[psutil.Process] = []
    with open(log, "wb") as fh:
        # A session of its own: the test's cleanup below can kill everything if it fails.
        proc = subprocess.Popen(
            cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
    try:
        tree = _tree_when_up(proc, log)
        # The night runs in a child with a group of its own that holds everything it starts
        # (neither uvicorn nor Dask's processes call setsid).
        night = psutil.Process(proc.pid).children()[0]
        assert {_pgid(p) for p in tree} - {None} == {night.pid}, [_cmdline(p) for p in tree]
        t0 = time.monotonic()
        os.kill(proc.pid, how)
        code = proc.wait(timeout=30)
        _, alive = psutil.wait_procs(tree, timeout=10)
        assert not alive, [_cmdline(p) for p in alive]
        took = time.monotonic() - t0
        print(f"{how.name}: {len(tree)} processes gone in {took:.1f} s, exit code {code}")
        assert code in {EXPECTED_CODE[how], 128 + signal.SIGKILL}, log.read_text()[-3000:]
    finally:  # whatever the outcome, leave nothing running
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        for p in tree:
            with contextlib.suppress(psutil.Error):
                p.kill()
        proc.wait(timeout=30)


def test_the_supervisor_returns_the_childs_code_and_output(tmp_path, capfd):
    # A child that prints, exits 3, and leaves a grandchild behind in its group: the code
    # comes back unchanged, the grandchild is killed.
    pidfile = tmp_path / "grandchild.pid"
    child = (
        "import subprocess, sys\n"
        "from streetcd.run.supervise import watch_supervisor\n"
        "watch_supervisor()\n"
        "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        f"open({str(pidfile)!r}, 'w').write(str(p.pid))\n"
        "print('night done'); sys.stderr.write('Error: one line\\n'); sys.exit(3)\n"
    )
    assert run_supervised([sys.executable, "-c", child]) == 3
    out, err = capfd.readouterr()
    assert out == "night done\n" and err == "Error: one line\n"
    assert _gone(int(pidfile.read_text()), timeout=5)


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM], ids=lambda s: s.name)
def test_a_supervised_child_dies_with_its_supervisor(tmp_path, how):
    # The supervisor (a process of its own here) SIGKILLed: the child's watchdog kills its
    # group, a sleeping grandchild included, at once. SIGTERMed: the child gets it, and the
    # supervisor kills what is left of the group and exits 128 + 15.
    pidfile = tmp_path / "pids"
    child = (
        "import subprocess, sys, time\n"
        "from streetcd.run.supervise import watch_supervisor\n"
        "watch_supervisor()\n"
        "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        "import os\n"
        f"open({str(pidfile)!r}, 'w').write(f'{{os.getpid()}} {{p.pid}}')\n"
        "time.sleep(60)\n"
    )
    supervisor = (
        "import sys\nfrom streetcd.run.supervise import run_supervised\n"
        f"sys.exit(run_supervised([sys.executable, '-c', {child!r}]))\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", supervisor], start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        while not (pidfile.exists() and len(pidfile.read_text().split()) == 2):
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.05)
        procs = [psutil.Process(int(pid)) for pid in pidfile.read_text().split()]
        proc.send_signal(how)
        assert proc.wait(timeout=10) == (-how if how == signal.SIGKILL else 128 + how)
        t0 = time.monotonic()
        _, alive = psutil.wait_procs(procs, timeout=5)
        assert not alive
        assert time.monotonic() - t0 < 2.0  # a pipe's EOF, not a poll
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
