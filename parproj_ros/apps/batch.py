"""``parproj batch``: many inputs (bags, image pairs with RPC) as independent tasks on Dask.

Each input is one task: import (an image pair), :func:`~.process.process_bag`, then
:func:`~parproj_ros.eval.evaluate.evaluate_bag` (without image matching), written into
``OUT/<name>/``:

- ``input/`` the imported bag (image pairs only), ``output/`` the output bag;
- ``evaluation.json``, ``log.txt`` (what the import and the pipeline said);
- ``summary.json``, the input's row of the batch summary, with the fingerprint (size and
  modification time of every input file) that makes a re-run skip it.

A task writes under a hidden temporary name and renames it when complete
(:func:`~parproj_ros.io.files.staged_output`), so a failed or killed task never leaves an output
that looks complete. A failing input is reported (its reason in the summary, its traceback in
``OUT/_failed/<name>.log``) and does not stop the others; a task whose worker is lost is run
again by Dask's scheduler (``distributed.scheduler.allowed-failures``), and a task that raises
is retried ``retries`` times.

The scheduler is Dask's: by default a :class:`distributed.LocalCluster` of worker processes on
this machine (one thread each, bound to 127.0.0.1), or any running cluster given by its address
(``--scheduler tcp://host:8786``; the workers there need this package and read the input and
output paths, e.g. on a shared file system). ``OUT/batch_summary.json`` collects every row.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from .. import __version__
from ..core import contract
from ..io.files import InputError, staged_output

#: Files of an input bag that say it is one (what BagWriter writes).
BAG_FILES = ("metadata.yaml",)
#: Folder (under OUT) of the tracebacks of failed inputs.
FAILED_DIR = "_failed"
#: The batch summary file (under OUT).
SUMMARY = "batch_summary.json"
#: Memory limit of each worker of the default LocalCluster, MiB (Dask restarts a worker that
#: goes over 95 % of it; its task is then run again elsewhere).
WORKER_MEMORY_MB = 4096
#: Columns of an image-pair list (CSV header, or YAML keys); the first three are required.
PAIR_COLUMNS = (
    "name",
    "left",
    "right",
    "rpc_left",
    "rpc_right",
    "dem",
    "geoid_undulation",
    "height_min",
    "height_max",
)

Status = Literal["done", "skipped", "failed"]


@dataclass(frozen=True)
class BatchInput:
    """One input of a batch: a bag, or an image pair to import.

    Attributes:
        name: the output folder's name (unique in the batch).
        kind: ``"bag"`` or ``"pair"``.
        paths: the bag folder; or the left and right images.
        options: for a pair, :func:`~.importer.import_pair` keyword arguments (``rpc_left``,
            ``rpc_right``, ``dem``, ``geoid_undulation``, ``heights``).
    """

    name: str
    kind: Literal["bag", "pair"]
    paths: tuple[Path, ...]
    options: Mapping[str, Any] = field(default_factory=dict)

    def files(self) -> list[Path]:
        """Every file the task reads (a bag's files, the images, RPC and DEM files)."""
        if self.kind == "bag":
            return sorted(p for p in self.paths[0].iterdir() if p.is_file())
        extra = [self.options.get(k) for k in ("rpc_left", "rpc_right", "dem")]
        return [*self.paths, *(Path(p) for p in extra if isinstance(p, str | Path))]

    def fingerprint(self) -> list[list[Any]]:
        """(path, size in bytes, modification time in ns) of every file the task reads."""
        out: list[list[Any]] = []
        for p in self.files():
            st = p.stat()
            out.append([str(p.resolve()), st.st_size, st.st_mtime_ns])
        return out


class EmptyResultError(Exception):
    """An input processed without error but with nothing to show (no pair made)."""


def _one_line(err: BaseException) -> str:
    """``<type>: <message>`` on one line, at most 500 characters."""
    return f"{type(err).__name__}: {' '.join(str(err).split())}"[:500]


def _is_bag(path: Path) -> bool:
    return path.is_dir() and all((path / f).is_file() for f in BAG_FILES)


def _optional_float(row: Mapping[str, Any], key: str, where: str) -> float | None:
    value = row.get(key)
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(where, f"{key}: not a number: {value!r}") from None


def read_pair_list(path: Path) -> list[BatchInput]:
    """Image pairs from a CSV (header line, :data:`PAIR_COLUMNS`) or YAML list of mappings.

    Paths are relative to the list's folder. ``height_min`` and ``height_max`` (metres above
    the WGS84 ellipsoid) go together; without them and without ``dem`` the importer uses the
    RPC's height range.

    Raises:
        InputError: unreadable list, unknown or missing column, bad number.
    """
    if path.suffix.lower() == ".csv":
        with path.open(newline="", encoding="utf-8") as f:
            rows: list[Any] = list(csv.DictReader(f))
    else:
        import yaml

        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
        rows = doc.get("pairs", []) if isinstance(doc, dict) else doc
    if not isinstance(rows, list) or not rows:
        raise InputError(path, "no image pairs (a CSV with a header, or a YAML list)")
    base = path.parent
    out: list[BatchInput] = []
    for k, row in enumerate(rows):
        where = f"{path}: pair {k + 1}"
        if not isinstance(row, dict):
            raise InputError(where, "not a mapping of column -> value")
        unknown = sorted(set(row) - set(PAIR_COLUMNS))
        missing = [c for c in PAIR_COLUMNS[:3] if not row.get(c)]
        if unknown or missing:
            raise InputError(
                where, f"unknown columns {unknown}" if unknown else f"missing {missing}"
            )
        name = str(row["name"])
        if (
            name.startswith(".")
            or any(c in name for c in "/\\\0")
            or name in (FAILED_DIR, SUMMARY)
        ):
            raise InputError(
                where,
                f"name {name!r}: not a plain folder name (no /, \\ or leading dot; not "
                f"{FAILED_DIR} nor {SUMMARY}): each pair's outputs go to OUTPUT/<name>",
            )
        if (base / str(row["left"])).resolve() == (base / str(row["right"])).resolve():
            raise InputError(
                where,
                f"right {row['right']}: is the left image too: a stereo pair needs two images",
            )
        options: dict[str, Any] = {}
        for key in ("rpc_left", "rpc_right", "dem"):
            if row.get(key):
                options[key] = base / str(row[key])
        und = _optional_float(row, "geoid_undulation", where)
        if und is not None:
            options["geoid_undulation"] = und
        lo, hi = (_optional_float(row, k, where) for k in ("height_min", "height_max"))
        if (lo is None) != (hi is None):
            raise InputError(where, "height_min and height_max go together")
        if lo is not None and hi is not None:
            options["heights"] = (lo, hi)
        out.append(
            BatchInput(
                name,
                "pair",
                (base / str(row["left"]), base / str(row["right"])),
                options,
            )
        )
    return out


def find_inputs(specs: Sequence[str | os.PathLike[str]]) -> list[BatchInput]:
    """The batch's inputs: bags, folders of bags, and image-pair lists (.csv, .yaml, .yml).

    Names are the bags' folder names (and the lists' ``name`` column); a repeated name gets a
    suffix ``-2``, ``-3``, ...

    Raises:
        InputError: a path that is none of these, or a folder with no bag in it.
    """
    found: list[BatchInput] = []
    for spec in specs:
        p = Path(spec)
        if _is_bag(p):
            found.append(BatchInput(p.name, "bag", (p,)))
        elif p.is_dir():
            bags = sorted(q for q in p.iterdir() if _is_bag(q))
            if not bags:
                raise InputError(p, "neither a bag nor a folder of bags (metadata.yaml)")
            found += [BatchInput(q.name, "bag", (q,)) for q in bags]
        elif p.is_file() and p.suffix.lower() in (".csv", ".yaml", ".yml"):
            found += read_pair_list(p)
        elif not p.exists():
            raise InputError(p, "no such file or folder")
        else:
            raise InputError(p, "not a bag, a folder of bags, or a pair list (.csv, .yaml)")
    seen: dict[str, int] = {}
    out = []
    for inp in found:
        n = seen[inp.name] = seen.get(inp.name, 0) + 1
        out.append(
            inp if n == 1 else BatchInput(f"{inp.name}-{n}", inp.kind, inp.paths, inp.options)
        )
    return out


def up_to_date(inp: BatchInput, out_root: Path) -> dict[str, Any] | None:
    """The previous summary row of ``inp`` if its output is complete and its inputs unchanged."""
    try:
        row = json.loads((out_root / inp.name / "summary.json").read_text())
        same = row.get("fingerprint") == inp.fingerprint() and row.get("version") == __version__
    except (OSError, ValueError):
        return None
    return row if same and row.get("status") == "done" else None


@contextmanager
def _peak_rss() -> Iterator[dict[str, float]]:
    """The peak resident memory of this process during the block, MB (sampled every 20 ms)."""
    import psutil

    proc = psutil.Process()
    peak = {"mb": proc.memory_info().rss / 1e6}
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.02):
            peak["mb"] = max(peak["mb"], proc.memory_info().rss / 1e6)

    t = threading.Thread(target=sample, daemon=True)
    t.start()
    try:
        yield peak
    finally:
        stop.set()
        t.join()
        peak["mb"] = max(peak["mb"], proc.memory_info().rss / 1e6)


def _pair_rows(evaluation: Mapping[str, Any]) -> dict[str, Any]:
    """Per-input figures from an evaluation: pairs, worst y rms and DSM figures of its pairs."""
    pairs = evaluation.get("pairs", [])
    published = [p["published_y_parallax_px"]["rms"] for p in pairs]
    geometric = [p["geometric"]["y_parallax_px"]["rms"] for p in pairs if "geometric" in p]
    dsms = evaluation.get("heights", [])
    truth = [d["against_truth"] for d in dsms if "against_truth" in d]
    return {
        "pairs": len(pairs),
        "y_parallax_rms_px": max(published) if published else None,
        "truth_y_parallax_rms_px": max(geometric) if geometric else None,
        "dsms": len(dsms),
        "dsm_completeness": min(d["completeness_published"] for d in dsms) if dsms else None,
        "dsm_nmad_m": max(t["nmad"] for t in truth) if truth else None,
    }


def run_input(
    inp: BatchInput, out_root: str | Path, overrides: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """One task (runs on a worker): import if needed, process, evaluate; its summary row.

    Never raises for a bad input: the row says ``failed`` with the reason, and the traceback is
    in ``OUT/_failed/<name>.log``. The output folder appears only when complete.
    """
    from ..eval.evaluate import evaluate_bag
    from ..ros.bag import BagReader
    from .process import process_bag

    out_root = Path(out_root)
    row: dict[str, Any] = {
        "name": inp.name,
        "kind": inp.kind,
        "inputs": [str(p) for p in inp.paths],
        "version": __version__,
        "worker_pid": os.getpid(),
    }
    lines: list[str] = []
    t0 = time.perf_counter()
    with _peak_rss() as peak:
        try:
            row["fingerprint"] = inp.fingerprint()
            with staged_output(out_root / inp.name, force=True, kind="folder") as work:
                if inp.kind == "pair":
                    from .importer import import_pair

                    bag = work / "input"
                    opts = dict(inp.options)
                    import_pair(inp.paths[0], inp.paths[1], bag, log=lines.append, **opts)
                else:
                    bag = inp.paths[0]
                summary = process_bag(
                    bag, work / "output", overrides=dict(overrides or {}), progress=False
                )
                lines += [f"[{i.level}] {i.where}: {i.message}" for i in summary.issues]
                if summary.pairs == 0:  # an empty result is not done (parproj process: exit 1)
                    raise EmptyResultError(
                        f"no pair was made (the [warn] / [error] lines in {FAILED_DIR}/"
                        f"{inp.name}.log say why)"
                    )
                truth = bag if contract.TRUTH_POINTS in BagReader(bag).topics() else None
                evaluation = evaluate_bag(work / "output", truth, matching=False)
                (work / "evaluation.json").write_text(
                    json.dumps(evaluation, indent=1, default=float)
                )
                (work / "log.txt").write_text("\n".join(lines) + "\n")
                row.update(_pair_rows(evaluation), scenes=summary.scenes, status="done")
                missing = row["pairs"] - row["dsms"]
                if (overrides or {}).get("heights") and missing > 0:
                    # done (the pairs are made and kept), but not what was asked: said, and
                    # the batch exits 1 (parproj process --heights of the same: exit 1)
                    row["warning"] = (
                        f"{missing} of {row['pairs']} pairs got no DSM (the [warn] lines of "
                        f"{inp.name}/log.txt say why)"
                    )
                row["time_s"] = time.perf_counter() - t0
                row["peak_rss_mb"] = peak["mb"]
                (work / "summary.json").write_text(json.dumps(row, indent=1, default=float))
        except Exception as err:  # one bad input never stops the batch
            failed = out_root / FAILED_DIR
            failed.mkdir(parents=True, exist_ok=True)
            (failed / f"{inp.name}.log").write_text(
                "\n".join(lines) + "\n" + traceback.format_exc()
            )
            row.update(
                status="failed", error=f"{type(err).__name__}: {' '.join(str(err).split())}"[:500]
            )
    row["time_s"] = time.perf_counter() - t0
    row["peak_rss_mb"] = peak["mb"]
    return row


def default_workers(memory_mb: float = WORKER_MEMORY_MB) -> int:
    """Worker processes for this machine: one per core, as many as the memory holds."""
    import psutil

    by_memory = int(psutil.virtual_memory().total / 2**20 // memory_mb)
    return max(1, min(os.cpu_count() or 1, by_memory))


@dataclass
class BatchResult:
    """What a batch did.

    Attributes:
        rows: one summary row per input, in input order.
        wall_s: the batch's elapsed time, seconds.
        workers: worker processes used (the cluster's, when one was given).
        dashboard: the Dask dashboard's address, or None.
    """

    rows: list[dict[str, Any]]
    wall_s: float
    workers: int
    dashboard: str | None

    def count(self, status: Status) -> int:
        """Inputs with this status."""
        return sum(r["status"] == status for r in self.rows)

    def as_dict(self) -> dict[str, Any]:
        """The JSON summary (``OUT/batch_summary.json``)."""
        done = [r for r in self.rows if r["status"] == "done"]
        return {
            "inputs": len(self.rows),
            "done": len(done),
            "skipped": self.count("skipped"),
            "failed": self.count("failed"),
            "workers": self.workers,
            "wall_s": self.wall_s,
            "pairs_per_hour": 3600 * sum(r.get("pairs", 0) for r in done) / self.wall_s
            if self.wall_s > 0
            else None,
            "dashboard": self.dashboard,
            "rows": self.rows,
        }


def _remove_stale_partials(out_root: Path, names: set[str]) -> None:
    """Hidden ``.<name>.*.partial`` folders of these inputs, left by killed tasks."""
    for p in out_root.glob(".*.partial"):
        if p.name[1:].split(".", 1)[0] in names:
            shutil.rmtree(p, ignore_errors=True)


def _dashboard(client: Any, cluster: Any) -> str | None:
    """The dashboard's address, if the scheduler runs one (a LocalCluster: with bokeh)."""
    import importlib.util

    if cluster is not None and importlib.util.find_spec("bokeh") is None:
        return None
    try:
        if "dashboard" not in client.scheduler_info().get("services", {}):
            return None
        return str(client.dashboard_link)
    except Exception:  # an old scheduler, or none reachable: no address to give
        return None


def run_batch(
    inputs: Sequence[BatchInput],
    out_root: str | Path,
    *,
    client: Any = None,
    scheduler: str | None = None,
    workers: int | None = None,
    worker_memory_mb: float = WORKER_MEMORY_MB,
    overrides: Mapping[str, Any] | None = None,
    force: bool = False,
    retries: int = 1,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> BatchResult:
    """Run every input as a Dask task; write ``OUT/batch_summary.json``.

    Args:
        inputs: from :func:`find_inputs`.
        out_root: the batch's output folder (created).
        client: a :class:`distributed.Client` to use (else one is made and closed here).
        scheduler: address of a running Dask scheduler (else a LocalCluster is started).
        workers: LocalCluster worker processes (default :func:`default_workers`).
        worker_memory_mb: memory limit of each LocalCluster worker, MiB.
        overrides: PipelineConfig fields for every input (as ``parproj process`` options).
        force: redo inputs whose outputs are complete and up to date.
        retries: further attempts of a task that raised (a lost worker is handled by the
            scheduler, not counted here).
        progress: show a progress bar.
        log: where the dashboard address and the skipped inputs are reported.
    """
    from distributed import Client, LocalCluster, as_completed

    out = Path(out_root)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: dict[str, dict[str, Any]] = {}
    todo = []
    for inp in inputs:
        prev = None if force else up_to_date(inp, out)
        if prev is not None:
            rows[inp.name] = {**prev, "status": "skipped", "previous_time_s": prev.get("time_s")}
            log(f"{inp.name}: up to date, skipped (--force redoes it)")
        else:
            todo.append(inp)
    cluster = None
    own_client = client is None
    if client is None:
        if scheduler:
            client = Client(scheduler)
        else:
            import importlib.util

            n = workers or default_workers(worker_memory_mb)
            has_dashboard = importlib.util.find_spec("bokeh") is not None  # else none runs
            cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address="127.0.0.1:0" if has_dashboard else None,
                memory_limit=f"{worker_memory_mb}MiB",
                silence_logs=40,
            )
            client = Client(cluster)
    dashboard = _dashboard(client, cluster)
    n_workers = len(client.scheduler_info().get("workers", {}))
    log(
        f"batch: {len(inputs)} inputs ({len(todo)} to run) on {n_workers} Dask workers"
        + (f"; dashboard {dashboard}" if dashboard else "")
    )
    try:
        futures = {
            client.submit(
                run_input,
                inp,
                str(out.resolve()),
                dict(overrides or {}),
                pure=False,
                retries=retries,
                key=f"parproj-batch-{inp.name}-{time.time_ns()}",
            ): inp
            for inp in todo
        }
        bar = None
        if progress and futures:
            from tqdm import tqdm

            bar = tqdm(total=len(futures), desc="batch", unit="input")
        for fut in as_completed(list(futures)):
            inp = futures[fut]
            try:
                row = fut.result()
            except Exception as err:  # KilledWorker (lost too often), or an error Dask raised
                row = {
                    "name": inp.name,
                    "kind": inp.kind,
                    "inputs": [str(p) for p in inp.paths],
                    "status": "failed",
                    "error": _one_line(err),
                }
            rows[inp.name] = row
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(f"{inp.name}: {row['status']}")
        if bar is not None:
            bar.close()
    finally:
        if own_client:
            client.close()
            if cluster is not None:
                cluster.close()
    _remove_stale_partials(out, {i.name for i in inputs})
    result = BatchResult(
        [rows[i.name] for i in inputs], time.perf_counter() - t0, n_workers, dashboard
    )
    tmp = out / f".{SUMMARY}.tmp"
    tmp.write_text(json.dumps(result.as_dict(), indent=1, default=float))
    os.replace(tmp, out / SUMMARY)
    return result


def format_summary(result: BatchResult) -> str:
    """The summary table a person reads (one line per input, then the totals)."""

    def fmt(v: Any, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    lines = [
        f"{'input':24} {'status':8} {'pairs':>5} {'y rms px':>9} {'time s':>8} {'peak MB':>8}"
    ]
    for r in result.rows:
        lines.append(
            f"{r['name'][:24]:24} {r['status']:8} {fmt(r.get('pairs'), 'd'):>5} "
            f"{fmt(r.get('y_parallax_rms_px'), '.3f'):>9} {fmt(r.get('time_s'), '.1f'):>8} "
            f"{fmt(r.get('peak_rss_mb'), '.0f'):>8}"
            + (f"  {r['error']}" if r.get("error") else "")
            + (f"  {r['warning']}" if r.get("warning") else "")
        )
    d = result.as_dict()
    lines.append(
        f"{d['done']} done, {d['skipped']} skipped, {d['failed']} failed; "
        f"{result.wall_s:.1f} s on {result.workers} workers"
    )
    return "\n".join(lines)
