"""What the benchmark and the long run share: the ROS domain, memory and CPU of processes, JSON.

The node process, the recorder and the waits are :mod:`parproj_ros.ros.live` (the demo and the live
tests use them too); this module holds what only the tools need.
"""

from __future__ import annotations

import math
import os
import platform as pyplatform
import resource
import signal
import subprocess
import threading
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from parproj_ros.ros.live import ros_environment

#: The repository (tools/ sits at its top).
ROOT = Path(__file__).resolve().parent.parent


#: The Fast DDS profile for large images shipped with the project (README, "Large images").
SHM_PROFILE = ROOT / "config" / "fastdds_shm.xml"

#: The variables that select the shared-memory profile and the RMW it is for (Fast DDS 3, in
#: the Kilted wheels, reads FASTDDS_DEFAULT_PROFILES_FILE; the former FASTRTPS_ name still works
#: but logs a deprecation warning, so it is not set, and removed when not wanted).
SHM_PROFILE_ENV = {
    "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
    "FASTDDS_DEFAULT_PROFILES_FILE": str(SHM_PROFILE),
}
#: The profile for a sensor publishing large samples over UDP: its reliable writers heartbeat
#: every 100 ms, not every 3 s (README, "Overload"; a datagram lost otherwise stalls a reader).
FAST_REPAIR_PROFILE = ROOT / "config" / "fastdds_fast_repair.xml"


def fast_dds() -> bool:
    """Whether ROS runs on Fast DDS here (the RMW the profiles in config/ are for)."""
    return os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps")


def join_ros_domain(
    domain_id: int | None = None,
    log_dir: Path | None = None,
    *,
    check_fields: bool = True,
    shm: bool = False,
    fast_repair: bool = False,
) -> dict[str, str]:
    """The node's environment (:func:`parproj_ros.ros.live.ros_environment`); we join it.

    ``check_fields`` sets the node's ROS_PYTHON_CHECK_FIELDS (the tests' 1, or 0 as deployed).
    ``shm`` selects the shared-memory profile (config/fastdds_shm.xml) for the node and this
    process; else ``fast_repair`` selects config/fastdds_fast_repair.xml (default transports,
    reliable writers heartbeating every 100 ms); with neither, a profile file set in the
    environment is removed. Fast DDS loads the
    profile once per process (at its first participant), so a process keeps what it had then.
    The discovery range, domain, log folder and profile are also set in ``os.environ``, so that
    the rclpy context this process opens afterwards is on the node's domain.
    """
    env = ros_environment(domain_id, log_dir)
    env["ROS_PYTHON_CHECK_FIELDS"] = "1" if check_fields else "0"
    for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_LOG_DIR"):
        os.environ[key] = env[key]
    for key, value in SHM_PROFILE_ENV.items():
        if shm:
            env[key] = os.environ[key] = value
        elif fast_repair and key == "FASTDDS_DEFAULT_PROFILES_FILE":
            # Only the file: another RMW (Cyclone DDS) keeps running, and ignores it.
            env[key] = os.environ[key] = str(FAST_REPAIR_PROFILE)
        elif key != "RMW_IMPLEMENTATION":
            env.pop(key, None)
            os.environ.pop(key, None)
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    os.environ.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    return env


def node_params_from_options(items: Sequence[str]) -> dict[str, Any] | None:
    """``--node-param KEY=VALUE`` options as parameters (values read as YAML); None if bad."""
    import sys

    import yaml

    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            print(f"--node-param needs KEY=VALUE, got {item!r}", file=sys.stderr)
            return None
        params[key] = yaml.safe_load(value)
    return params


# ---- memory and CPU of processes -------------------------------------------------------------


def proc_status(pid: int) -> dict[str, float]:
    """VmRSS and VmHWM of a process, MB (empty when it is gone)."""
    out: dict[str, float] = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    key, val = line.split(":", 1)
                    out[key] = int(val.split()[0]) / 1024.0
    except OSError:
        pass
    return out


def mem_available_mb() -> float:
    """MemAvailable of /proc/meminfo, MB."""
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1024.0
    return math.inf


def proc_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process (None when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_busy_s() -> float:
    """CPU seconds the whole machine has been busy since boot (all cores, /proc/stat)."""
    vals = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    return (sum(vals[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def own_cpu_s(*, children: bool) -> float:
    """CPU seconds of this process, and with ``children`` of its waited-for children."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    total = me.ru_utime + me.ru_stime
    if children:
        ch = resource.getrusage(resource.RUSAGE_CHILDREN)
        total += ch.ru_utime + ch.ru_stime
    return total


def process_age_s() -> float | None:
    """Seconds since this process started (interpreter start-up included), from /proc."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])
        btime = next(
            int(line.split()[1])
            for line in Path("/proc/stat").read_text().splitlines()
            if line.startswith("btime")
        )
        return time.time() - (btime + start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, StopIteration):
        return None


class RssMonitor:
    """Samples a process's VmRSS and CPU time every ``period_s`` s in a thread (wall time, MB).

    Above ``kill_above_mb`` it kills the process (SIGKILL) and says so in ``killed``: the guard
    that keeps the benchmark within the machine's memory.
    """

    def __init__(self, pid: int, period_s: float = 0.2, kill_above_mb: float = math.inf) -> None:
        self.pid = pid
        self.period_s = period_s
        self.kill_above_mb = kill_above_mb
        self.samples: list[tuple[float, float]] = []
        self.cpu: list[tuple[float, float]] = []
        self.hwm_mb = 0.0
        self.killed: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss_monitor", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            st = proc_status(self.pid)
            cpu = proc_cpu_s(self.pid)
            now = time.time()
            if "VmRSS" in st:
                self.samples.append((now, st["VmRSS"]))
                self.hwm_mb = max(self.hwm_mb, st.get("VmHWM", 0.0))
                if st["VmRSS"] > self.kill_above_mb and self.killed is None:
                    self.killed = (
                        f"node killed: resident memory {st['VmRSS']:.0f} MB above the "
                        f"benchmark's limit of {self.kill_above_mb:.0f} MB"
                    )
                    try:
                        os.kill(self.pid, signal.SIGKILL)
                    except OSError:
                        pass
            if cpu is not None:
                self.cpu.append((now, cpu))
            self._stop.wait(self.period_s)

    def cpu_rate(self, window_s: float) -> float | None:
        """CPU seconds per second used over the last ``window_s`` seconds (None: too early)."""
        if not self.cpu or self.cpu[-1][0] - self.cpu[0][0] < window_s:
            return None
        t1, c1 = self.cpu[-1]
        for t0, c0 in reversed(self.cpu):
            if t1 - t0 >= window_s:
                return (c1 - c0) / (t1 - t0)
        return None

    @property
    def rss_mb(self) -> float:
        """Latest VmRSS sample, MB (0 before the first)."""
        return self.samples[-1][1] if self.samples else 0.0

    def peak_between(self, t0: float, t1: float) -> float | None:
        """Largest VmRSS sampled in [t0, t1] (wall time), MB."""
        vals = [r for t, r in self.samples if t0 <= t <= t1]
        return max(vals) if vals else None

    def stop(self) -> None:
        """Stop sampling."""
        self._stop.set()
        self._thread.join(timeout=2)


# ---- reports ---------------------------------------------------------------------------------


def machine_info() -> dict[str, Any]:
    """CPU, memory, versions, load, OpenBLAS core type, date and git commit of this run."""
    import cv2
    import scipy

    cpu = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        mem = next(
            int(line.split()[1]) / 2**20
            for line in Path("/proc/meminfo").read_text().splitlines()
            if line.startswith("MemTotal:")
        )
    except (OSError, StopIteration):
        mem = math.nan
    try:
        commit = subprocess.run(
            ["git", "-C", str(ROOT), "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return {
        "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gb": round(mem, 1),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "kernel": pyplatform.release(),
        "python": pyplatform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "openblas_coretype": os.environ.get("OPENBLAS_CORETYPE"),
        "commit": commit or None,
    }


def jsonable(x: Any) -> Any:
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python, tuples -> lists."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
