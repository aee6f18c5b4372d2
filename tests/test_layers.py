"""The package's layering, read from the source (README "Architecture").

Every module's imports are parsed with ``ast``: module level, inside functions and classes, and
under ``if TYPE_CHECKING:``. All three count as dependencies, for cycles too: an import moved into
a function (or under TYPE_CHECKING) to dodge a circular import only hides the cycle; the two
modules still cannot be read, tested or layered apart. The implicit import of a package's
``__init__`` when one of its submodules is imported is not counted (``geometry/__init__.py``
re-exports its submodules, which import one another by their own names).

Layers, bottom up (:data:`LAYERS`): ``geometry/`` (numpy, scipy, the standard library),
``imaging/``, ``rpc/``, ``core/`` (the ROS-free core), ``io/``, the message types, ``sim/``, the
node (``ros/``), ``eval/`` and ``apps/``. Only ``ros/`` and ``apps/`` (and ``tools/``, not checked
here) import rclpy; the simulator's recorders (:data:`MESSAGE_MODULES`) build messages too.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "parproj_ros"

#: Where rclpy may be imported: the ROS 2 side and the applications (and ``tools/``, not checked
#: here).
RCLPY_PACKAGES = ("parproj_ros.ros", "parproj_ros.apps")
#: Besides those, the modules that build ROS messages without rclpy: the simulator's recorders.
MESSAGE_MODULES = {
    "parproj_ros.sim.recording",  # simulated acquisitions recorded to bags
    "parproj_ros.sim.synthetic",  # the benchmark's acquisition as messages
}

#: The layers, bottom up (README "Architecture"): a module imports only modules of its own layer
#: or of lower ones. Packages count with every module in them (the longest entry wins). A new
#: module goes in one.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("geometry", ("parproj_ros.geometry",)),  # the papers' equations: numpy, scipy
    ("imaging", ("parproj_ros.imaging",)),  # scenes from strips, resampling, matching
    ("rpc", ("parproj_ros.rpc",)),  # RPC sensor models and their files
    ("core", ("parproj_ros.core",)),  # parameters, results, the pipeline
    ("io", ("parproj_ros.io",)),  # GCP files, DEM, rasters, safe files (no ROS)
    (
        "messages",
        (
            "parproj_ros.ros.conversions",
            "parproj_ros.ros.bag",
            "parproj_ros.ros.cdr",
            "parproj_ros.ros.inputs",
        ),
    ),
    ("sim", ("parproj_ros.sim",)),  # the simulator and its recordings
    ("ros", ("parproj_ros.ros",)),  # the node, the live graph
    ("eval", ("parproj_ros.eval",)),  # evaluation, paper, reference grids
    ("apps", ("parproj_ros.apps", "parproj_ros")),  # commands; the package (its version)
)
#: What the ROS-free core (geometry, imaging, core) may import besides itself.
CORE_THIRD_PARTY = {"numpy", "scipy", "cv2", "tifffile"}


@dataclass(frozen=True)
class Import:
    """One imported module: where (file, line), how (module, function, type_checking)."""

    source: str
    target: str
    line: int
    how: str


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def layer_of(module: str) -> int | None:
    """Index in :data:`LAYERS` of a module (the longest matching entry), None if in none."""
    best: tuple[int, int] | None = None
    for k, (_, names) in enumerate(LAYERS):
        for n in names:
            if module == n or (module.startswith(n + ".") and n != "parproj_ros"):
                if best is None or len(n) > best[1]:
                    best = (k, len(n))
    return None if best is None else best[0]


CORE_LAYER = 3
#: The ROS-free core: every module of the geometry, imaging, rpc and core layers.
CORE = tuple(m for m in MODULES if layer_of(m) is not None and layer_of(m) <= CORE_LAYER)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _resolve(name: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module of a ``from ... import`` (relative levels resolved)."""
    if node.level == 0:
        return node.module or ""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    base = package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(name: str) -> list[Import]:
    """Every import of module ``name``; a ``from pkg import sub`` of a submodule names it."""
    path = MODULES[name]
    found: list[Import] = []

    def visit(node: ast.AST, how: str) -> None:
        for child in ast.iter_child_nodes(node):
            inner = how
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                inner = "function"
            if isinstance(child, ast.If) and _is_type_checking(child.test) and how == "module":
                for stmt in child.body:
                    visit_stmt(stmt, "type_checking")
                for stmt in child.orelse:
                    visit_stmt(stmt, how)
                continue
            visit_stmt(child, inner)

    def visit_stmt(stmt: ast.AST, how: str) -> None:
        if isinstance(stmt, ast.Import):
            for alias in stmt.names:
                found.append(Import(name, alias.name, stmt.lineno, how))
        elif isinstance(stmt, ast.ImportFrom):
            base = _resolve(name, path, stmt)
            for alias in stmt.names:
                sub = f"{base}.{alias.name}"
                found.append(Import(name, sub if sub in MODULES else base, stmt.lineno, how))
        else:
            visit(stmt, how)

    visit(ast.parse(path.read_text(), str(path)), "module")
    return found


ALL_IMPORTS = {name: imports_of(name) for name in MODULES}


def _is_ros(target: str) -> bool:
    top = target.split(".")[0]
    return (
        top == "rclpy"
        or top.startswith(("rosidl", "rcl_", "rosbag2"))
        or top.endswith(("_msgs", "_interfaces"))
    )


def _where(imp: Import) -> str:
    return f"{MODULES[imp.source].relative_to(ROOT)}:{imp.line} ({imp.how})"


def test_the_parser_sees_every_kind_of_import() -> None:
    """A sanity check of :func:`imports_of` on modules known to hold each kind."""
    node = {(i.target, i.how) for i in ALL_IMPORTS["parproj_ros.ros.node"]}
    assert ("rclpy.node", "module") in node
    assert ("parproj_ros.ros.conversions", "module") in node  # `from . import conversions as conv`
    assert ("parproj_ros.core.session", "module") in node
    startup = {(i.target, i.how) for i in ALL_IMPORTS["parproj_ros.ros.startup"]}
    assert ("rclpy", "module") in startup
    assert ("rclpy.duration", "function") in startup
    geometry = {i.target for i in ALL_IMPORTS["parproj_ros.geometry"]}
    assert "parproj_ros.geometry.epipolar" in geometry
    resample = {(i.target, i.how) for i in ALL_IMPORTS["parproj_ros.imaging.resample"]}
    assert ("parproj_ros.geometry.ptp", "function") in resample


def _cycles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), and self-imports."""
    graph = {
        name: sorted({i.target for i in imps if i.target in MODULES})
        for name, imps in ALL_IMPORTS.items()
    }
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph[v]:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            strong(v)
    return out


def test_no_import_cycles() -> None:
    """No module depends on itself through others (module, function or TYPE_CHECKING imports)."""
    problems = []
    for comp in _cycles():
        edges = [
            f"  {i.source} -> {i.target} at {_where(i)}"
            for name in comp
            for i in ALL_IMPORTS[name]
            if i.target in comp
        ]
        problems.append("cycle among " + ", ".join(comp) + ":\n" + "\n".join(edges))
    assert not problems, "\n".join(problems)


def _may_import_rclpy(module: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in RCLPY_PACKAGES)


def test_rclpy_only_in_ros_and_apps() -> None:
    """rclpy only in ros/ and apps/; message packages there and in :data:`MESSAGE_MODULES`."""
    outside = [
        f"{i.target} in {_where(i)}"
        for name, imps in ALL_IMPORTS.items()
        if not _may_import_rclpy(name)
        for i in imps
        if _is_ros(i.target) and (i.target.split(".")[0] == "rclpy" or name not in MESSAGE_MODULES)
    ]
    assert not outside, "ROS imports outside ros/, apps/ and MESSAGE_MODULES:\n" + "\n".join(
        outside
    )
    stale = sorted(
        m for m in MESSAGE_MODULES if not any(_is_ros(i.target) for i in ALL_IMPORTS[m])
    )
    assert not stale, f"in MESSAGE_MODULES but importing no ROS package (remove them): {stale}"
    assert any(_is_ros(i.target) for i in ALL_IMPORTS["parproj_ros.ros.node"])


def test_geometry_imports_only_numpy_scipy_stdlib() -> None:
    allowed = set(sys.stdlib_module_names) | {"numpy", "scipy"}
    bad = [
        f"{i.target} in {_where(i)}"
        for name, imps in ALL_IMPORTS.items()
        if name == "parproj_ros.geometry" or name.startswith("parproj_ros.geometry.")
        for i in imps
        if not i.target.startswith("parproj_ros.geometry")
        and i.target.split(".")[0] not in allowed
    ]
    assert not bad, "geometry/ imports outside numpy, scipy and the standard library:\n" + (
        "\n".join(bad)
    )


def _in_core(target: str) -> bool:
    layer = layer_of(target)
    return layer is not None and layer <= CORE_LAYER


def test_every_module_has_a_layer() -> None:
    missing = sorted(m for m in MODULES if layer_of(m) is None)
    assert not missing, f"modules in no layer (add them to LAYERS, and README): {missing}"
    assert "parproj_ros.core.pipeline" in CORE and "parproj_ros.geometry.rotation" in CORE


def test_imports_go_down_the_layers() -> None:
    """A module imports modules of its own layer or of lower ones (any kind of import)."""
    layer = {m: layer_of(m) or 0 for m in MODULES}  # (a module in none fails above)
    names = [n for n, _ in LAYERS]
    up = [
        f"{i.source} ({names[layer[i.source]]}) -> {i.target} ({names[layer[i.target]]}) "
        f"at {_where(i)}"
        for imps in ALL_IMPORTS.values()
        for i in imps
        if i.target in MODULES and layer[i.target] > layer[i.source]
    ]
    assert not up, "imports up the layers:\n" + "\n".join(up)


def test_every_module_is_under_strict_mypy() -> None:
    """setup.cfg's mypy runs strict on every module of the package (the node included): its
    ``files`` name the package whole or a folder or file holding each module, and no section
    relaxes a parproj_ros module's checks (an ``ignore_errors`` or a silenced import)."""
    import configparser

    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    assert cfg.getboolean("mypy", "strict")
    files = [f.strip().rstrip("/") for f in cfg.get("mypy", "files").split(",")]
    uncovered = [
        m
        for m, path in MODULES.items()
        if not any(
            path.relative_to(ROOT).as_posix() == f or path.relative_to(ROOT).is_relative_to(f)
            for f in files
        )
    ]
    assert not uncovered, f"modules outside strict mypy: {uncovered}"
    relaxed = [
        f"[{name}] {key}"
        for name in cfg.sections()
        if name.startswith("mypy-parproj_ros")
        for key in ("ignore_errors", "follow_imports")
        if cfg.has_option(name, key)
    ]
    assert not relaxed, f"relaxed for the package: {relaxed}"


def test_the_node_and_the_bags_need_no_simulator() -> None:
    """The node, the live graph and the bag contract import nothing of the simulator: what they
    read of a bag is the contract's reader (ros/inputs.py), beside the bag code."""
    found = [
        f"{i.source} -> {i.target} at {_where(i)}"
        for name, imps in ALL_IMPORTS.items()
        if name.startswith("parproj_ros.ros")
        for i in imps
        if i.target.startswith("parproj_ros.sim")
    ]
    assert not found, "the ROS side imports the simulator:\n" + "\n".join(found)


def test_core_imports_only_core() -> None:
    """The core (geometry, imaging, results, pipeline, ...) imports no adapter or application."""
    allowed = set(sys.stdlib_module_names) | CORE_THIRD_PARTY
    bad = [
        f"{i.target} in {_where(i)}"
        for name, imps in ALL_IMPORTS.items()
        if _in_core(name)
        for i in imps
        if not _in_core(i.target) and i.target.split(".")[0] not in allowed
    ]
    assert not bad, "the ROS-free core imports outside itself:\n" + "\n".join(bad)


# Runs in a fresh interpreter in which rclpy, rosidl and every *_msgs package fail to import.
WITHOUT_ROS = textwrap.dedent(
    """
    import importlib
    import sys


    class NoRos:
        @staticmethod
        def find_spec(name, path=None, target=None):
            top = name.split(".")[0]
            if (
                top == "rclpy"
                or top.startswith(("rosidl", "rcl_", "rosbag2"))
                or top.endswith(("_msgs", "_interfaces"))
            ):
                raise ImportError(f"{name}: ROS is not available in this test")
            return None


    sys.meta_path.insert(0, NoRos())
    try:
        import rclpy  # noqa: F401
    except ImportError:
        pass
    else:
        raise SystemExit("the ROS blocker does not work")
    for name in sys.argv[1:]:
        importlib.import_module(name)

    import numpy as np

    from parproj_ros.core.pipeline import Pipeline, PipelineConfig
    from parproj_ros.core.results import Level, Method
    from parproj_ros.sim.synthetic import acquisition, stereo_platform, texture_blocks
    from parproj_ros.core.trajectory import NavSample

    lines, dets, strip = 512, 256, 64
    # the aft camera sees the fore camera's ground some scenes later: base-to-height >= 0.005
    plat = stereo_platform(lines, dets)
    pipe = Pipeline(PipelineConfig(plat.views, scene_lines=lines, tie_points=False))
    (block,) = texture_blocks(1, lines, dets, seed=1)
    out = None
    for ev in acquisition(plat, 1, strip, 50.0):
        if ev.kind == "nav":
            s = NavSample(ev.stamp_ns, plat.position(ev.t_s), plat.body, plat.velocity)
            step = pipe.add_navigation(s)
        else:
            rows = block[ev.row0 : ev.row0 + ev.rows]
            step = pipe.add_strip(("left", "right")[ev.view], ev.stamp_ns, ev.scene_id, rows)
        out = step if out is None else (out.extend(step) or out)
    out.extend(pipe.flush())
    errors = [i for i in out.issues if i.level == Level.ERROR]
    assert not errors, errors
    assert len(out.pairs) == 1, out.issues
    assert {s.method for s in out.scenes[:2]} == {Method.NAVIGATION}, out.scenes
    assert out.blocks, "the pair was not streamed"
    rms = out.pairs[0].y_parallax_stats[1]
    assert rms < 0.05, rms
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("rclpy", "parproj_msgs"))
    assert not leaked, leaked
    print("ok", len(out.pairs), f"{rms:.4f}")
    """
)


def test_core_imports_and_runs_without_ros() -> None:
    """The core imports, and a streamed fore/aft pair is made, with every ROS import failing."""
    proc = subprocess.run(
        [sys.executable, "-c", WITHOUT_ROS, *CORE],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("ok 1"), proc.stdout


# ---- the interface contract: no topic name written outside core/contract.py --------------------

#: The one module that spells topic names (parproj_ros/core/contract.py).
CONTRACT = PACKAGE / "core" / "contract.py"
TOOLS = ROOT / "tools"
#: Files being rewritten now (issue 23: the node, the pipeline and its policies, ``parproj
#: process``) and migrated to the contract by their author afterwards: their literals are not
#: checked yet. Empty it as each one imports the contract (pipeline, streaming, pairing and
#: navigation had none left when it was written; node.py and process.py had some).
PENDING_CONTRACT: set[str] = set()

#: Names that are topics wherever they are written (a leading "/" aside).
TOPIC_ONLY_NAMES = {
    "stereo_pair",
    "parallel_projection",
    "normalized_block",
    "image_normalized",
    "image_strip",
    "scanner_info",
    "dsm_fused",
    "truth/points",
    "diagnostics",
}
#: Suffixes of per-view and per-side topics: ``left/image_strip``, f"{side}/normalized_block".
TOPIC_SUFFIXES = ("/image_strip", "/scanner_info", "/image_normalized", "/normalized_block")
#: Topic names that are also words of the results, parameters and reports ("navigation" is a
#: Method, "gcp" a source, "height" a field): topics only where used as one (below).
AMBIGUOUS_NAMES = {"navigation", "gcp", "pairs", "dsm", "height", "disparity", "anaglyph"}
#: Calls whose string arguments are topic names (bags, rclpy, the frame observer).
TOPIC_CALLS = {
    "add_topic",
    "write",
    "write_raw",
    "create_publisher",
    "create_subscription",
    "observe",
    "first_frame_id",
    "messages",
    "raw_messages",
}
#: Keyword arguments holding topic names besides ``*topic*``.
TOPIC_KEYWORDS = {"wait_for", "also", "reliable_inputs"}
#: Dictionaries keyed by topic besides ``*topic*`` ones (``counts["dsm"]``, ``sent.get(...)``).
TOPIC_KEYED = {"counts", "sent", "messages", "pubs", "images"}


def _is_topic_name(text: str, context: bool) -> bool:
    """Whether a string constant spells a topic (in a topic context when ``context``)."""
    from parproj_ros.core import contract

    bare = text.removeprefix("/")
    concrete = set(contract.OUTPUT_TOPICS) | {t.name for t in contract.INPUTS}
    if bare in TOPIC_ONLY_NAMES or (text in concrete and "/" in text):
        return True
    if bare.endswith(TOPIC_SUFFIXES) and bare.count("/") == 1 and " " not in bare:
        return True
    if text.startswith("/") and bare in {n.lstrip("/") for n in concrete}:
        return True  # fully qualified, "/navigation"
    return context and bare in AMBIGUOUS_NAMES


def _named_topic(node: ast.AST) -> bool:
    """An expression naming topics: ``x.topic``, ``topics``, ``reader.topics()``, ``topic_of``."""
    if isinstance(node, ast.Call):
        return _named_topic(node.func)
    name = node.id if isinstance(node, ast.Name) else getattr(node, "attr", None)
    return isinstance(name, str) and "topic" in name.lower()


def _keyed_by_topic(node: ast.AST) -> bool:
    name = node.id if isinstance(node, ast.Name) else getattr(node, "attr", None)
    return isinstance(name, str) and ("topic" in name.lower() or name in TOPIC_KEYED)


def _strings(node: ast.AST | None) -> list[ast.Constant]:
    if node is None:
        return []
    return [n for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def _topic_contexts(tree: ast.AST) -> set[int]:
    """ids of the string constants written where a topic goes (see :func:`topic_literals`)."""
    marked: set[int] = set()

    def mark(node: ast.AST | None) -> None:
        marked.update(id(c) for c in _strings(node))

    # lists iterated as topics (``for topic, cb in inputs``): what is put in them
    carriers = {
        node.iter.id
        for node in ast.walk(tree)
        if isinstance(node, ast.For)
        and isinstance(node.iter, ast.Name)
        and any(_named_topic(n) for n in ast.walk(node.target) if isinstance(n, ast.Name))
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id in carriers for t in targets):
                mark(node.value)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in ("append", "extend", "insert")
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id in carriers
        ):
            for a in node.args:
                mark(a)

    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if called in TOPIC_CALLS:
                for a in node.args:
                    if isinstance(a, ast.Constant | ast.JoinedStr):
                        mark(a)
            if called == "get" and isinstance(func, ast.Attribute) and node.args:
                if _keyed_by_topic(func.value):
                    mark(node.args[0])
            for kw in node.keywords:
                if kw.arg and ("topic" in kw.arg or kw.arg in TOPIC_KEYWORDS):
                    mark(kw.value)
        elif isinstance(node, ast.Subscript) and _keyed_by_topic(node.value):
            mark(node.slice)
        elif isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            if any(_named_topic(o) for o in operands):
                for o in operands:
                    mark(o)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(_named_topic(n) for t in targets for n in ast.walk(t)):
                mark(node.value)
        elif isinstance(node, ast.For | ast.comprehension):
            names = [n for n in ast.walk(node.target) if isinstance(n, ast.Name)]
            tested = [n for c in getattr(node, "ifs", []) for n in ast.walk(c)]
            loop_vars = {n.id for n in names}
            if any(_named_topic(n) for n in names) or any(
                isinstance(c, ast.Compare)
                and any(_named_topic(o) for o in [c.left, *c.comparators])
                and any(isinstance(o, ast.Name) and o.id in loop_vars for o in [c.left])
                for c in tested
            ):
                mark(node.iter)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            args = node.args
            positional = [*args.posonlyargs, *args.args]
            pairs = list(
                zip(positional[len(positional) - len(args.defaults) :], args.defaults, strict=True)
            )
            pairs += [
                (a, d)
                for a, d in zip(args.kwonlyargs, args.kw_defaults, strict=True)
                if d is not None
            ]
            for a, d in pairs:
                if "topic" in a.arg:
                    mark(d)
    return marked


def topic_literals(path: Path, root: Path = ROOT) -> list[str]:
    """Topic names spelt in ``path``: ``file:line: text``, docstrings left out.

    A string constant is a topic name when it is one wherever it is written (``stereo_pair``,
    ``left/image_strip``, ``/diagnostics``, ``truth/points``, ...), an f-string ending in a
    per-view or per-side suffix (f"{view}/image_strip"), or a word that is also a result or a
    parameter (``navigation``, ``gcp``, ``dsm``, ``height`` ...) written where a topic goes: an
    argument of ``add_topic``/``write``/``create_subscription``/..., a ``topic``/``topics``
    keyword or parameter default, compared with a ``.topic`` or ``reader.topics()``, a key of a
    dictionary of topics, a value given to or iterated as a ``topic`` variable.
    """
    tree = ast.parse(path.read_text(), str(path))
    docstrings = {
        id(n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)
    }
    in_fstring = {id(v) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr) for v in n.values}
    contexts = _topic_contexts(tree)
    rel = path.relative_to(root).as_posix()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            parts = [v.value for v in node.values if isinstance(v, ast.Constant)]
            tail = node.values[-1] if node.values else None
            if (
                isinstance(tail, ast.Constant)
                and isinstance(tail.value, str)
                and tail.value.endswith(TOPIC_SUFFIXES)
                and tail.value.count("/") == 1
            ):
                found.append(f"{rel}:{node.lineno}: f-string ...{''.join(map(str, parts))!r}")
        elif (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and id(node) not in docstrings
            and id(node) not in in_fstring
            and _is_topic_name(node.value, id(node) in contexts)
        ):
            found.append(f"{rel}:{node.lineno}: {node.value!r}")
    return sorted(set(found), key=lambda s: (s.split(":")[0], int(s.split(":")[1])))


def _code_files() -> list[Path]:
    return sorted(p for p in [*PACKAGE.rglob("*.py"), *TOOLS.rglob("*.py")] if p != CONTRACT)


def test_no_topic_literal_outside_the_contract() -> None:
    """Topic names are written once, in core/contract.py; everything else imports them."""
    found = {p.relative_to(ROOT).as_posix(): topic_literals(p) for p in _code_files()}
    spelt = [line for f, lines in found.items() if f not in PENDING_CONTRACT for line in lines]
    assert not spelt, (
        "topic names spelt outside parproj_ros/core/contract.py (use its names):\n"
        + "\n".join(spelt)
    )
    gone = sorted(f for f in PENDING_CONTRACT if f not in found)
    assert not gone, f"PENDING_CONTRACT names files that do not exist: {gone}"


def test_the_topic_check_sees_each_kind(tmp_path: Path) -> None:
    """:func:`topic_literals` on a file holding each kind of topic literal, and none."""
    src = tmp_path / "x.py"
    src.write_text(
        textwrap.dedent(
            '''
            """Docstring naming stereo_pair and left/image_strip: not code."""
            a = "stereo_pair"
            b = f"{view}/image_strip"
            c = "/diagnostics"
            bw.add_topic("dsm", "t", "reliable")
            if item.topic == "navigation":
                pass
            n = reader.messages(topics=["gcp"])
            def read(path, topic="height"):
                pass
            for topic, x in (("pairs", 1),):
                pass
            inputs = [("navigation", 1)]
            inputs.append(("gcp", 2))
            for topic, n in inputs:
                pass
            ok = ["gcp", "navigation", Method("height"), "anaglyph", "dsm_fused: prose"]
            Issue(Level.WARN, "navigation", "a report's label, not a topic")
            '''
        )
    )
    got = [line.split(":", 1)[1] for line in topic_literals(src, tmp_path)]
    assert got == [
        "3: 'stereo_pair'",
        "4: f-string ...'/image_strip'",
        "5: '/diagnostics'",
        "6: 'dsm'",
        "7: 'navigation'",
        "9: 'gcp'",
        "10: 'height'",
        "12: 'pairs'",
        "14: 'navigation'",
        "15: 'gcp'",
    ], got
