"""The infra starts: the commands that ``infra/docker-compose.yml`` and the dask Helm chart with
``infra/helm/dask-values.yaml`` run, run here without containers, as the image runs them.

Every command goes through the image's entrypoint (``infra/entrypoint.sh``) with the venv's
``bin`` first on ``PATH`` (the image's ``pip install``), the Dockerfile's environment (numba's
cache folder, filled by the Dockerfile's warm-up, and ``infra/dask.yaml`` as Dask config) and
the compose file's environment. Only host names and ports are changed (free local ports):
a real ``prefect server start``, ``dask scheduler`` with a compose worker and a Helm worker,
the Helm scheduler (started and stopped), and ``infra/flow-worker.sh`` (``prefect deploy`` of
``infra/prefect.yaml``, then ``prefect worker start``). The deployment is then run on a small
synthetic city, its LAZ files as the archive to ingest, until the index is written, and its
nightly schedule must have made the next runs. At the end every process started, and
everything they started, is gone.

numba's cache: the image's build step (``infra/warm-numba.sh``) compiles the kernels into a
folder that is then copied to the workers' (the image shipped). In the default test that
folder is kept between test sessions in pytest's cache (``.pytest_cache``), written only by
the warm-up script, so the script runs every time but compiles only kernels whose source
changed (numba checks each file's stamp); the workers still get nothing but what the script
left. The slow variant starts from an empty folder: the warm-up compiles everything, as a
fresh image build does (~1 min of a core alone).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from contextlib import ExitStack, closing, contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from zoneinfo import ZoneInfo

import psutil
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
INFRA = ROOT / "infra"
VENV_BIN = Path(sys.executable).parent
ENTRYPOINT = str(INFRA / "entrypoint.sh")
# The Prefect worker asks for runs every 10 s by default, a wait only; the command is the file's.
FAST_POLLS = {"PREFECT_WORKER_QUERY_SECONDS": "1"}
# issue 19: a fresh worker's first view, numba cache shipped. CPU seconds of the worker
# process (the views' cpu_s): compiling would cost ~30 s of it, and, unlike wall time, it does
# not grow when other jobs share the cores.
FIRST_VIEW_MAX_S = 3.0


def free_ports(n: int) -> list[int]:
    """``n`` different TCP ports free on 127.0.0.1 now. All are held open until all are
    chosen: one at a time, the system may hand out the same port twice, and a Prefect server
    given the Dask dashboard's port never answers its health check (the likeliest cause of a
    fresh-clone failure on 2026-11-27, "no answer in 180 s"; its server log was not kept,
    which :func:`wait_http` now prints)."""
    with ExitStack() as stack:
        socks = [stack.enter_context(socket.socket()) for _ in range(n)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]


def compose_command(compose: dict, service: str) -> list[str]:
    """A compose service's ``command`` as the argv the entrypoint gets."""
    command = compose["services"][service]["command"]
    return list(command) if isinstance(command, list) else shlex.split(command)


def helm_scheduler_args(values: dict) -> list[str]:
    """The scheduler's args as the dask chart's template writes them (fixed there, only the
    port comes from the values)."""
    port = values["scheduler"]["servicePort"]
    return ["dask-scheduler", f"--port={port}", "--dashboard-address=:8787"]


def helm_worker_args(values: dict, scheduler: str) -> list[str]:
    """The worker's args as the dask chart's template builds them from the values."""
    worker = values["worker"]
    return [
        worker["image"]["dask_worker"],
        scheduler,
        "--nthreads",
        str(worker["threads_per_worker"]),
        "--memory-limit",
        str(worker["resources"]["limits"]["memory"]),
        "--no-dashboard",
        "--dashboard-address",
        "8790",
        *[str(a) for a in worker.get("extraArgs", [])],
    ]


def local(argv: list[str], ports: dict[str, int]) -> list[str]:
    """``argv`` with the containers' addresses and ports replaced by free local ones:
    ``ports`` maps the original port ("8786") to the local one."""
    out = []
    for arg in argv:
        arg = re.sub(r"\b0\.0\.0\.0\b", "127.0.0.1", arg)
        arg = re.sub(r"\b[\w.-]*(dask-scheduler|prefect-server)(?=:\d)", "127.0.0.1", arg)
        for old, new in ports.items():
            arg = re.sub(rf"(?<![\d.]){old}\b", str(new), arg)
        out.append(arg)
    return out


@dataclass
class Started:
    """Processes started for the test, each in its own session, with their logs."""

    root: Path
    env: dict[str, str]
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, name: str, argv: list[str], **env: str) -> subprocess.Popen:
        log = open(self.root / f"{name}.log", "wb")  # the child keeps its own copy
        proc = subprocess.Popen(
            argv,
            cwd=ROOT,  # the image's WORKDIR holds the same tree
            env={**self.env, **env},
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        self.procs[name] = proc
        return proc

    def log(self, name: str) -> str:
        return (self.root / f"{name}.log").read_text(errors="replace")

    def wait_for(self, name: str, text: str, timeout: float) -> None:
        """Until ``text`` is in the process's log; fails with the log's tail if it ends first."""
        end = time.monotonic() + timeout
        while text not in self.log(name):
            code = self.procs[name].poll()
            assert code is None, f"{name} ended ({code}):\n{self.log(name)[-3000:]}"
            assert time.monotonic() < end, (
                f"{name}: no {text!r} in {timeout} s:\n{self.log(name)[-3000:]}"
            )
            time.sleep(0.5)

    def wait_exit(self, name: str, timeout: float) -> None:
        """Until the process ends; fails with its log's tail unless it ended with status 0."""
        try:
            code = self.procs[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{name}: still running after {timeout} s") from None
        assert code == 0, f"{name} ended ({code}):\n{self.log(name)[-3000:]}"

    def stop(self, name: str) -> None:
        _stop_group(self.procs[name])

    def stop_all(self) -> list[str]:
        """Stop every process group; return what is still alive afterwards (should be none)."""
        sessions = {p.pid for p in self.procs.values()}
        tree = [c for p in self.procs.values() for c in _tree(p.pid)]
        for proc in self.procs.values():
            _stop_group(proc)
        left = [p for p in tree if _alive(p)]
        left += [
            p
            for p in psutil.process_iter()
            if _alive(p) and _session(p) in sessions and p not in left
        ]
        return [f"{p.pid} {' '.join(_cmdline(p))[:200]}" for p in left]


def _tree(pid: int) -> list[psutil.Process]:
    try:
        root = psutil.Process(pid)
        return [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _stop_group(proc: subprocess.Popen, grace_s: float = 20.0) -> None:
    """SIGTERM to the process's group, SIGKILL to what is left after ``grace_s``."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
        end = time.monotonic() + grace_s
        while time.monotonic() < end and _group_alive(proc.pid):
            proc.poll()
            time.sleep(0.2)
        if not _group_alive(proc.pid):
            break
    proc.wait(timeout=10)


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    # zombies of our own children count as gone
    return any(_alive(p) and _pgid(p) == pgid for p in psutil.process_iter())


def _alive(p: psutil.Process) -> bool:
    try:
        return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _pgid(p: psutil.Process) -> int | None:
    try:
        return os.getpgid(p.pid)
    except OSError:
        return None


def _session(p: psutil.Process) -> int | None:
    try:
        return os.getsid(p.pid)
    except OSError:
        return None


def _cmdline(p: psutil.Process) -> list[str]:
    try:
        return p.cmdline()
    except psutil.Error:
        return []


def wait_http(url: str, timeout: float, run: Started, name: str) -> None:
    """Until ``url`` answers 200; fails with process ``name``'s log tail if it ends first or
    ``timeout`` s pass."""
    end = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        code = run.procs[name].poll()
        assert code is None, f"{name} ended ({code}):\n{run.log(name)[-3000:]}"
        assert time.monotonic() < end, (
            f"{url}: no answer in {timeout} s; {name}'s log:\n{run.log(name)[-3000:]}"
        )
        time.sleep(1)


def scheduled_runs(api_url: str, timeout: float) -> list[dict]:
    """The deployment's flow runs in state Scheduled (its cron schedule's), waiting up to
    ``timeout`` s for the server's scheduler service to make them."""
    with urllib.request.urlopen(f"{api_url}/deployments/name/streetcd-nightly/nightly") as r:
        deployment_id = json.load(r)["id"]
    body = {
        "deployments": {"id": {"any_": [deployment_id]}},
        "flow_runs": {"state": {"type": {"any_": ["SCHEDULED"]}}},
        "limit": 10,
    }
    end = time.monotonic() + timeout
    while True:
        request = urllib.request.Request(
            f"{api_url}/flow_runs/filter",
            data=json.dumps(body).encode(),
            headers={"Content-Type": "application/json"},
        )
        with urllib.request.urlopen(request) as r:
            runs = json.load(r)
        if runs or time.monotonic() > end:
            return runs
        time.sleep(2)


def dockerfile_env() -> dict[str, str]:
    """The Dockerfile's ``ARG name=default`` and ``ENV name=value`` settings (simple forms)."""
    text = (INFRA / "Dockerfile").read_text().replace("\\\n", " ")
    env: dict[str, str] = {}
    for rest in re.findall(r"^(?:ARG|ENV)\s+(.*)$", text, flags=re.M):
        for name, value in re.findall(r"(\w+)=(\S+)", rest):
            env[name] = re.sub(r"\$\{(\w+)\}", lambda m: env.get(m.group(1), ""), value)
    return env


@contextmanager
def infra(tmp: Path) -> Iterator[Started]:
    """The processes, stopped at the end; fails if any of them or their children is left."""
    dask_config = tmp / "etc-dask"  # the image's /etc/dask
    dask_config.mkdir()
    (dask_config / "streetcd.yaml").write_text((INFRA / "dask.yaml").read_text())
    image_env = dockerfile_env()
    env = {
        **os.environ,
        "PATH": f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "PREFECT_HOME": str(tmp / "prefect-home"),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DASK_CONFIG": str(dask_config),
        "NUMBA_CACHE_DIR": str(tmp / "numba-cache"),  # the image's is under /opt/streetcd
        **FAST_POLLS,
        "NUMBA_CPU_NAME": image_env["NUMBA_CPU_NAME"],
    }
    for name in ("PREFECT_API_URL", "STREETCD_SCHEDULER", "PREFECT_PROFILES_PATH"):
        env.pop(name, None)
    started = Started(tmp, env)
    try:
        yield started
    finally:
        left = started.stop_all()
    assert not left, f"processes left after the test: {left}"


def cache_files(folder: Path) -> dict[str, tuple[int, int]]:
    """numba's cache files under ``folder``: relative path -> (size, mtime in ns)."""
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in folder.rglob("*.nb[ic]")
    }


def numba_build_folder(request: pytest.FixtureRequest, kind: str, tmp: Path) -> Path:
    """Where the warm-up compiles (the image build's cache folder): kept between sessions in
    pytest's cache for ``kind`` "kept" (when pytest's cache plugin is on), else empty."""
    cache = getattr(request.config, "cache", None)
    if kind == "kept" and cache is not None:
        return Path(cache.mkdir("streetcd-infra-numba-cache"))
    folder = tmp / "numba-build"
    folder.mkdir()
    return folder


@pytest.mark.parametrize(
    "numba_cache", ["kept", pytest.param("empty", marks=pytest.mark.slow)]
)  # slow: ~1 min more of a core, compiling every kernel
def test_infra_commands_start_and_run_the_deployment(small_city, tmp_path, request, numba_cache):
    t0 = time.perf_counter()
    compose = yaml.safe_load((INFRA / "docker-compose.yml").read_text())
    values = yaml.safe_load((INFRA / "helm" / "dask-values.yaml").read_text())
    dockerfile = (INFRA / "Dockerfile").read_text()
    assert "pip install --no-cache-dir -c constraints.txt ." in dockerfile
    assert 'ENTRYPOINT ["/opt/streetcd/infra/entrypoint.sh"]' in dockerfile
    (warm_up,) = re.findall(r"^RUN (infra/warm-numba\.sh)\b", dockerfile, flags=re.M)

    chosen = free_ports(5)
    ports = dict(zip(("8786", "8787", "4200"), chosen[:3], strict=True))
    helm_ports = dict(zip(("8786", "8787"), chosen[3:], strict=True))
    api_url = f"http://127.0.0.1:{ports['4200']}/api"
    scheduler = f"tcp://127.0.0.1:{ports['8786']}"
    service_env = {  # the compose file's x-streetcd environment, local addresses
        k: local([v], ports)[0]
        for k, v in compose["services"]["flow-worker"]["environment"].items()
    }
    assert service_env == {"STREETCD_SCHEDULER": scheduler, "PREFECT_API_URL": api_url}

    build = numba_build_folder(request, numba_cache, tmp_path)
    with infra(tmp_path) as run:
        # the image's build step: compile numba's kernels into its cache folder, meanwhile
        # the services that do not run kernels start
        run.start("warm-numba", [str(ROOT / warm_up)], NUMBA_CACHE_DIR=str(build))

        # the server runs from the streetcd image too: the venv's (locked) Prefect is the one
        services = compose["services"]
        assert services["prefect-server"]["image"] == services["dask-scheduler"]["image"]
        server = local(compose_command(compose, "prefect-server"), ports)
        run.start("prefect-server", [ENTRYPOINT, *server, "--port", str(ports["4200"])])

        run.start(
            "dask-scheduler",
            [ENTRYPOINT, *local(compose_command(compose, "dask-scheduler"), ports)],
        )
        run.start("helm-scheduler", [ENTRYPOINT, *local(helm_scheduler_args(values), helm_ports)])
        # the deployment and the Prefect worker need the server only
        wait_http(f"{api_url}/health", 180, run, "prefect-server")
        run.start(
            "flow-worker", [ENTRYPOINT, *compose_command(compose, "flow-worker")], **service_env
        )
        run.wait_exit("warm-numba", 480)
        warm_s = time.perf_counter() - t0
        (kernels,) = re.findall(r"numba cache: (\d+) compiled kernels", run.log("warm-numba"))
        assert int(kernels) > 0, run.log("warm-numba")[-3000:]
        # the image as shipped: the cache folder of the workers and of the flow runs holds
        # what the build step left (the flow worker's imports may have made the folder)
        shutil.copytree(build, run.env["NUMBA_CACHE_DIR"], dirs_exist_ok=True)
        shipped = cache_files(Path(run.env["NUMBA_CACHE_DIR"]))

        run.wait_for("dask-scheduler", "Scheduler at:", 60)
        # one worker as compose runs it, one as the Helm chart does, on the compose scheduler
        run.start(
            "dask-worker", [ENTRYPOINT, *local(compose_command(compose, "dask-worker"), ports)]
        )
        run.start(
            "helm-worker",
            [ENTRYPOINT, *local(helm_worker_args(values, scheduler), ports)],
            **{e["name"]: str(e["value"]) for e in values["worker"].get("env", [])},
        )
        run.wait_for("helm-scheduler", "Scheduler at:", 60)
        run.stop("helm-scheduler")
        for name in ("dask-worker", "helm-worker"):
            run.wait_for(name, "Registered to:", 60)
        run.wait_for("flow-worker", "started!", 180)  # "Worker 'ProcessWorker …' started!"
        started_s = time.perf_counter() - t0

        data = tmp_path / "data"
        params = {
            "images": str(small_city.images),
            "poses": str(small_city.poses),
            "archive": str(small_city.manifest.parent / "cloud"),  # ingested by the flow run
            "store": str(data / "store.zarr"),
            "index": str(data / "change_index.sqlite"),
            "out": str(data / "results"),
        }
        t = time.perf_counter()
        trigger = subprocess.run(
            ["prefect", "deployment", "run", "streetcd-nightly/nightly", "--params",
             json.dumps(params), "--watch", "--watch-interval", "1", "--watch-timeout", "600"],
            cwd=ROOT, env={**run.env, **service_env}, capture_output=True, text=True, timeout=660,
        )  # fmt: skip
        run_s = time.perf_counter() - t
        assert "Completed" in trigger.stdout, (
            trigger.stdout[-3000:] + trigger.stderr[-2000:] + run.log("flow-worker")[-4000:]
        )
        # the nightly schedule is live: the server made the cron's next runs
        nights = scheduled_runs(api_url, 60)
        assert nights, "no scheduled run:\n" + run.log("prefect-server")[-3000:]

    (schedule,) = yaml.safe_load((INFRA / "prefect.yaml").read_text())["deployments"][0][
        "schedules"
    ]
    zone = ZoneInfo(schedule["timezone"])
    for night in nights:
        start = datetime.fromisoformat(night["expected_start_time"]).astimezone(zone)
        minute, hour = (int(x) for x in schedule["cron"].split()[:2])
        assert (start.hour, start.minute) == (hour, minute), night["expected_start_time"]
    # the flow used the compose cluster: both workers got the run's warm-up
    for name in ("dask-worker", "helm-worker"):
        assert "warm_worker" in run.log(name), run.log(name)[-2000:]
    with closing(sqlite3.connect(f"file:{params['index']}?mode=ro", uri=True)) as db:
        views = db.execute("SELECT status, total_s, cpu_s FROM views").fetchall()
    n_images = len(list(small_city.images.glob("*.jpg")))
    assert len(views) == n_images and {s for s, _, _ in views} == {"done"}, views
    slowest = max(t for _, t, _ in views)
    most_cpu = max(c for _, _, c in views)
    print(
        f"\ninfra test ({numba_cache} numba cache, {kernels} kernels): numba warm-up "
        f"{warm_s:.0f} s, infra up {started_s:.0f} s, "
        f"deployment run {run_s:.0f} s, slowest view {slowest:.2f} s wall, "
        f"{most_cpu:.2f} s CPU, total {time.perf_counter() - t0:.0f} s"
    )
    # each worker's first view is among these: the shipped cache spares numba's compiler,
    # which would have written what it compiled into the workers' cache folder
    assert most_cpu < FIRST_VIEW_MAX_S, views
    compiled = cache_files(Path(run.env["NUMBA_CACHE_DIR"])).items() - shipped.items()
    assert not compiled, f"compiled after the image was built: {sorted(dict(compiled))}"
