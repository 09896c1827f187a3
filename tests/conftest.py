"""Shared test set-up: DDS stays on this machine, each run gets its own ROS domain.

Node processes are started from the working tree (`python -m MODULE`), so tests exercise the
code under test; tests/docs/test_install.py checks the installed ament layout (`ros2 run`).
Tests mirror the source layout (tests/trainer/bag/test_bag_io.py tests trainer/bag/); what they
share is the `helpers` package next to this file.
"""
from __future__ import annotations

import fcntl
import os
import resource
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

# Test modules sit in subfolders; `import helpers` finds tests/helpers through this entry, first
# on sys.path so that no installed module of that name can shadow it. The subfolders have no
# __init__.py: tests/trainer/ must not shadow the trainer package.
sys.path.insert(0, str(Path(__file__).resolve().parent))

from helpers import ROOT, Proc

#: The tests' own domains: ROS 2's other "safe" range (above Linux's ephemeral ports), apart from
#: the 1..101 that the launchers the tests start draw a fresh domain from
#: (trainer.launch.rosprocs.fresh_domain_id): a stack started by one worker never joins the
#: domain of another worker's test, even between two of its tests, when no port shows it in use.
TEST_DOMAINS = range(215, 233)


def ros_domain_id() -> int:
    """A domain of its own for this process: the first of TEST_DOMAINS, from a start that depends
    on the run and the pytest-xdist worker, whose lock file it can take. The lock is held until the
    process ends, so two test runs on one machine (two sessions, a run beside a helper's) never
    share a domain: with a shared one, one run's nodes answer the other's. All 18 taken: the
    start itself, as before the locks."""
    first, size = TEST_DOMAINS.start, len(TEST_DOMAINS)
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    start = os.getpid() % size
    if worker:
        start = zlib.crc32(os.environ.get("PYTEST_XDIST_TESTRUNUID", "").encode()) + int(worker.removeprefix("gw"))
    for i in range(size):
        domain = first + (start + i) % size
        fd = os.open(f"/tmp/protocad-test-domain-{domain}.lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _DOMAIN_LOCKS.append(fd)   # held (open) for the life of this process
        return domain
    return first + start % size


#: The lock files' descriptors this process holds (ros_domain_id).
_DOMAIN_LOCKS: list[int] = []


# Set before anything imports rclpy. LOCALHOST keeps discovery off external interfaces;
# a per-run domain keeps concurrent test runs (and users) apart.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["ROS_DOMAIN_ID"] = str(ros_domain_id())
if os.environ.get("PYTEST_XDIST_WORKER"):
    # Workers side by side share the cores: torch's one thread per core in each (and in the
    # processes they start) would only make them wait on each other. Before torch is imported.
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1)
                                                     // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))))
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(ROOT / "sim_bridge" / "fastdds_discovery.xml"))
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ["PYTHONUNBUFFERED"] = "1"
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item, call):
    """Keeps each phase's report on the test item, so that fixtures know at teardown whether
    the test failed."""
    report = yield
    setattr(item, f"report_{report.when}", report)
    return report


# --cpu-durations=N: the N tests that used the most CPU, printed after the run like --durations.
# Wall time hides what a test costs while it waits on DDS or a child; on a machine with fewer or
# slower cores, CPU seconds are what add up. Counted per phase in the process that runs the test:
# its own CPU and that of the child processes it reaped (a spawned node counts where it is
# stopped; a run's workers count through the parent that reaped them).
def pytest_addoption(parser):
    parser.addoption("--cpu-durations", type=int, default=None, metavar="N",
                     help="show the N tests that used the most CPU seconds (user + system, with reaped "
                          "child processes); 0 for all")


def cpu_seconds() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _counted(phase: str):
    @pytest.hookimpl(wrapper=True)
    def hook(item, *args):
        if item.config.getoption("cpu_durations") is None:
            return (yield)
        start = cpu_seconds()
        try:
            return (yield)
        finally:
            item.user_properties.append((f"cpu_s_{phase}", cpu_seconds() - start))
    return hook


pytest_runtest_setup, pytest_runtest_call, pytest_runtest_teardown = map(_counted, ("setup", "call", "teardown"))
_CPU_BY_TEST: dict[str, float] = {}


def pytest_runtest_logreport(report):
    """On the controller too (pytest-xdist sends each report with its properties): the teardown
    report carries all three phases."""
    if report.when == "teardown":
        cpu = sum(v for k, v in report.user_properties if k.startswith("cpu_s_"))
        if cpu:
            _CPU_BY_TEST[report.nodeid] = cpu


def pytest_terminal_summary(terminalreporter, config):
    n = config.getoption("cpu_durations")
    if n is None or not _CPU_BY_TEST or hasattr(config, "workerinput"):
        return
    rows = sorted(_CPU_BY_TEST.items(), key=lambda kv: -kv[1])
    terminalreporter.write_sep("=", f"CPU seconds, {'all' if n == 0 else f'top {n}'} "
                                    f"(all tests: {sum(_CPU_BY_TEST.values()):.0f} s)")
    for nodeid, cpu in rows[:n or None]:
        terminalreporter.write_line(f"{cpu:8.2f}s  {nodeid}")


#: How much of each spawned process's output a failed test prints (its last characters).
FAILED_LOG_TAIL = 4000


@pytest.fixture
def spawn(tmp_path, request):
    """spawn(name, *args) starts `python args...` (in the repository, or `cwd`); every process
    is stopped at teardown. When the test failed, the end of each process's output is printed
    (pytest shows it under the failure): a timeout on a loaded CI machine is otherwise silent
    about what the nodes were doing."""
    procs: list[Proc] = []

    def _spawn(name: str, *args: str, env: dict | None = None, cwd: Path = ROOT) -> Proc:
        proc = Proc([sys.executable, *args], tmp_path / f"{name}.log", env, cwd)
        procs.append(proc)
        return proc

    yield _spawn
    report = getattr(request.node, "report_call", None)
    for proc in procs:
        proc.stop()
        if report is not None and report.failed:
            print(f"----- {proc.log_path.name} (exit {proc.p.returncode}), last {FAILED_LOG_TAIL} "
                  f"characters -----\n{proc.output()[-FAILED_LOG_TAIL:]}")


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny tensors on 2 shared cores: a second torch thread only adds synchronisation cost."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


class SmallDisk:
    """A tmpfs of a given size mounted at `path` (a disk that fills up for real); grow() frees
    space by remounting it larger."""

    def __init__(self, path: Path):
        self.path = path

    def grow(self, size: str = "256m") -> None:
        subprocess.run(["mount", "-o", f"remount,size={size}", str(self.path)], check=True)


@pytest.fixture
def small_disk(tmp_path, request):
    """A 1.5 MB tmpfs (size from `@pytest.mark.disk_size("1m")`), unmounted afterwards; skipped
    where mounting is not allowed (it needs root; CI runs as root)."""
    marker = request.node.get_closest_marker("disk_size")
    size = marker.args[0] if marker else "1536k"
    mnt = tmp_path / "small_disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    yield SmallDisk(mnt)
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
