"""``parproj process``: the pipeline over a bag without DDS, outputs written to a bag.

Outputs are logged at the log time of the input message that produced them.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

from ..core import contract
from ..core.config import PipelineConfig
from ..core.dem_terrain import DemSampler, DemTerrain
from ..core.memory import raw_pair_bytes, tune_malloc
from ..core.results import Issue, Level, Outputs
from ..core.session import InputKind, Session
from ..io.earth import earth_transform
from ..ros import conversions as conv
from ..ros.bag import BagReader, BagWriter
from ..ros.inputs import config_from_bag, frame_from_bag

T = TypeVar("T")

#: Messages read ahead of the pipeline, and output messages waiting to be written: each up to
#: 8 (a full-size strip or block is 14 MB: about 110 MB each at most).
READ_AHEAD = 8
WRITE_BEHIND = 8
#: On an error or a signal, the longest wait for each of the two threads, s.
ABORT_TIMEOUT_S = 5.0


class _Failure:
    """An exception raised in a worker thread, carried to the main thread."""

    def __init__(self, err: BaseException) -> None:
        self.err = err


_END = object()


class ReadAhead(Generic[T]):
    """Iterates ``source`` in a thread, up to ``depth`` items ahead of the consumer.

    Reading the bag (file read, chunk decompression and CRC, both without the GIL; and the
    deserialization) overlaps the pipeline's work on the other core. An exception raised by
    ``source`` is raised again by the iteration, in the consumer's thread. :meth:`close` stops
    the thread (it is a daemon: a consumer that stops early does not keep the process alive).
    """

    def __init__(self, source: Iterable[T], depth: int = READ_AHEAD) -> None:
        self._q: queue.Queue[Any] = queue.Queue(maxsize=max(int(depth), 1))
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(source,), name="bag-read-ahead", daemon=True
        )
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self, source: Iterable[T]) -> None:
        try:
            for item in source:
                if not self._put(item):
                    return
            self._put(_END)
        except BaseException as err:  # carried to the consumer, raised there
            self._put(_Failure(err))

    def __iter__(self) -> Iterator[T]:
        while True:
            item = self._q.get()
            if item is _END:
                return
            if isinstance(item, _Failure):
                raise item.err
            yield item

    def close(self, timeout: float | None = None) -> None:
        """Stop reading ahead and wait for the thread (items not taken are dropped).

        ``timeout`` (s): wait no longer (the error path). A SIGINT/SIGTERM exception raised in
        the consumer just as it took the queue's lock can leave that lock held (the exception
        comes between the acquire and the ``with`` block: bpo-29988); the thread then never
        returns, and is left behind (a daemon: the process still exits).
        """
        self._stop.set()
        self._thread.join(timeout)


class WriteBehind:
    """Writes ``(topic, message, log time)`` to a BagWriter in a thread, in the order given.

    A message given as ``bytes`` is CDR already (``BagWriter.write_raw``).

    Serialization holds the GIL; chunk compression, CRC and the file write do not, and overlap
    the pipeline's work. A write error is raised again by the next :meth:`write` or by
    :meth:`close`; the messages after it are discarded (the bag is being abandoned).
    """

    def __init__(self, bag: BagWriter, depth: int = WRITE_BEHIND) -> None:
        self._bag = bag
        self._q: queue.Queue[tuple[str, Any, int] | None] = queue.Queue(maxsize=max(depth, 1))
        self.error: BaseException | None = None
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bag-write-behind", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                item = self._q.get(timeout=0.1)
            except queue.Empty:
                if self._closing.is_set():  # abort(): everything queued is written
                    return
                continue
            if item is None:
                self._q.task_done()
                return
            self._write(*item)
            del item  # the message is not kept alive while waiting for the next one
            self._q.task_done()

    def _write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        if self.error is not None:
            return
        try:
            if isinstance(msg, bytes):  # already CDR (conversions.block_to_cdr)
                self._bag.write_raw(topic, msg, stamp_ns)
            else:
                self._bag.write(topic, msg, stamp_ns)
        except BaseException as err:  # carried to the producer
            self.error = err

    def drain(self) -> None:
        """Wait until every queued message is written, then raise a write error if any.

        For whole images (hundreds of MB each at IKONOS size), so that they are not kept while
        the next input is processed.
        """
        self._q.join()
        if self.error is not None:
            raise self.error

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Queue one message (blocks while ``depth`` are waiting)."""
        if self.error is not None:
            raise self.error
        self._q.put((topic, msg, stamp_ns))

    def close(self) -> None:
        """Write what is queued, stop the thread; raise a write error if there was one."""
        self._q.put(None)
        self._thread.join()
        if self.error is not None:
            raise self.error

    def abort(self, timeout: float) -> None:
        """The error path: the thread writes what is queued and stops; wait ``timeout`` s.

        Takes no lock of the queue (a SIGINT/SIGTERM exception may have left it held: see
        :meth:`ReadAhead.close`); a thread that does not end in time is left behind (a daemon).
        Write errors are not raised: the run's own error is.
        """
        self._closing.set()
        self._thread.join(timeout)


@dataclass
class ProcessSummary:
    """What ``process_bag`` did.

    Attributes:
        scenes: scenes with parameters.
        pairs: normalized pairs written.
        issues: every problem reported (also written on /diagnostics).
        messages_in: input messages read.
        recovery: the input reader's recovery report (cut-off bags).
        skipped_topics: topics of unknown types, with counts.
        direct: whether the output bag was written past the page cache (O_DIRECT).
        unusable: the pairs whose normalized images share almost no ground
            (:attr:`PairResult.unusable`).
        heights: (pair, whether it got a DSM) of every pair the heights step saw.
        tiles: (pair, whether the tile has heights) of every streamed DSM tile.
    """

    scenes: int = 0
    pairs: int = 0
    issues: list[Issue] = field(default_factory=list)
    messages_in: int = 0
    recovery: Any = None
    skipped_topics: dict[str, int] = field(default_factory=dict)
    direct: bool = False
    unusable: list[str] = field(default_factory=list)
    heights: list[tuple[str, bool]] = field(default_factory=list)
    tiles: list[tuple[str, bool]] = field(default_factory=list)


def _bag_issues(reader: BagReader, name: str) -> Outputs:
    """What reading the input bag lost or skipped, as issues for /diagnostics."""
    out = Outputs()
    rec = reader.recovery
    if rec is not None and not rec.complete:
        lost = rec.messages_lost
        out.issues.append(
            Issue(
                Level.WARN,
                name,
                (
                    f"input bag cut off ({rec.error}): "
                    + (f"{lost} messages lost, " if lost is not None else "")
                    + f"{rec.messages_read} complete messages read and processed"
                ),
            )
        )
    for topic, n in sorted(reader.skipped.items()):
        out.issues.append(
            Issue(
                Level.WARN,
                topic,
                (f"{n} messages of type {reader.topics().get(topic, '?')} unknown here: skipped"),
            )
        )
    for topic, n in sorted(reader.decode_errors.items()):
        out.issues.append(Issue(Level.WARN, topic, f"{n} messages could not be decoded: skipped"))
    return out


def _input(topic: str, msg: Any, strip_topics: dict[str, str]) -> tuple[InputKind, Any] | None:
    """The session input of a bag message (None: a topic the pipeline does not take).

    Raises:
        conversions.ConversionError: a message that does not convert.
    """
    if topic == contract.NAVIGATION:
        return InputKind.NAV, conv.odometry_to_sample(msg)
    if topic in strip_topics:
        return InputKind.STRIP, conv.strip_from_msg(strip_topics[topic], msg)
    if topic == contract.GCP:
        return InputKind.GCP, conv.gcp_from_msg(msg)
    if topic == contract.PAIRS:
        return InputKind.PAIRS, conv.pairs_from_msg(msg)
    return None


def process_bag(
    src: Path,
    dst: Path,
    *,
    config: PipelineConfig | None = None,
    frame_id: str = "",
    progress: bool = True,
    overrides: dict[str, Any] | None = None,
    on_outputs: Callable[[Outputs], None] | None = None,
    compression: str = "zstd",
    image_compression: str | None = None,
    direct: bool = True,
    dem: DemSampler | None = None,
) -> ProcessSummary:
    """Run the pipeline over the bag ``src`` and write its outputs to the bag ``dst``.

    ``compression`` is the output bag's chunk compression ("zstd", "lz4", "none");
    ``image_compression``, when given, that of the topics carrying images (normalized images,
    anaglyph, column blocks, StereoPair): zstd spends most of the writing time on them
    (BagWriter's ``topic_compression``; README, "Recording large images"). ``direct``: the
    output bag is written past the page cache (``O_DIRECT``, where the file system allows it;
    ``summary.direct`` tells): a large output then takes no fresh memory for its pages
    (io/direct.py). ``frame_id`` labels the outputs; "" (default): the frame of the bag's
    GCP / truth / navigation messages, else ``map`` (:func:`~parproj_ros.ros.inputs.
    frame_from_bag`; an input in another frame is a WARN naming both). ``dem``: the DEM of the
    pairs' terrain (``parproj_ros.io.dem.load_dem``; ``parproj process --dem``), placed in that
    frame (:class:`~parproj_ros.core.dem_terrain.DemTerrain`).
    """
    from tqdm import tqdm

    reader = BagReader(src)
    cfg = config or config_from_bag(reader, **(overrides or {}))
    frame, frame_issues = frame_from_bag(reader, frame_id)
    frame_id = frame.frame_id
    on_earth = earth_transform(frame_id)  # recorded with the first outputs (object_frame)
    if on_earth is not None:
        frame_issues.append(Issue(Level.OK, "object frame", f"{frame_id}: {on_earth.definition}"))
    # Freed strips, blocks and images reused, not given back and faulted in again: up to two
    # raw pairs of free heap kept (a pair's blocks freed at once; core/memory.py)
    tune_malloc(2 * raw_pair_bytes(cfg))
    session = Session(cfg)
    if dem is not None:
        session.pipeline.use_dem(DemTerrain(dem, lambda: frame_id))
    summary = ProcessSummary()
    strip_topics = {contract.strip_topic(v.name): v.name for v in cfg.views}
    per_topic = (
        {t: image_compression for t in contract.image_topics()}
        if image_compression is not None
        else None
    )
    with BagWriter(
        dst, compression=compression, topic_compression=per_topic, overwrite=True, direct=direct
    ) as bw:
        bw.add_topics(contract.OUTPUTS)

        def emit(out: Outputs, stamp_ns: int) -> None:
            for topic, msg, _ in conv.outputs_to_messages(
                out,
                frame_id=frame_id,
                stamp_ns=stamp_ns,
                raw_blocks=True,
                dsm_cloud_step=cfg.dense.cloud_step,
            ):
                writer.write(topic, msg, stamp_ns)  # log time: the input that produced it
            if any(p.left_image is not None for p in out.pairs):
                writer.drain()  # whole images written before the next input, as before
            summary.scenes += len(out.scenes)
            summary.pairs += len(out.pairs)
            summary.unusable += [p.pair_id for p in out.pairs if p.unusable]
            summary.heights += [(h.pair_id, h.ok) for h in out.heights]
            summary.tiles += [(t.pair_id, t.ok) for t in out.tiles]
            summary.issues += out.issues
            if on_outputs:
                on_outputs(out)

        last = 0
        bar = tqdm(
            total=reader.message_count,
            desc=f"process {Path(src).name}",
            unit="msg",
            disable=not progress,
            leave=False,
        )
        writer = WriteBehind(bw)
        inputs = ReadAhead(reader.messages(image_views=True))
        try:
            for item in inputs:
                summary.messages_in += 1
                bar.update(1)
                last = item.log_time_ns
                out = Outputs()
                try:
                    fed = _input(item.topic, item.msg, strip_topics)
                except conv.ConversionError as err:
                    out.issues.append(Issue(Level.WARN, item.topic, f"{err}: message dropped"))
                else:
                    if fed is not None:
                        out = session.feed(*fed)
                if frame_issues:  # inputs in another frame: with the first outputs
                    out.issues[:0] = frame_issues
                    frame_issues = []
                if on_earth is not None:
                    msg = conv.earth_transform_to_msg(on_earth, stamp_ns=item.log_time_ns)
                    writer.write(contract.OBJECT_FRAME, msg, item.log_time_ns)
                    on_earth = None
                emit(out, item.log_time_ns)
            emit(_bag_issues(reader, Path(src).name), last)
            emit(session.feed(InputKind.FLUSH, None), last)
        except BaseException:
            try:
                inputs.close(timeout=ABORT_TIMEOUT_S)
                bar.close()
            finally:
                # The outputs queued so far; the run's error is raised.
                writer.abort(timeout=ABORT_TIMEOUT_S)
            raise
        inputs.close()
        bar.close()
        writer.close()
    summary.recovery = reader.recovery
    summary.skipped_topics = dict(reader.skipped)
    summary.direct = bw.direct  # once written: a file system may refuse at the first write
    return summary
