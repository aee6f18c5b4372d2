"""GCP files (CSV, YAML): parsing, merging of rows, errors with their line, CSV round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from parproj_ros.core.pipeline import GroundPoint
from parproj_ros.io.gcp_file import GcpFileError, load_gcp_file, save_gcp_csv

HEADER = "id,X,Y,Z,check,scene_id,line,sample\n"


def write(tmp_path: Path, text: str, name: str = "gcp.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_csv_rows_merged_per_point(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        HEADER
        + "g01,1520.3,-880.0,412.7,0,left_0000,1033.25,517.5\n"
        + "g02,10,20,30,1,left_0000,1,2\n"
        + " g01 ,1520.3,-880.0,412.7,0, right_0000 ,998.0,520.1\n"
        + "g03,-5e3,2.5E2,-58.4,false,right_0000,0,767\n",
    )
    pts = {p.id: p for p in load_gcp_file(path)}
    assert list(pts) == ["g01", "g02", "g03"]
    g01 = pts["g01"]
    np.testing.assert_array_equal(g01.xyz, [1520.3, -880.0, 412.7])
    assert g01.check is False
    assert g01.observations == {"left_0000": (1033.25, 517.5), "right_0000": (998.0, 520.1)}
    assert pts["g02"].check is True
    assert pts["g02"].observations == {"left_0000": (1.0, 2.0)}
    np.testing.assert_array_equal(pts["g03"].xyz, [-5000.0, 250.0, -58.4])
    assert pts["g03"].check is False


@pytest.mark.parametrize(
    ("flag", "expected"),
    [
        ("0", False),
        ("1", True),
        ("true", True),
        ("false", False),
        ("TRUE", True),
        (" False ", False),
    ],
)
def test_csv_check_flag(tmp_path: Path, flag: str, expected: bool) -> None:
    path = write(tmp_path, HEADER + f"g,1,2,3,{flag},s,4,5\n")
    (p,) = load_gcp_file(path)
    assert p.check is expected


def test_csv_without_check_column_means_gcp(tmp_path: Path) -> None:
    path = write(tmp_path, "scene_id,line,sample,id,X,Y,Z\ns,4,5,g,1,2,3\n")
    (p,) = load_gcp_file(path)
    assert p.check is False and p.observations == {"s": (4.0, 5.0)}
    np.testing.assert_array_equal(p.xyz, [1.0, 2.0, 3.0])


@pytest.mark.parametrize(
    ("rows", "text"),
    [
        ("g,1,2,3,0,s,4,5\ng,1,2,abc,0,s,4,5\n", r"gcp\.csv:3: .*abc"),
        ("g,1,2,3,0,s,4,5\nh,1,2,3,0,s,4\n", r"gcp\.csv:3: "),  # a row with a missing cell
        ("g,1,2,3,0,s,4,5\ng,1,2,3.5,0,t,4,5\n", r"gcp\.csv:3: point g repeated"),
        ("g,1,2,3,0,s,4,5\ng,1,2,3,1,t,4,5\n", r"gcp\.csv:3: point g repeated"),
        ("g,1,2,3,0,s,4,5\nh,1,2,3,maybe,s,4,5\n", r"gcp\.csv:3: .*check flag 'maybe'"),
        ("g,1,2,3,2,s,4,5\n", r"gcp\.csv:2: .*check flag '2'"),
        ("g,1,2,3,0,s,4,5\ng,1,2,3,0,s,4,5\nh,nan,2,3,0,s,4,5\n", r"gcp\.csv:4: non-finite"),
        ("g,1,2,3,0,s,inf,5\n", r"gcp\.csv:2: non-finite"),
        ("g,1,2,3,0,s,4,-inf\n", r"gcp\.csv:2: non-finite"),
    ],
    ids=["number", "short-row", "xyz", "check", "flag", "flag-2", "nan", "inf-line", "inf-sample"],
)
def test_csv_errors_name_the_line(tmp_path: Path, rows: str, text: str) -> None:
    path = write(tmp_path, HEADER + rows)
    with pytest.raises(GcpFileError, match=text):
        load_gcp_file(path)


def test_csv_missing_columns(tmp_path: Path) -> None:
    path = write(tmp_path, "id,X,Y,check,line\ng,1,2,0,4\n")
    with pytest.raises(GcpFileError, match=r"missing columns \['Z', 'sample', 'scene_id'\]"):
        load_gcp_file(path)
    with pytest.raises(GcpFileError, match="missing columns"):
        load_gcp_file(write(tmp_path, "", "empty.csv"))


def test_csv_error_line_counts_blank_lines(tmp_path: Path) -> None:
    # Line 1 header, 2 a point, 3 blank, 4 the bad number: the message must say line 4.
    path = write(tmp_path, HEADER + "g,1,2,3,0,s,4,5\n\nh,1,2,x3,0,s,4,5\n")
    with pytest.raises(GcpFileError) as err:
        load_gcp_file(path)
    assert ":4:" in str(err.value), str(err.value)


def test_csv_repeated_point_with_other_coordinates_far_from_origin(tmp_path: Path) -> None:
    # Rows of one point must agree on X Y Z; 0.5 m apart is another point, whatever the size of
    # the coordinates (here 100 km from the frame origin).
    path = write(tmp_path, HEADER + "g,100000.0,5.0,3.0,0,s,4,5\ng,100000.5,5.0,3.0,0,t,6,7\n")
    with pytest.raises(GcpFileError, match=r":3: point g repeated"):
        load_gcp_file(path)


# ---- YAML ---------------------------------------------------------------------------------------


def test_yaml(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "points:\n"
        "  - id: g01\n"
        "    xyz: [1520.3, -880.0, 412.7]\n"
        "    check: false\n"
        "    observations: {left_0000: [1033.25, 517.5], right_0000: [998.0, 520.1]}\n"
        "  - id: 7\n"
        "    xyz: [1, 2, 3]\n"
        "    check: 1\n"
        "  - id: c\n"
        "    xyz: [4, 5, 6]\n"
        "    check: true\n"
        "    observations: {s: [1, 2]}\n",
        "gcp.yaml",
    )
    pts = load_gcp_file(path)
    assert [p.id for p in pts] == ["g01", "7", "c"]
    assert [p.check for p in pts] == [False, True, True]
    np.testing.assert_array_equal(pts[0].xyz, [1520.3, -880.0, 412.7])
    assert pts[0].observations == {"left_0000": (1033.25, 517.5), "right_0000": (998.0, 520.1)}
    assert pts[1].observations == {}
    assert pts[2].observations == {"s": (1.0, 2.0)}


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("gcp: []\n", "'points' list"),
        ("points: {a: 1}\n", "'points' list"),
        ("- 1\n- 2\n", "'points' list"),
        ("points: [\n", "gcp.yml"),  # not YAML
        ("points:\n  - xyz: [1, 2, 3]\n", r"points\[0\]"),  # no id
        ("points:\n  - {id: a, xyz: [1, 2, 3]}\n  - {id: b, xyz: [1, 2]}\n", r"points\[1\]: xyz"),
        ("points:\n  - {id: a, xyz: [1, .nan, 3]}\n", r"points\[0\]: xyz must be 3 finite"),
        ("points:\n  - {id: a, xyz: [1, 2, x]}\n", r"points\[0\]"),
        ("points:\n  - {id: a, xyz: [1, 2, 3], check: perhaps}\n", r"points\[0\].*perhaps"),
        ("points:\n  - {id: a, xyz: [1, 2, 3], observations: {s: [1]}}\n", r"points\[0\]"),
    ],
)
def test_yaml_errors(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(GcpFileError, match=match):
        load_gcp_file(write(tmp_path, text, "gcp.yml"))


def test_yaml_non_finite_observation_rejected(tmp_path: Path) -> None:
    # The CSV reader rejects a non-finite line or sample; the YAML reader must too.
    text = "points:\n  - {id: a, xyz: [1, 2, 3], observations: {s: [.nan, 5.0]}}\n"
    with pytest.raises(GcpFileError, match=r"points\[0\]"):
        load_gcp_file(write(tmp_path, text, "gcp.yaml"))


# ---- CSV round trip -----------------------------------------------------------------------------


def test_save_load_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    pts = []
    for k in range(6):
        obs = {
            f"scene_{j}": (float(rng.uniform(0, 768)), float(rng.uniform(0, 768)))
            for j in range(1 + k % 3)
        }
        pts.append(GroundPoint(f"p{k:02d}", rng.uniform(-5e4, 5e4, 3), k % 2 == 1, obs))
    path = tmp_path / "out.csv"
    save_gcp_csv(pts, path)
    assert path.read_text().splitlines()[0] == HEADER.strip()
    assert len(path.read_text().splitlines()) == 1 + sum(len(p.observations) for p in pts)
    back = load_gcp_file(path)
    assert [p.id for p in back] == [p.id for p in pts]
    for a, b in zip(pts, back, strict=True):
        assert b.check is a.check
        np.testing.assert_allclose(b.xyz, a.xyz, rtol=0, atol=5e-7)
        assert list(b.observations) == list(a.observations)
        for sid, (line, sample) in a.observations.items():
            assert b.observations[sid] == pytest.approx((line, sample), abs=5e-7)
