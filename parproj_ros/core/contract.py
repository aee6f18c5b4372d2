"""The interface contract: every topic of parproj_node and of the bags, in one place.

Pure data, no ROS: the core, the simulator, the evaluation, the applications and the tools all
import it. A topic name written anywhere else is a bug (tests/test_layers.py looks for them).

**Input topics** (:data:`INPUTS`; relative names, as the node subscribes to them and as an input
bag holds them): ``navigation``, ``<view>/image_strip`` and ``<view>/scanner_info`` per view
(:func:`strip_topic`, :func:`scanner_info_topic`), ``gcp``, ``pairs`` and ``truth/points``.
**Output topics** (:data:`OUTPUTS`, the one table of them): what the node publishes and
``parproj process`` records, in that order; the conversion dispatch
(``parproj_ros.ros.conversions.outputs_to_messages``), the output bags' topics
(``BagWriter.add_topics``) and docs/node.md's topic tables (:func:`published_markdown`,
``python -m parproj_ros.core.contract --write .``) are made from it.

**QoS** as plain data (:class:`Qos`): ``Topic.qos`` is what the node uses (its subscription of
an input, its publisher of an output), ``Topic.recorded`` the offered profile a bag records
for the topic (a key of :data:`BAG_QOS`). ``parproj_ros.ros.conversions.qos_profile`` makes
the rclpy profile.

**Frame ids**:

- the *object frame* (local Cartesian, metres, Z up): the ``header.frame_id`` of the first
  message of :data:`FRAME_TOPICS` that names one, unless the user gives one; :data:`DEFAULT_FRAME`
  (``map``, a simulated bag's) when none does; an imported real pair's is
  ``enu_wgs84:lat=...,lon=...,h=...`` (:mod:`parproj_ros.core.frames`,
  ``parproj_ros.io.scene_import.frame_id_of``). Every output is labelled with it;
- ``navigation``: ``child_frame_id`` :data:`BODY_FRAME` (the velocity is in it);
- ``<view>/image_strip``: ``header.frame_id`` is the *scene id* (one acquisition), not a frame;
- a normalized image, block, disparity or height image of side ``s``: ``<object frame>/
  normalized_<s>`` (:func:`normalized_frame`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

from .frames import DEFAULT_FRAME

__all__ = [
    "ANAGLYPH",
    "BAG_QOS",
    "BODY_FRAME",
    "DEFAULT_FRAME",
    "DIAGNOSTICS",
    "DISPARITY",
    "DSM",
    "DSM_CLOUD",
    "DSM_FUSED",
    "DSM_FUSED_CLOUD",
    "DSM_QUICKLOOK_TILE",
    "DSM_TILE",
    "FRAME_TOPICS",
    "GCP",
    "HEIGHT",
    "IMAGE_STRIP",
    "INPUTS",
    "INPUT_TYPES",
    "NAVIGATION",
    "OBJECT_FRAME",
    "OUTPUTS",
    "OUTPUT_TOPICS",
    "PAIRS",
    "PAIR_IMAGE_TOPICS",
    "PARALLEL_PROJECTION",
    "SCANNER_INFO",
    "SIDES",
    "STEREO_PAIR",
    "TRUTH_POINTS",
    "VIEW",
    "Qos",
    "Topic",
    "fully_qualified",
    "image_topics",
    "input_topics",
    "normalized_block_topic",
    "normalized_frame",
    "normalized_image_topic",
    "published_markdown",
    "scanner_info_topic",
    "stream_topics",
    "strip_topic",
    "subscribed_markdown",
    "topic",
    "view_of",
]

# ---- QoS -----------------------------------------------------------------------------------

Reliability = Literal["reliable", "best_effort"]
Durability = Literal["volatile", "transient_local"]


@dataclass(frozen=True)
class Qos:
    """A QoS profile as plain data (history is always keep-last; the rest is RMW's default).

    Attributes:
        reliability: ``reliable`` or ``best_effort``.
        durability: ``volatile`` or ``transient_local`` (latched: a late joiner gets the last
            ``depth`` messages).
        depth: history depth, messages.
        why: the reason for this choice.
    """

    reliability: Reliability
    durability: Durability
    depth: int
    why: str

    @property
    def text(self) -> str:
        """For people: ``best effort, volatile, depth 500``."""
        return (
            f"{self.reliability.replace('_', ' ')}, {self.durability.replace('_', ' ')}, "
            f"depth {self.depth}"
        )

    def as_dict(self) -> dict[str, str | int]:
        """history, depth, reliability, durability (rosbag2's names for them)."""
        return {
            "history": "keep_last",
            "depth": self.depth,
            "reliability": self.reliability,
            "durability": self.durability,
        }


#: The node's subscription of navigation.
NAVIGATION_QOS = Qos(
    "best_effort",
    "volatile",
    500,
    "sensor data (REP 2003: best effort, volatile); a deep queue, so that a burst of samples "
    "waits while the worker is busy; qos_overrides./navigation.subscription.reliability can make "
    "it reliable for a lossless replay",
)
#: The node's subscription of each view's strips.
STRIP_QOS = Qos(
    "best_effort",
    "volatile",
    200,
    "sensor data (REP 2003: best effort, volatile); a deep queue, since a strip lost is a gap in "
    "a scene; qos_overrides./<view>/image_strip.subscription.reliability makes it reliable for "
    "a lossless replay",
)
#: The node's subscriptions of GCP and of the pair selection.
LATCHED_INPUT_QOS = Qos(
    "reliable",
    "transient_local",
    10,
    "reliable and transient local, so that a set published before the node started (a ground "
    "station's latched set) still arrives",
)
#: The node's publishers of its outputs (``/diagnostics`` included: rclpy's depth-10 default).
OUTPUT_QOS = Qos(
    "reliable",
    "volatile",
    10,
    "reliable, so that every scene's parameters and every pair reach recorders",
)
#: The node's publishers of per-scene and per-pair results a late subscriber still needs
#: (parameters, pairs, DSMs): transient local, the last ``latched_depth`` kept.
LATCHED_OUTPUT_QOS = Qos(
    "reliable",
    "transient_local",
    10,
    "reliable and transient local, so that a subscriber started after the pass (a map server, "
    "a viewer) still gets the last results; depth: the latched_depth parameter",
)

#: Offered profiles a bag records for a topic (``BagWriter.add_topic``'s ``qos``): the rclpy
#: defaults ``QoSProfile(depth=10)``, ``qos_profile_sensor_data``, and a latched depth-1 topic.
BAG_QOS: dict[str, Qos] = {
    "reliable": Qos("reliable", "volatile", 10, "rclpy's QoSProfile(depth=10)"),
    "sensor_data": Qos(
        "best_effort", "volatile", 5, "rclpy's qos_profile_sensor_data (a sensor's stream)"
    ),
    "transient_local": Qos(
        "reliable", "transient_local", 1, "latched: sent once, a late subscriber gets it"
    ),
}

# ---- names ---------------------------------------------------------------------------------

#: The placeholder for a view's name in :data:`INPUTS` (``<view>/image_strip``).
VIEW = "<view>"
#: The two sides of a normalized pair (output topics per side).
SIDES = ("left", "right")

NAVIGATION = "navigation"
#: The suffix of a view's strips (:func:`strip_topic`).
IMAGE_STRIP = "image_strip"
#: The suffix of a view's camera (:func:`scanner_info_topic`).
SCANNER_INFO = "scanner_info"
GCP = "gcp"
PAIRS = "pairs"
TRUTH_POINTS = "truth/points"

PARALLEL_PROJECTION = "parallel_projection"
STEREO_PAIR = "stereo_pair"
ANAGLYPH = "anaglyph"
DISPARITY = "disparity"
HEIGHT = "height"
DSM = "dsm"
DSM_CLOUD = "dsm_cloud"
DSM_TILE = "dsm_tile"
DSM_QUICKLOOK_TILE = "dsm_quicklook_tile"
DSM_FUSED = "dsm_fused"
DSM_FUSED_CLOUD = "dsm_fused_cloud"
OBJECT_FRAME = "object_frame"
DIAGNOSTICS = "/diagnostics"

#: The child (body) frame of navigation.
BODY_FRAME = "base_link"


def strip_topic(view: str) -> str:
    """A view's strips: ``<view>/image_strip``."""
    return f"{view}/{IMAGE_STRIP}"


def scanner_info_topic(view: str) -> str:
    """A view's camera: ``<view>/scanner_info``."""
    return f"{view}/{SCANNER_INFO}"


def normalized_image_topic(side: str) -> str:
    """A whole normalized image: ``<side>/image_normalized`` (side ``left`` or ``right``)."""
    return f"{side}/image_normalized"


def normalized_block_topic(side: str) -> str:
    """A streamed pair's column blocks: ``<side>/normalized_block``."""
    return f"{side}/normalized_block"


def normalized_frame(frame_id: str, side: str) -> str:
    """The frame of a normalized image of ``side`` in the object frame ``frame_id``."""
    return f"{frame_id}/normalized_{side}"


def fully_qualified(name: str) -> str:
    """``navigation`` -> ``/navigation`` (the node in the root namespace; ``qos_overrides``)."""
    return "/" + name.lstrip("/")


def view_of(name: str, suffix: str = IMAGE_STRIP) -> str | None:
    """The view of a per-view topic (``left/image_strip`` -> ``left``), None if not one."""
    head, sep, tail = name.lstrip("/").rpartition("/")
    return head if sep and tail == suffix and head and "/" not in head else None


# ---- the tables ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Topic:
    """One topic of the contract.

    Attributes:
        name: the relative topic name (``<view>/...`` for one per view, :data:`VIEW`).
        msgtype: the message type (``pkg/msg/Name``).
        qos: the node's profile for it: its subscription (input) or publisher (output).
        recorded: the offered profile a bag records for it (a key of :data:`BAG_QOS`).
        description: one line: what it holds.
        carries: an output's result (:mod:`parproj_ros.core.results`); for an input, who
            reads it.
        subscribed: an input the node subscribes to (the others are read from bags only).
        images: carries images (an output bag's ``image_compression`` applies).
    """

    name: str
    msgtype: str
    qos: Qos
    recorded: str
    description: str
    carries: str = ""
    subscribed: bool = True
    images: bool = False

    def for_view(self, view: str) -> Topic:
        """The row with :data:`VIEW` replaced by ``view``."""
        return replace(self, name=self.name.replace(VIEW, view))


_ODOMETRY = "nav_msgs/msg/Odometry"
_IMAGE = "sensor_msgs/msg/Image"
_POINTS = "parproj_msgs/msg/GroundControlPoints"
_GRID = "parproj_msgs/msg/ElevationGrid"
_BLOCK = "parproj_msgs/msg/NormalizedBlock"
_CLOUD = "sensor_msgs/msg/PointCloud2"

#: Input topics, in the order a simulated input bag declares them.
INPUTS: tuple[Topic, ...] = (
    Topic(
        NAVIGATION,
        _ODOMETRY,
        NAVIGATION_QOS,
        "sensor_data",
        "platform pose in the object frame (local Cartesian, Z up, m) and velocity in the child "
        "(body) frame",
        "the pipeline (scene parameters from navigation, streaming)",
    ),
    Topic(
        strip_topic(VIEW),
        _IMAGE,
        STRIP_QOS,
        "sensor_data",
        "blocks of scan lines (mono8, mono16, 32FC1); stamp = first line's exposure; frame_id = "
        "scene id",
        "the pipeline (scenes)",
    ),
    Topic(
        scanner_info_topic(VIEW),
        "parproj_msgs/msg/ScannerInfo",
        LATCHED_INPUT_QOS,
        "transient_local",
        "the view's line camera, once",
        "bags only: the cameras of parproj process (the node takes them as parameters)",
        subscribed=False,
    ),
    Topic(
        GCP,
        _POINTS,
        LATCHED_INPUT_QOS,
        "transient_local",
        "GCP and check points with their image observations per scene",
        "the pipeline (scene parameters from GCP)",
    ),
    Topic(
        PAIRS,
        "parproj_msgs/msg/PairSelection",
        LATCHED_INPUT_QOS,
        "transient_local",
        "single-camera mode: which acquisitions (scene ids) pair up, a scene possibly in "
        'several pairs; absent: 2k and 2k+1 (see "Pair selection" above)',
        "the pipeline (pairing)",
    ),
    Topic(
        TRUTH_POINTS,
        _POINTS,
        LATCHED_INPUT_QOS,
        "transient_local",
        "exact points for the evaluation",
        "bags only: parproj evaluate",
        subscribed=False,
    ),
)

#: Output topics, in the order the node creates its publishers and a bag declares them.
OUTPUTS: tuple[Topic, ...] = (
    Topic(
        PARALLEL_PROJECTION,
        "parproj_msgs/msg/ParallelProjection",
        LATCHED_OUTPUT_QOS,
        "transient_local",
        "per scene: L M N, omega phi kappa, s, dx dy, A1..A8, roll, scene frame, method, "
        "sigma0, residuals, covariance",
        "`Outputs.scenes` (`SceneResult`)",
    ),
    Topic(
        STEREO_PAIR,
        "parproj_msgs/msg/StereoPair",
        LATCHED_OUTPUT_QOS,
        "transient_local",
        "both normalized images and parameters, the 2x3 normalization affines, output grids, "
        "x-parallax -> height, y-parallax statistics",
        "`Outputs.pairs` (`PairResult`)",
        images=True,
    ),
    *(
        Topic(
            normalized_image_topic(side),
            _IMAGE,
            OUTPUT_QOS,
            "reliable",
            f"the {side} normalized image of a pair made whole; both sides have identical stamps "
            "(the pair's last line)",
            f"`PairResult.{side}_image`",
            images=True,
        )
        for side in SIDES
    ),
    Topic(
        ANAGLYPH,
        _IMAGE,
        OUTPUT_QOS,
        "reliable",
        "(rgb8) red = left, cyan = right",
        "`PairResult.left_image`, `PairResult.right_image`",
        images=True,
    ),
    *(
        Topic(
            normalized_block_topic(side),
            _BLOCK,
            OUTPUT_QOS,
            "reliable",
            f"streaming mode: column blocks of the {side} normalized image (full height), with "
            "their position in the full image",
            f"`Outputs.blocks` (`BlockResult`, side {side})",
            images=True,
        )
        for side in SIDES
    ),
    Topic(
        DISPARITY,
        "stereo_msgs/msg/DisparityImage",
        OUTPUT_QOS,
        "reliable",
        "`heights` on: the pair's dense disparity `col_left - col_right` (32FC1, left "
        "normalized grid, 1/16 px steps); invalid pixels hold `min_disparity - 1` (below the "
        "searched range, as the message defines); `f` and `t` are 0: a push-broom pair has no "
        "focal length and baseline, its heights are linear in disparity (below)",
        "`HeightsResult.disparity` (`Outputs.heights`)",
    ),
    Topic(
        HEIGHT,
        _IMAGE,
        OUTPUT_QOS,
        "reliable",
        "`heights` on: `Z = a d + b` per left normalized pixel, metres in the object frame, "
        "NaN invalid (rviz and Foxglove show an Image, not a DisparityImage)",
        "`HeightsResult.height` (`Outputs.heights`)",
    ),
    Topic(
        DSM,
        _GRID,
        LATCHED_OUTPUT_QOS,
        "transient_local",
        "`heights` on: the DSM on a north-up grid of the object frame (origin, cell size, "
        "heights 32FC1 with NaN holes) and the ortho-image on the same grid; a message of our "
        'own (see "Heights"); it names the terrain searched and where it came from '
        "(`terrain_min_m`, `terrain_max_m`, `terrain_source`, `terrain_points`)",
        "`HeightsResult.dsm`, `HeightsResult.ortho` (`Outputs.heights`)",
    ),
    Topic(
        DSM_CLOUD,
        _CLOUD,
        LATCHED_OUTPUT_QOS,
        "transient_local",
        "`heights` on and `dsm_cloud_step` not 0: the same DSM for viewers (RViz, Foxglove): one "
        "point per DSM cell with a height, every `dsm_cloud_step`-th row and column (-1: the "
        "least step giving at most 2 M points), fields x y z intensity (float32; x y z the "
        "cell centre and its height, metres in the object frame; intensity the ortho-image's "
        "value); NaN cells left out (`is_dense`, one row)",
        "`HeightsResult.dsm`, `HeightsResult.ortho` (`Outputs.heights`)",
    ),
    Topic(
        DSM_TILE,
        _GRID,
        OUTPUT_QOS,
        "reliable",
        "`heights` on, streaming (two views, `scene_lines`), `heights_quicklook` >= 0: the "
        "streamed pair's DSM tile by tile while its blocks arrive, each final when published "
        "(`pair_id` `<pair>#<index>/<count>`; a span of 256 left columns matched as soon as "
        "both sides cover it plus the disparity margin; the cells it owns on the pair's one "
        "grid, NaN elsewhere, so the tiles assembled are the pair's DSM without seams; "
        "`parproj_ros/core/tiles.py`); a pair whose stream breaks ends with an ERROR on "
        "`/diagnostics`",
        "`Outputs.tiles` (`HeightTile`, factor 1)",
    ),
    Topic(
        DSM_QUICKLOOK_TILE,
        _GRID,
        OUTPUT_QOS,
        "reliable",
        "`heights` on, streaming, `heights_quicklook` 1, 2, 3 (or -1, -2, -3: instead of "
        "`dsm_tile`): the same tiles made on the normalized blocks reduced by 2, 4, 8 "
        "(`pair_id` `<pair>#<index>/<count>@<factor>`; cells that factor times the DSM's)",
        "`Outputs.tiles` (`HeightTile`, factor 2, 4 or 8)",
    ),
    Topic(
        DSM_FUSED,
        _GRID,
        LATCHED_OUTPUT_QOS,
        "transient_local",
        "`heights` on and `heights_fuse_mb` > 0: each time a pair's DSM overlaps the kept DSMs "
        "of earlier pairs (three views of one place, repeated passes), their fusion on one grid "
        "(`pair_id` `fused:<pair>,<pair>,...`; heights only: per cell the weighted mean of the "
        "samples near their median, after the pairs' level offsets; `parproj_ros/core/fusion.py`)"
        "; the offsets before and after on `/diagnostics`",
        "`Outputs.fused` (`FusedResult`)",
    ),
    Topic(
        DSM_FUSED_CLOUD,
        _CLOUD,
        LATCHED_OUTPUT_QOS,
        "transient_local",
        "`dsm_fused` as `dsm_cloud` is `dsm`: fields x y z (no ortho-image), same decimation",
        "`Outputs.fused` (`FusedResult`)",
    ),
    Topic(
        OBJECT_FRAME,
        "geometry_msgs/msg/TransformStamped",
        LATCHED_OUTPUT_QOS,
        "transient_local",
        "where the outputs' object frame lies on Earth, once it is known and only when it has a "
        "place on Earth (an imported pair's `enu_wgs84:...` plane): the transform from `earth` "
        "(ECEF, REP 105) to it; its definition in words on `/diagnostics` (tf2_msgs has no wheel "
        "here, so it is not on `/tf_static`)",
        "`io/earth.EarthTransform`",
    ),
    Topic(
        DIAGNOSTICS,
        "diagnostic_msgs/msg/DiagnosticArray",
        OUTPUT_QOS,
        "reliable",
        "one status per problem, and a 1 Hz summary (level and values: see above)",
        "`Outputs.issues` (`Issue`)",
    ),
)

#: Output topics and their types (node and offline process alike), in :data:`OUTPUTS`' order.
OUTPUT_TOPICS: dict[str, str] = {t.name: t.msgtype for t in OUTPUTS}
#: Input topics and their types, ``<view>`` as ``*`` (the pattern the bag checks match).
INPUT_TYPES: dict[str, str] = {t.name.replace(VIEW, "*"): t.msgtype for t in INPUTS}
#: The images of a pair sent whole, published after its StereoPair (a streamed pair's pixels
#: come before it, as NormalizedBlock messages).
PAIR_IMAGE_TOPICS = (*(normalized_image_topic(s) for s in SIDES), ANAGLYPH)
#: Input topics whose header.frame_id names the object frame, in the order they are read.
FRAME_TOPICS = (GCP, TRUTH_POINTS, NAVIGATION)


def image_topics() -> tuple[str, ...]:
    """The output topics that carry images (an output bag's ``image_compression``)."""
    return tuple(t.name for t in OUTPUTS if t.images)


def topic(name: str) -> Topic:
    """The contract's row of a topic (a per-view input's row for that view).

    Raises:
        KeyError: not a topic of the contract.
    """
    bare = name.lstrip("/")
    for t in OUTPUTS:
        if t.name.lstrip("/") == bare:
            return t
    for t in INPUTS:
        if t.name == bare:
            return t
        suffix = t.name.removeprefix(VIEW + "/")
        if suffix != t.name and view_of(bare, suffix) is not None:
            return t.for_view(bare.rpartition("/")[0])
    raise KeyError(f"{name!r} is not a topic of the contract (parproj_ros/core/contract.py)")


def input_topics(
    views: Iterable[str], *, navigation: bool = True, truth: bool = True
) -> list[Topic]:
    """An input bag's topics, in the order they are declared.

    Navigation (``navigation``), each view's strips and camera, GCP, and the truth points
    (``truth``).
    """
    rows = [topic(NAVIGATION)] if navigation else []
    for v in views:
        rows += [topic(strip_topic(v)), topic(scanner_info_topic(v))]
    rows.append(topic(GCP))
    if truth:
        rows.append(topic(TRUTH_POINTS))
    return rows


def stream_topics(views: Iterable[str]) -> list[str]:
    """The node's streamed inputs: navigation, each view's strips.

    Their QoS may be changed by ``qos_overrides.<topic>`` (a reliable, lossless replay).
    """
    return [NAVIGATION, *(strip_topic(v) for v in views)]


# ---- docs/node.md's tables -----------------------------------------------------------------


def _type_text(msgtype: str) -> str:
    return msgtype.replace("/msg/", "/")


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def subscribed_markdown() -> str:
    """docs/node.md's Subscribed topics table (markdown, ends with a newline)."""
    rows = ["| topic | type | QoS | meaning |", "|---|---|---|---|"]
    for t in INPUTS:
        if t.subscribed:
            name = f"`{t.name}` (one per view)" if VIEW in t.name else f"`{t.name}`"
            rows.append(
                f"| {name} | {_type_text(t.msgtype)} | {t.qos.text} | {_cell(t.description)} |"
            )
    return "\n".join(rows) + "\n"


def published_markdown() -> str:
    """docs/node.md's Published topics table (markdown, ends with a newline)."""
    rows = ["| topic | type | QoS | meaning | result |", "|---|---|---|---|---|"]
    for t in OUTPUTS:
        rows.append(
            f"| `{t.name}` | {_type_text(t.msgtype)} | {t.qos.text} | {_cell(t.description)} "
            f"| {_cell(t.carries)} |"
        )
    return "\n".join(rows) + "\n"


#: The page holding the generated tables, relative to the repository.
NODE_DOC = "docs/node.md"
#: (begin marker, end marker, table) of each generated table in :data:`NODE_DOC`.
DOC_TABLES = (
    (
        "<!-- subscribed topics: generated from parproj_ros/core/contract.py "
        "(subscribed_markdown) -->",
        "<!-- end of subscribed topics -->",
        subscribed_markdown,
    ),
    (
        "<!-- published topics: generated from parproj_ros/core/contract.py "
        "(published_markdown) -->",
        "<!-- end of published topics -->",
        published_markdown,
    ),
)


def doc_with_tables(text: str) -> str:
    """``text`` (docs/node.md) with the text between each pair of markers regenerated.

    Raises:
        ValueError: a marker is missing, repeated or out of order.
    """
    for begin_mark, end_mark, table in DOC_TABLES:
        begin, end = text.find(begin_mark), text.find(end_mark)
        if text.count(begin_mark) != 1 or text.count(end_mark) != 1 or end < begin:
            raise ValueError(f"{NODE_DOC} needs the lines {begin_mark!r} and {end_mark!r}")
        text = f"{text[: begin + len(begin_mark)]}\n{table()}{text[end:]}"
    return text


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m parproj_ros.core.contract``: print the topic tables, or rewrite the doc's."""
    parser = argparse.ArgumentParser(
        prog="python -m parproj_ros.core.contract", description="the topic tables of docs/node.md"
    )
    parser.add_argument("--write", metavar="REPO", help="rewrite REPO/docs/node.md's tables")
    args = parser.parse_args(argv)
    if args.write:
        doc = Path(args.write) / NODE_DOC
        try:
            doc.write_text(doc_with_tables(doc.read_text()))
        except (OSError, ValueError) as err:
            print(f"{parser.prog}: --write {args.write}: {err}", file=sys.stderr)
            return 2
        print(f"wrote {doc}")
    else:
        sys.stdout.write(subscribed_markdown() + "\n" + published_markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
