"""Ground control point files (CSV or YAML), read into :class:`~parproj_ros.pipeline.GroundPoint`.

CSV: a header line and one row per observation of a point in a scene::

    id,X,Y,Z,check,scene_id,line,sample
    g01,1520.3,-880.0,412.7,0,left_0000,1033.25,517.5

X, Y, Z are object coordinates in metres (the node's frame_id); check is 0/1 (or true/false);
line and sample are continuous pixel coordinates in the scene (pixel centres at integers).
Rows with the same id are one point (its X, Y, Z and check must agree).

YAML::

    points:
      - id: g01
        xyz: [1520.3, -880.0, 412.7]
        check: false
        observations: {left_0000: [1033.25, 517.5], right_0000: [998.0, 520.1]}
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .pipeline import GroundPoint


class GcpFileError(ValueError):
    """A GCP file that cannot be used, with the line or entry at fault."""


def _bool(text: object) -> bool:
    t = str(text).strip().lower()
    if t in ("1", "true", "yes", "y", "check"):
        return True
    if t in ("0", "false", "no", "n", "", "gcp"):
        return False
    raise GcpFileError(f"check flag {text!r} is not 0/1/true/false")


def load_gcp_file(path: str | Path) -> list[GroundPoint]:
    """Read a .csv or .yaml/.yml GCP file (format in the module docstring)."""
    p = Path(path)
    if p.suffix.lower() in (".yaml", ".yml"):
        return _load_yaml(p)
    return _load_csv(p)


def _load_csv(path: Path) -> list[GroundPoint]:
    points: dict[str, GroundPoint] = {}
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        need = {"id", "X", "Y", "Z", "scene_id", "line", "sample"}
        missing = need - set(reader.fieldnames or [])
        if missing:
            raise GcpFileError(f"{path}: missing columns {sorted(missing)}")
        for row in reader:
            n = reader.line_num  # the file's line, blank lines included
            try:
                xyz = np.array([float(row["X"]), float(row["Y"]), float(row["Z"])])
                obs = (float(row["line"]), float(row["sample"]))
                check = _bool(row.get("check", "0"))
            except (TypeError, ValueError) as err:
                raise GcpFileError(f"{path}:{n}: {err}") from err
            if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(obs))):
                raise GcpFileError(f"{path}:{n}: non-finite value")
            pid = row["id"].strip()
            old = points.get(pid)
            if old is None:
                points[pid] = GroundPoint(pid, xyz, check, {row["scene_id"].strip(): obs})
            else:
                if not np.allclose(old.xyz, xyz, rtol=0.0, atol=1e-6) or old.check != check:
                    raise GcpFileError(f"{path}:{n}: point {pid} repeated with other X Y Z/check")
                old.observations[row["scene_id"].strip()] = obs
    return list(points.values())


def _load_yaml(path: Path) -> list[GroundPoint]:
    import yaml

    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise GcpFileError(f"{path}: {err}") from err
    if not isinstance(doc, dict) or not isinstance(doc.get("points"), list):
        raise GcpFileError(f"{path}: expected a mapping with a 'points' list")
    out = []
    for i, item in enumerate(doc["points"]):
        try:
            xyz = np.asarray(item["xyz"], dtype=float)
            obs = {
                str(k): (float(v[0]), float(v[1]))
                for k, v in (item.get("observations") or {}).items()
            }
            gp = GroundPoint(str(item["id"]), xyz, _bool(item.get("check", False)), obs)
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise GcpFileError(f"{path}: points[{i}]: {err!r}") from err
        if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
            raise GcpFileError(f"{path}: points[{i}]: xyz must be 3 finite numbers")
        bad = [k for k, v in obs.items() if not np.all(np.isfinite(v))]
        if bad:
            raise GcpFileError(f"{path}: points[{i}]: non-finite observation in {bad}")
        out.append(gp)
    return out


def save_gcp_csv(points: list[GroundPoint], path: str | Path) -> None:
    """Write points in the CSV format above."""
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "X", "Y", "Z", "check", "scene_id", "line", "sample"])
        for p in points:
            for sid, (line, sample) in p.observations.items():
                w.writerow(
                    [
                        p.id,
                        *(f"{v:.6f}" for v in p.xyz),
                        int(p.check),
                        sid,
                        f"{line:.6f}",
                        f"{sample:.6f}",
                    ]
                )
