"""The bags the pipeline reads and writes, checked against the interface contract, read back.

An input bag (``parproj simulate``, ``parproj import``, a recording of a sensor) holds the input
topics of :mod:`parproj_ros.core.contract` (navigation, each view's strips and camera, GCP, the
pair selection, truth points); an output bag (``parproj process``, a recording of the node) its
output topics (``contract.OUTPUTS``). This module checks both kinds, and reads
back what the pipeline and the node need from an input bag: its cameras, its truth, its object
frame, the settings and node parameters that fit it. It sits beside the bag code (the messages
layer), so that the node, ``parproj process`` and the evaluation need nothing of the simulator.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..core import contract
from ..core.config import PipelineConfig, ViewConfig, view_values
from ..core.frames import ObjectFrame
from ..core.results import GroundPoint, Issue
from ..geometry import GeometryError, LineCamera, quaternion_to_rotation
from .bag import BagError, BagReader
from .conversions import gcp_from_msg

#: Topics of an input bag whose type is checked (``*`` stands for a view name): the contract's
#: inputs but the pair selection, whose messages ``parproj process`` converts one by one (a
#: malformed one is a WARN, the message dropped).
CHECKED_INPUTS = {k: v for k, v in contract.INPUT_TYPES.items() if k != contract.PAIRS}
_TRUTH = {contract.TRUTH_POINTS: contract.INPUT_TYPES[contract.TRUTH_POINTS]}
_SCANNER_INFO = "*/" + contract.SCANNER_INFO


def _expected_type(topic: str, expected: dict[str, str]) -> str | None:
    name = topic.lstrip("/")
    for pattern, msgtype in expected.items():
        if pattern.startswith("*/"):
            if name.endswith(pattern[1:]) and name.count("/") == pattern.count("/"):
                return msgtype
        elif name == pattern.lstrip("/"):
            return msgtype
    return None


def check_topic_types(reader: BagReader, expected: dict[str, str]) -> None:
    """Every topic of ``reader`` named in ``expected`` has the type given there.

    Raises:
        BagError: naming the bag, the topic, its type and the expected one.
    """
    encodings = reader.message_encodings()
    for topic, msgtype in reader.topics().items():
        want = _expected_type(topic, expected)
        if want is not None and encodings.get(topic, "cdr") != "cdr":
            raise BagError(
                f"topic {topic} has message encoding {encodings[topic]!r}: only ROS 2 CDR "
                "('cdr') is read",
                reader.path,
            )
        if want is not None and msgtype != want:
            raise BagError(
                f"topic {topic} has type {msgtype or '(no schema)'}, expected {want}", reader.path
            )


def check_input_bag(path: Path) -> tuple[ViewConfig, ...]:
    """An input bag the pipeline can run on (the checks of ``parproj process`` and the demo).

    Returns its cameras.

    Raises:
        BagError: not a bag, topics of the wrong type, no camera or more than two, a camera
            without strips.
        FileNotFoundError: no such bag.
    """
    reader = BagReader(path)
    check_topic_types(reader, CHECKED_INPUTS)
    views = views_from_bag(reader)
    if not views:
        rec = reader.recovery
        cut = "" if rec.complete else f" (the file is damaged or cut off: {rec.error})"
        raise BagError(
            "no <view>/scanner_info topic: not an input bag (made by parproj simulate or "
            f"parproj import){cut}",
            path,
        )
    if len(views) > 2:
        raise BagError(f"{len(views)} cameras ({[v.name for v in views]}); 1 or 2 needed", path)
    topics = reader.topics()
    lacking = [v.name for v in views if contract.strip_topic(v.name) not in topics]
    if lacking:
        raise BagError(
            f"no image strips for camera {lacking[0]} ({contract.strip_topic(lacking[0])})", path
        )
    return views


def check_output_bag(path: Path) -> None:
    """A bag of outputs (``parproj process``, the node): a stereo_pair topic of the right type.

    Raises:
        BagError: not a bag, no stereo_pair topic, topics of the wrong type.
    """
    reader = BagReader(path)
    check_topic_types(reader, {**contract.OUTPUT_TOPICS, **_TRUTH})
    if contract.STEREO_PAIR not in {t.lstrip("/") for t in reader.topics()}:
        raise BagError(
            "no stereo_pair topic: not an output of parproj process or of the node", path
        )


def check_truth_bag(path: Path) -> None:
    """A bag with truth points (``truth/points``, GroundControlPoints).

    Raises:
        BagError: not a bag, no truth/points topic, or of the wrong type.
    """
    reader = BagReader(path)
    check_topic_types(reader, _TRUTH)
    if contract.TRUTH_POINTS not in reader.topics():
        raise BagError("no truth/points topic: no truth to evaluate against", path)


def views_from_bag(reader: BagReader) -> tuple[ViewConfig, ...]:
    """The cameras (ScannerInfo messages) recorded in a bag, in topic order.

    Raises:
        BagError: a ``*/scanner_info`` topic is not a ScannerInfo, or describes no camera.
    """
    topics = [t for t in reader.topics() if t.endswith(_SCANNER_INFO[1:])]
    if not topics:
        return ()  # (an empty topic list would read every topic)
    check_topic_types(reader, {_SCANNER_INFO: contract.INPUT_TYPES[_SCANNER_INFO]})
    views = []
    for item in reader.messages(topics=topics):
        m = item.msg
        q = m.mounting
        try:
            cam = LineCamera(
                m.principal_distance,
                m.pixel_size,
                int(m.detectors),
                m.line_period,
                m.principal_point,
            )
        except (GeometryError, ValueError, OverflowError) as err:
            raise BagError(f"{item.topic}: not a usable camera: {err}", reader.path) from None
        views.append(
            ViewConfig(
                item.topic.rsplit("/", 1)[0], cam, quaternion_to_rotation([q.x, q.y, q.z, q.w])
            )
        )
    order = {name: i for i, name in enumerate(("left", "right"))}
    views.sort(key=lambda v: order.get(v.name, 99))
    return tuple(dict((v.name, v) for v in views).values())


def truth_from_bag(reader: BagReader) -> list[GroundPoint]:
    """Truth points recorded on truth/points."""
    out: list[GroundPoint] = []
    for item in reader.messages(topics=[contract.TRUTH_POINTS]):
        try:
            out += gcp_from_msg(item.msg)
        except ValueError as err:  # ConversionError, or a GroundPoint refused
            raise BagError(
                f"{contract.TRUTH_POINTS}: malformed message: {err}", reader.path
            ) from err
    return out


def node_parameters(views: tuple[ViewConfig, ...], **extra: Any) -> dict[str, Any]:
    """parproj_node parameters for these cameras (for --params-file or -p)."""
    params: dict[str, Any] = {"views": [v.name for v in views]}
    for v in views:
        params.update({f"{v.name}.{name}": x for name, x in view_values(v).items()})
    params.update(extra)
    return params


def config_from_bag(reader: BagReader, **overrides: Any) -> PipelineConfig:
    """Pipeline settings for a bag: its cameras plus ``overrides`` (PipelineConfig fields)."""
    return PipelineConfig(views=views_from_bag(reader), **overrides)


def frame_from_bag(reader: BagReader, given: str = "") -> tuple[ObjectFrame, list[Issue]]:
    """The object frame of a bag's outputs (:mod:`parproj_ros.core.frames`).

    Reads the ``header.frame_id`` of the first message of each of ``contract.FRAME_TOPICS`` present
    (GCP, truth points, navigation), in log-time order: the first that names a frame is the
    outputs' frame unless ``given`` is.

    Args:
        reader: the input bag.
        given: the frame the user asked for ("" = the inputs').

    Returns:
        (frame, issues): ``frame.frame_id`` is the outputs' frame; a WARN for each input in
        another frame, naming both.
    """
    frame = ObjectFrame(given)
    issues: list[Issue] = []
    present = [t for t in contract.FRAME_TOPICS if t in reader.topics()]
    firsts: dict[str, tuple[int, str]] = {}
    if present:
        # Only the chunks holding these topics are read, up to the first message of each.
        for item in reader.messages(topics=present):
            if item.topic not in firsts:
                firsts[item.topic] = (item.log_time_ns, str(item.msg.header.frame_id))
            if len(firsts) == len(present):
                break
    order = sorted(firsts.items(), key=lambda kv: (kv[1][0], contract.FRAME_TOPICS.index(kv[0])))
    for topic, (_, frame_id) in order:
        issues += frame.observe(topic, frame_id)
    return frame, issues
