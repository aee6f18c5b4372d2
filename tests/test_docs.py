"""The docs name only what exists: modules, functions, classes, tests, files (issue 23, Docs).

Every markdown page a reader is sent to (README.md, RELIABILITY.md, bags/README.md, docs/*.md)
is read, and each of these must resolve in the repository:

- a module path, ``parproj_ros/.../x.py`` or a shorter one in backticks (``core/memory.py``,
  ``node.py``: some file of the package, the tests or the tools ends with it), and a dotted
  module, ``parproj_ros.x.y`` (anywhere in the text, code blocks included);
- a name written with its module in backticks: ``parproj_ros.core.param_docs.parameters_markdown``,
  ``core/memory.held_bytes``, ``gcp_file.load_gcp_file`` (a module's base name), or a class's
  attribute, ``Pipeline.add_strip``, ``ElevationGrid.filled_cells`` (a message field);
- a test named as ``tests/x/test_y.py::test_z`` (or ``test_y.py::test_z``);
- a relative link ``[text](path#anchor)``: the file, and the heading the anchor names.

Modules are parsed with :mod:`ast`, never imported: no ROS, fast. A backticked ``a.b`` whose
first part is neither a module, a class of the package, a message nor in :data:`FOREIGN` fails,
so that a module renamed or removed is caught instead of skipped.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOP_PAGES = [ROOT / "README.md", ROOT / "RELIABILITY.md", ROOT / "bags" / "README.md"]
PAGES = sorted([*TOP_PAGES, *(ROOT / "docs").glob("*.md")])
CODE_DIRS = ("parproj_ros", "tests", "tools")

#: First parts of backticked ``a.b`` names that are not ours: libraries, and variables or
#: settings the docs show in code (``np.abs(q)``, ``pan.detectors``).
FOREIGN = {
    "np",
    "numpy",
    "cv2",
    "scipy",
    "rclpy",
    "rasterio",
    "pyproj",
    "laspy",
    "mcap",
    "distributed",
    "dask",
    "contextlib",
    "pub",
    "pan",
    "left_params",
    "views",
    "qos_overrides",
    "src",
    "msg",
    "sys",
    "os",
    "time",
    "header",
}
#: Last parts that make ``a.b`` a file name, not a module attribute.
FILE_SUFFIXES = {
    "py", "md", "yaml", "yml", "json", "csv", "mcap", "xml", "tif", "tiff", "png", "txt", "hgt",
    "geom", "las", "laz", "jp2", "vrt", "gtx", "msg", "cfg", "toml", "sh", "RPB", "TXT", "XML",
    "partial", "db3", "aux", "log", "jpg", "ntf", "html",
}  # fmt: skip

BACKTICKS = re.compile(r"`([^`\n]+)`")
DOTTED_MODULE = re.compile(r"\b(?:parproj_ros|tools)(?:\.[A-Za-z_]\w*)+")
PATH_IN_PACKAGE = re.compile(r"\bparproj_ros/[\w/]*\w(?:\.py)?")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
CHAIN = re.compile(r"^([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+)(?:\(.*\))?$")
SLASHED = re.compile(r"^((?:[\w.]+/)+\w+)\.([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)(?:\(.*\))?$")
TEST_ID = re.compile(r"^([\w/]+\.py)::(\w+)(?:::(\w+))?(?:\[.*\])?$")
SHORT_PATH = re.compile(r"^(?:[\w.]+/)*\w+\.py$")


# ---- the repository, parsed --------------------------------------------------------------------


@cache
def code_files() -> tuple[Path, ...]:
    """Every Python file of the package, the tests and the tools (relative to ROOT)."""
    return tuple(p.relative_to(ROOT) for d in CODE_DIRS for p in sorted((ROOT / d).rglob("*.py")))


def dotted(rel: Path) -> str:
    """``parproj_ros/core/config.py`` -> ``parproj_ros.core.config`` (packages: no __init__)."""
    parts = list(rel.with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


@cache
def modules() -> dict[str, Path]:
    """Dotted module name -> file."""
    return {dotted(p): p for p in code_files()}


@cache
def by_base_name() -> dict[str, list[str]]:
    """A module's or package's last name -> the dotted modules with it."""
    out: dict[str, list[str]] = defaultdict(list)
    for name in modules():
        out[name.rsplit(".", 1)[-1]].append(name)
    return out


@cache
def tree(module: str) -> ast.Module:
    return ast.parse((ROOT / modules()[module]).read_text(), filename=str(modules()[module]))


def _body_names(body: list[ast.stmt]) -> Iterator[tuple[str, ast.AST]]:
    """Names a statement list binds, looking into if / try / with blocks."""
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            yield node.name, node
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                for t in ast.walk(target):
                    if isinstance(t, ast.Name):
                        yield t.id, node
        elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(
            node.target, ast.Name
        ):
            yield node.target.id, node
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                yield (alias.asname or alias.name).split(".")[0], node
        elif isinstance(node, ast.If):
            yield from _body_names(node.body + node.orelse)
        elif isinstance(node, ast.Try):
            yield from _body_names(node.body + node.orelse + node.finalbody)
            for h in node.handlers:
                yield from _body_names(h.body)
        elif isinstance(node, (ast.With, ast.AsyncWith)):
            yield from _body_names(node.body)


@cache
def classes() -> dict[str, list[ast.ClassDef]]:
    """Class name -> its definitions anywhere in the package (nested ones too)."""
    out: dict[str, list[ast.ClassDef]] = defaultdict(list)
    for name in modules():
        if name.startswith("parproj_ros"):
            for node in ast.walk(tree(name)):
                if isinstance(node, ast.ClassDef):
                    out[node.name].append(node)
    return out


def class_members(cls: ast.ClassDef, seen: frozenset[str] = frozenset()) -> set[str]:
    """Attributes of a class: its body, ``self.x = ...`` in its methods, its bases' members."""
    names = {n for n, _ in _body_names(cls.body)}
    for node in ast.walk(cls):
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                if (
                    isinstance(t, ast.Attribute)
                    and isinstance(t.value, ast.Name)
                    and t.value.id == "self"
                ):
                    names.add(t.attr)
    for base in cls.bases:
        base_name = base.id if isinstance(base, ast.Name) else getattr(base, "attr", None)
        if base_name and base_name not in seen:
            for b in classes().get(base_name, []):
                names |= class_members(b, seen | {cls.name})
    return names


@cache
def message_fields() -> dict[str, set[str]]:
    """parproj_msgs message name -> its field and constant names."""
    out: dict[str, set[str]] = {}
    for path in (ROOT / "msg_defs" / "msg").glob("*.msg"):
        names = set()
        for line in path.read_text().splitlines():
            words = line.split("#", 1)[0].replace("=", " = ").split()
            if len(words) >= 2:
                names.add(words[1])
        out[path.stem] = names
    return out


def has_attributes(module: str, attrs: list[str]) -> bool:
    """Whether ``module.a.b...`` resolves: names in the module, then class members."""
    if not attrs:
        return True
    first, rest = attrs[0], attrs[1:]
    if f"{module}.{first}" in modules():
        return has_attributes(f"{module}.{first}", rest)
    bound = dict(_body_names(tree(module).body))
    if first not in bound:
        return False
    node = bound[first]
    if not rest:
        return True
    if isinstance(node, ast.ClassDef):
        return class_has(node, rest)
    if isinstance(node, ast.ImportFrom):  # a re-export: follow it
        target = _import_target(module, node, first)
        return target is not None and has_attributes(target[0], target[1] + rest)
    return True  # an attribute of a value (a constant, an instance): not checked further


def _import_target(module: str, node: ast.ImportFrom, name: str) -> tuple[str, list[str]] | None:
    """(module, attributes) that ``from X import name`` in ``module`` refers to."""
    base = module.split(".")
    if modules()[module].name != "__init__.py":
        base = base[:-1]
    if node.level:
        base = base[: len(base) - node.level + 1]
        src = ".".join(base + ([node.module] if node.module else []))
    else:
        src = node.module or ""
    original = next((a.name for a in node.names if (a.asname or a.name) == name), name)
    if f"{src}.{original}" in modules():
        return f"{src}.{original}", []
    if src in modules():
        return src, [original]
    return None


def class_has(cls: ast.ClassDef, attrs: list[str]) -> bool:
    if attrs[0] not in class_members(cls):
        return False
    if len(attrs) == 1:
        return True
    nested = [n for n in cls.body if isinstance(n, ast.ClassDef) and n.name == attrs[0]]
    return not nested or any(class_has(n, attrs[1:]) for n in nested)


def resolve_dotted(text: str) -> bool:
    """``parproj_ros.a.b.name...``: the longest module prefix, then its attributes."""
    parts = text.split(".")
    for i in range(len(parts), 0, -1):
        name = ".".join(parts[:i])
        if name in modules():
            return has_attributes(name, parts[i:])
    return False


def find_file(path: str) -> list[Path]:
    """Files a doc's path may mean: from the root, the package, or any code file ending so."""
    hits = [ROOT / path, ROOT / "parproj_ros" / path]
    found = [h for h in hits if h.exists()]
    if not found and path.endswith(".py"):
        found = [ROOT / p for p in code_files() if f"/{p.as_posix()}".endswith(f"/{path}")]
    return found


# ---- what the docs name ------------------------------------------------------------------------


def doc_text(page: Path) -> str:
    return page.read_text(encoding="utf-8")


def check_span(span: str) -> str | None:
    """Why a backticked span names nothing that exists, or None (fine, or not a name)."""
    span = span.strip()
    test = TEST_ID.match(span)
    if test:
        files = find_file(test.group(1))
        if not files:
            return f"no file {test.group(1)}"
        names = [test.group(2)] + ([test.group(3)] if test.group(3) else [])
        for f in files:
            bound = dict(_body_names(ast.parse(f.read_text()).body))
            node = bound.get(names[0])
            if node is not None and (
                len(names) == 1 or (isinstance(node, ast.ClassDef) and class_has(node, names[1:]))
            ):
                return None
        return f"no test {'::'.join(names)} in {test.group(1)}"
    if SHORT_PATH.match(span):
        return None if find_file(span) else f"no file {span}"
    slashed = SLASHED.match(span)
    if slashed and slashed.group(2).split(".")[0] not in FILE_SUFFIXES:
        path, attrs = slashed.group(1), slashed.group(2)
        files = find_file(f"{path}.py")
        if not files:
            return f"no module {path}.py"
        for f in files:
            if has_attributes(dotted(f.relative_to(ROOT)), attrs.split(".")):
                return None
        return f"{path}.py has no {attrs}"
    chain = CHAIN.match(span)
    if not chain:
        return None
    parts = chain.group(1).split(".")
    if parts[-1] in FILE_SUFFIXES or parts[0] in FOREIGN:
        return None
    if parts[0] in {"parproj_ros", "tools", "tests"}:
        return None if resolve_dotted(chain.group(1)) else f"{chain.group(1)} does not resolve"
    if parts[0] in by_base_name():
        for module in by_base_name()[parts[0]]:
            if has_attributes(module, parts[1:]):
                return None
        return f"no module {parts[0]} has {'.'.join(parts[1:])}"
    if parts[0] in classes():
        if any(class_has(c, parts[1:]) for c in classes()[parts[0]]):
            return None
        return f"class {parts[0]} has no {'.'.join(parts[1:])}"
    if parts[0] in message_fields():
        if parts[1].rstrip("_*") in message_fields()[parts[0]] or parts[1].endswith("_"):
            return None
        return f"message {parts[0]} has no field {parts[1]}"
    return f"{parts[0]} is no module, class or message of this repository (or add it to FOREIGN)"


def slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    out: set[str] = set()
    in_code = False
    for line in doc_text(page).splitlines():
        if line.startswith("```"):
            in_code = not in_code
        elif not in_code and line.startswith("#"):
            out.add(slug(line.lstrip("#")))
    return out


def problems(page: Path) -> list[str]:
    text = doc_text(page)
    found = []
    for m in DOTTED_MODULE.finditer(text):
        if not resolve_dotted(m.group(0)):
            found.append(f"{m.group(0)}: no such module or name")
    for m in PATH_IN_PACKAGE.finditer(text):
        if not (ROOT / m.group(0)).exists():
            found.append(f"{m.group(0)}: no such file or folder")
    for m in BACKTICKS.finditer(text):
        why = check_span(m.group(1))
        if why:
            found.append(f"`{m.group(1)}`: {why}")
    for m in LINK.finditer(text):
        target = m.group(1)
        if re.match(r"^[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            found.append(f"link {target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            found.append(f"link {target}: no heading #{anchor} in {dest.name}")
    return found


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_doc_names_what_exists(page: Path) -> None:
    found = problems(page)
    assert not found, f"{page.relative_to(ROOT)}:\n  " + "\n  ".join(found)


def test_the_checker_catches_what_is_gone(tmp_path: Path) -> None:
    """The checks fail on names that do not exist and pass on ones that do."""
    assert check_span("parproj_ros.core.param_docs.parameters_markdown") is None
    assert check_span("core/memory.held_bytes") is None
    assert check_span("gcp_file.load_gcp_file") is None
    assert check_span("Pipeline.add_strip") is None
    assert check_span("ElevationGrid.terrain_source") is None
    assert check_span("tests/core/test_params.py::test_params_file_is_the_rendered_one") is None
    assert check_span("parproj_ros/core/terrain.py") is None
    assert check_span("parproj_ros.core.nothing") is not None
    assert check_span("core/memory.nothing") is not None
    assert check_span("offline.process_bag") is not None
    assert check_span("Pipeline.no_such_method") is not None
    assert check_span("ElevationGrid.no_field") is not None
    assert check_span("tests/core/test_params.py::test_nothing") is not None
    assert check_span("core/offline.py") is not None
    page = tmp_path / "p.md"
    page.write_text("# Top\n[a](p.md#top) [b](missing.md) [c](p.md#nowhere) `parproj_ros/x.py`\n")
    assert problems(page) == [
        "parproj_ros/x.py: no such file or folder",
        "`parproj_ros/x.py`: no file parproj_ros/x.py",
        "link missing.md: no such file",
        "link p.md#nowhere: no heading #nowhere in p.md",
    ]


# ---- docs/node.md's topic tables are the interface contract's -----------------------------------


def test_node_doc_topic_tables_are_the_contract() -> None:
    """docs/node.md's Subscribed and Published topics tables are what parproj_ros/core/contract.py
    renders from its rows (``python -m parproj_ros.core.contract --write .`` rewrites them)."""
    from parproj_ros.core import contract

    text = (ROOT / contract.NODE_DOC).read_text()
    for begin, end, table in contract.DOC_TABLES:
        start = text.index(begin) + len(begin) + 1
        assert text[start : text.index(end)] == table(), (
            f"{contract.NODE_DOC}: the table after {begin!r} differs from the contract's: run "
            "python -m parproj_ros.core.contract --write ."
        )
    published = re.findall(r"^\| `([^`]+)` \|", contract.published_markdown(), re.M)
    assert published == list(contract.OUTPUT_TOPICS)


def test_contract_write_rewrites_the_tables(tmp_path: Path) -> None:
    """``--write`` replaces the text between each pair of markers, and nothing else."""
    from parproj_ros.core import contract

    (tmp_path / "docs").mkdir()
    doc = tmp_path / contract.NODE_DOC
    (b1, e1, t1), (b2, e2, t2) = contract.DOC_TABLES
    doc.write_text(f"x\n{b1}\nold\n{e1}\ny\n{b2}\n| old |\n{e2}\nz\n")
    assert contract.main(["--write", str(tmp_path)]) == 0
    assert doc.read_text() == f"x\n{b1}\n{t1()}{e1}\ny\n{b2}\n{t2()}{e2}\nz\n"
    with pytest.raises(ValueError, match="needs the lines"):
        contract.doc_with_tables(f"x\n{b1}\n{e1}\n")
