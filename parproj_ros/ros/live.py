"""Live-graph helpers for the demo and the end-to-end tests.

Replaying a bag into DDS (``ros2 bag play`` has no wheel), recording topics into a bag, and
running the node in its own process.
"""

from __future__ import annotations

import atexit
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from ..core import contract
from .bag import BagReader, BagWriter, get_message_class


def ros_environment(domain_id: int | None = None, log_dir: Path | None = None) -> dict[str, str]:
    """The environment for ROS processes, with the rules of every run here.

    DDS on localhost only, a domain of our own, a writable log directory, checked fields.
    """
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    if log_dir is not None:
        env["ROS_LOG_DIR"] = str(log_dir)
    env.setdefault("ROS_LOG_DIR", str(Path.cwd() / "build" / "ros_log"))
    Path(env["ROS_LOG_DIR"]).mkdir(parents=True, exist_ok=True)
    env["ROS_PYTHON_CHECK_FIELDS"] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _all_acked(pub: Any) -> bool:
    """Whether every subscriber acknowledged ``pub``'s messages (waits up to 0.2 s)."""
    from rclpy.duration import Duration

    return bool(pub.wait_for_all_acked(Duration(seconds=0.2)))


def wait_until(
    cond: Callable[[], bool],
    timeout_s: float,
    alive: Callable[[], bool] = lambda: True,
    poll_s: float = 0.05,
) -> bool:
    """Poll ``cond`` until it holds; returns ``cond()`` at the end.

    Polls every ``poll_s`` seconds and gives up after ``timeout_s`` seconds or as soon as
    ``alive()`` turns false (e.g. the node process died).
    """
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and alive():
        if cond():
            return True
        time.sleep(poll_s)
    return cond()


def _qos(kind: str) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if kind == "transient_local":
        return QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
    return QoSProfile(
        depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
    )


def replay(
    node: Any,
    bag: Path,
    *,
    rate: float = 1.0,
    max_gap_s: float | None = None,
    wait_for: list[str] | None = None,
    wait_timeout_s: float = 20.0,
    progress: bool = False,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Publish a bag's messages on ``node`` at ``rate`` x recorded speed (0 = as fast as possible).

    Waits until every topic in ``wait_for`` has a subscriber (or ``wait_timeout_s``), paces by log
    time, shortens idle stretches longer than ``max_gap_s`` to that, and waits for reliable
    deliveries to be acknowledged at the end. Returns counts and the reader's recovery report.
    """
    from tqdm import tqdm

    reader = BagReader(bag)
    pubs: dict[str, Any] = {}
    for topic, msgtype in reader.topics().items():
        cls = get_message_class(msgtype)
        if cls is None:
            log(f"replay: {topic}: type {msgtype} unknown here: not published")
            continue
        try:
            pubs[topic] = node.create_publisher(cls, topic, _qos(reader.qos(topic)))
        except Exception as err:  # rclpy: invalid topic name (assorted exception types)
            why = " ".join(str(err).split())
            log(f"replay: {topic}: cannot be published ({type(err).__name__}: {why}): skipped")
    deadline = time.monotonic() + wait_timeout_s
    for topic in wait_for or []:
        if topic not in pubs:
            log(f"replay: {topic} is not published from this bag: not waited for")
            continue
        while pubs[topic].get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        if pubs[topic].get_subscription_count() == 0:
            log(f"replay: nobody subscribes to {topic} after {wait_timeout_s} s")
    if wait_for:
        time.sleep(0.5)  # let the readers' side of discovery finish too (see Recorder)
    sent = 0
    start_wall = time.monotonic()
    first_log: int | None = None
    skipped = 0.0
    latest: int | None = None  # latest log time so far: a jump back is sent at once
    bar = tqdm(
        total=reader.message_count,
        desc=f"replay {Path(bag).name}",
        unit="msg",
        disable=not progress,
        leave=False,
    )
    for item in reader.messages():
        pub = pubs.get(item.topic)
        if pub is None:
            continue
        if first_log is None:
            first_log = item.log_time_ns  # pacing starts at the bag's first message, not at 0
        if max_gap_s is not None and latest is not None:
            gap = (item.log_time_ns - latest) / 1e9
            if gap > max_gap_s:
                skipped += gap - max_gap_s
        latest = item.log_time_ns if latest is None else max(latest, item.log_time_ns)
        if rate > 0:
            due = start_wall + ((item.log_time_ns - first_log) / 1e9 - skipped) / rate
            # time.sleep returns early when a signal handler raises (SIGINT, parproj's SIGTERM)
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        pub.publish(item.msg)
        sent += 1
        bar.update(1)
    bar.close()

    for topic, pub in pubs.items():
        # in slices, so that a signal is handled within 0.2 s
        acked = wait_until(partial(_all_acked, pub), 10.0, poll_s=0)
        if not acked:
            log(f"replay: {topic}: not every message was acknowledged within 10 s")
    return {
        "sent": sent,
        "seconds": time.monotonic() - start_wall,
        "recovery": reader.recovery,
        "skipped_types": reader.unknown_types(),
    }


def largest_idle_s(reader: BagReader, max_gap_s: float | None = None) -> tuple[float, int]:
    """The longest wait of a paced replay of ``reader`` at rate 1, s, and the message before it.

    As :func:`replay` paces: from the first message, log times in file order, a jump back sent
    at once, idle stretches longer than ``max_gap_s`` shortened to it. A bag whose first
    message was logged at a tiny time (an unset clock) and the rest at the real time would
    otherwise wait for decades.
    """
    latest: int | None = None
    idle, where = 0.0, 0
    for k, item in enumerate(reader.raw_messages()):
        t = item.log_time_ns
        if latest is not None and t > latest:
            gap = (t - latest) / 1e9
            if max_gap_s is not None:
                gap = min(gap, max_gap_s)
            if gap > idle:
                idle, where = gap, k
        latest = t if latest is None else max(latest, t)
    return idle, where


class Recorder:
    """Subscribes to topics and writes every message to a bag (receive time as log time)."""

    def __init__(self, node: Any, bag: Path, topics: dict[str, str]) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.writer = BagWriter(bag, compression="zstd", overwrite=True)
        self.counts: dict[str, int] = {t: 0 for t in topics}
        self.messages: dict[str, list[Any]] = {t: [] for t in topics}
        self._lock = threading.Lock()
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self._subs = []
        for topic, msgtype in topics.items():
            self.writer.add_topic(topic, msgtype, "reliable")
            cls = get_message_class(msgtype)
            self._subs.append(
                node.create_subscription(cls, topic, lambda m, t=topic: self._on(t, m), qos)
            )
        self._clock = node.get_clock()

    def _on(self, topic: str, msg: Any) -> None:
        with self._lock:
            self.writer.write(topic, msg, self._clock.now().nanoseconds)
            self.counts[topic] += 1
            self.messages[topic].append(msg)

    def wait_for_publishers(
        self, topics: list[str], timeout_s: float = 20.0, settle_s: float = 1.0
    ) -> bool:
        """Wait until each of ``topics`` has a matched publisher (discovery done).

        Discovery is not symmetric: a subscription can see the publisher before the publisher
        has matched the subscription, and a volatile sample published in between is lost (seen
        once in CI with the 19-message Ventoux bag, whose pair comes out within a second). So,
        after every topic shows a publisher, wait ``settle_s`` more for the writers' side.
        """
        deadline = time.monotonic() + timeout_s
        subs = dict(zip(self.counts, self._subs, strict=True))
        while time.monotonic() < deadline:
            if all(subs[t].get_publisher_count() > 0 for t in topics):
                time.sleep(settle_s)
                return True
            time.sleep(0.05)
        return False

    def pairs_complete(self, pairs: int, also: Sequence[str] = ()) -> bool:
        """Whether ``pairs`` stereo pairs have arrived with every image that belongs to them.

        ``also``: topics that carry one message per pair after it (``disparity``, ``height``
        with heights on), each awaited ``pairs`` times too.

        A pair's StereoPair message comes first and its images follow it (left, right,
        anaglyph: large messages that take a while over DDS); a streamed pair's pixels came
        before it as NormalizedBlock messages. Stopping the node on the StereoPair alone, or on
        the left image alone, lost the right image once in CI.
        """
        with self._lock:
            done = self.messages.get(contract.STEREO_PAIR, [])[:pairs]
            if len(done) < pairs:
                return False
            whole = sum(1 for p in done if not getattr(p, "streamed", False))
            return all(self.counts.get(t, 0) >= whole for t in contract.PAIR_IMAGE_TOPICS) and all(
                self.counts.get(t, 0) >= pairs for t in also
            )

    def wait_complete(
        self,
        pairs: int,
        timeout_s: float,
        alive: Callable[[], bool] = lambda: True,
        also: Sequence[str] = (),
    ) -> bool:
        """Wait until :meth:`pairs_complete` (or ``timeout_s``, or ``alive()`` turns false)."""
        return wait_until(lambda: self.pairs_complete(pairs, also), timeout_s, alive)

    def close(self) -> None:
        """Close the bag."""
        with self._lock:
            self.writer.close()


def node_params_yaml(params: dict[str, Any], path: Path, *, reliable_inputs: list[str]) -> Path:
    """Write a --params-file for parproj_node.

    ``reliable_inputs`` (fully qualified topic names) get reliable QoS overrides: lossless
    replay for tests and the demo.
    """
    import yaml

    p = dict(params)
    overrides: dict[str, Any] = {}
    for topic in reliable_inputs:
        overrides[topic] = {"subscription": {"reliability": "reliable", "depth": 1000}}
    doc: dict[str, Any] = {"parproj_node": {"ros__parameters": p}}
    if overrides:
        doc["parproj_node"]["ros__parameters"]["qos_overrides"] = overrides
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class NodeProcess:
    """parproj_node in a child process (its own DDS participant), stopped with SIGINT."""

    def __init__(
        self,
        params_file: Path,
        env: dict[str, str],
        log_path: Path,
        program: Sequence[str] | None = None,
    ) -> None:
        """Start the node.

        ``program`` is the command before ``--ros-args`` (default: ``python -m
        parproj_ros.ros.node``; tests give a launcher that injects faults).
        """
        self.log_path = log_path
        self._log = log_path.open("w")
        program = list(program or [sys.executable, "-m", "parproj_ros.ros.node"])
        self.proc = subprocess.Popen(
            [*program, "--ros-args", "--params-file", str(params_file)],
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )
        # A caller that raises before stop() (a bench or test bug) leaves no orphaned node.
        atexit.register(self._kill_at_exit)

    def _kill_at_exit(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def stop(self, timeout: float = 60.0) -> int:
        """SIGINT (the node flushes open scenes and exits); kill after ``timeout``."""
        atexit.unregister(self._kill_at_exit)
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return int(self.proc.returncode)

    def output(self) -> str:
        """What the node printed so far."""
        return self.log_path.read_text(errors="replace")


@dataclass
class LiveRun:
    """What :func:`run_through_node` saw.

    Attributes:
        output: the bag the node's outputs were recorded into.
        counts: messages recorded per topic.
        code: the node's exit code (0: clean stop on SIGINT).
        log: what the node printed.
        replay: :func:`replay`'s result (sent, seconds, recovery, skipped types).
        discovered: whether the node's outputs were discovered before the replay.
        complete: whether every expected pair arrived with its images.
    """

    output: Path
    counts: dict[str, int]
    code: int
    log: str
    replay: dict[str, Any]
    discovered: bool
    complete: bool


def run_through_node(
    bag: Path,
    workdir: Path,
    *,
    params: dict[str, Any],
    rate: float = 0.0,
    max_gap_s: float = 0.2,
    pairs: int = 1,
    timeout_s: float = 120.0,
    env: dict[str, str] | None = None,
    progress: bool = False,
    log: Callable[[str], None] = print,
    also: Sequence[str] = (),
    program: Sequence[str] | None = None,
    skip: Sequence[str] = (),
) -> LiveRun:
    """Replay ``bag`` into parproj_node (its own process) and record the outputs.

    The node gets ``params`` (plus reliable QoS on the bag's input topics: a lossless replay)
    from ``workdir/node_params.yaml`` and logs to ``workdir/node.log``; an rclpy node of ours,
    in its own Context, records ``contract.OUTPUT_TOPICS`` into ``workdir/output``,
    waits for the outputs to be discovered, replays, waits until ``pairs`` pairs have come
    with all their images and one message on each ``also`` topic (or ``timeout_s``, or the
    node died), and stops the node (SIGINT). ``program``: the command before ``--ros-args``
    (:class:`NodeProcess`; e.g. the node of a colcon install tree started from a shell that
    sourced its setup script). ``skip``: output topics not subscribed to (nor recorded).
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from .inputs import views_from_bag

    workdir.mkdir(parents=True, exist_ok=True)
    env = env or ros_environment(log_dir=workdir / "ros_log")
    views = views_from_bag(BagReader(bag))
    inputs = [contract.fully_qualified(t) for t in contract.stream_topics(v.name for v in views)]
    pfile = node_params_yaml(params, workdir / "node_params.yaml", reliable_inputs=inputs)
    proc = NodeProcess(pfile, env, workdir / "node.log", program)
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("parproj_recorder", context=ctx)
    topics = {t: m for t, m in contract.OUTPUT_TOPICS.items() if t not in skip}
    recorder = Recorder(node, workdir / "output", topics)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    res: dict[str, Any] = {}
    try:
        discovered = recorder.wait_for_publishers(list(topics), timeout_s=60.0)
        if not discovered:
            log("live: the node's output topics were not discovered in 60 s")
        res = replay(
            node,
            bag,
            rate=rate,
            max_gap_s=max_gap_s,
            # every input stream the node subscribes to: navigation too, so that its first
            # samples are not published before the node's subscription is matched
            wait_for=[contract.strip_topic(v.name) for v in views]
            + [t for t in (contract.NAVIGATION,) if t in BagReader(bag).topics()],
            progress=progress,
            log=log,
        )
        complete = recorder.wait_complete(
            pairs, timeout_s, lambda: proc.proc.poll() is None, also=also
        )
        time.sleep(1.0)  # one more 1 Hz diagnostics summary
    finally:
        code = proc.stop()
        executor.shutdown()
        spin.join(timeout=5)
        recorder.close()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    return LiveRun(
        workdir / "output", dict(recorder.counts), code, proc.output(), res, discovered, complete
    )
