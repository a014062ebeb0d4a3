"""A headerless .bin read in the wrong layout is refused, naming --scan-format.

Every bundled sample scan is written here in each of the three .bin layouts (KITTI as
shipped; NCLT's 5 mm uint16 records; a PointNetVLAD-style Oxford submap, as
test_protocols makes them), so which layout a file is in is known. Read in its own
layout it must pass; read in another whose record size fits, it must be refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.errors import ScanReadError
from disco_cli.io.readers import read_scan
from disco_cli.io.readers.nclt import RECORD
from disco_cli.io.readers.plausible import layout_problem

LAYOUTS = ("kitti", "nclt", "oxford")
RECORD_BYTES = {"kitti": 16, "nclt": 8, "oxford": 24}


def _as_nclt(points: np.ndarray, rng: np.random.Generator) -> bytes:
    p = points[:, :3].astype(np.float64) * [1.0, -1.0, -1.0]  # NCLT: z down
    keep = np.all(np.abs(p) < 99.0, axis=1)
    raw = np.round((p[keep] + 100.0) / 0.005).astype("<u2")
    rec = np.zeros(len(raw), RECORD)
    rec["x"], rec["y"], rec["z"] = raw.T
    rec["intensity"] = np.clip(points[keep, 3] * 255, 0, 255)
    rec["laser"] = rng.integers(0, 32, len(raw))  # an HDL-32E's laser ids
    return rec.tobytes()


def _as_oxford(points: np.ndarray, rng: np.random.Generator) -> bytes:
    # PointNetVLAD's submaps: no ground, 4096 points, centred, scaled to a mean distance
    # of 0.5, negated, cropped to [-1, 1].
    p = points[:, :3].astype(np.float64)
    p = p[(np.abs(p[:, 0]) < 40) & (np.abs(p[:, 1]) < 40) & (p[:, 2] > -1.4)]
    pick = (p * [1.0, -1.0, -1.0])[rng.choice(len(p), 4096, replace=len(p) < 4096)]
    c = pick.mean(axis=0)
    out = -(0.5 / np.linalg.norm(pick - c, axis=1).mean()) * (pick - c)
    return out[np.all(np.abs(out) <= 1.0, axis=1)].astype("<f8").tobytes()


@pytest.fixture(scope="module")
def written(samples: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[Path]]:
    """Every sample scan in each layout: {layout: files}."""
    rng = np.random.default_rng(0)
    root = tmp_path_factory.mktemp("layouts")
    files: dict[str, list[Path]] = {f: [] for f in LAYOUTS}
    for i, src in enumerate(sorted(samples.glob("0[01]/velodyne/*.bin"))):
        pts = np.fromfile(src, "<f4").reshape(-1, 4)
        files["kitti"].append(src)
        for fmt, make in (("nclt", _as_nclt), ("oxford", _as_oxford)):
            path = root / f"{fmt}_{i:03d}.bin"
            path.write_bytes(make(pts, rng))
            files[fmt].append(path)
    return files


@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_scan_read_in_its_own_layout_passes(written, layout: str) -> None:
    for path in written[layout]:
        assert len(read_scan(path, format=layout)) >= 1000


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("read_as", LAYOUTS)
def test_a_scan_read_in_another_layout_is_refused(written, layout: str, read_as: str) -> None:
    if read_as == layout:
        return
    tried = 0
    for path in written[layout]:
        if path.stat().st_size % RECORD_BYTES[read_as]:
            continue  # refused by its size already
        tried += 1
        with pytest.raises(ScanReadError) as info:
            read_scan(path, format=read_as)
        message = str(info.value)
        assert message.startswith(f"{path}: ") and "--scan-format" in message
        assert "\n" not in message
    assert tried > 0, "no file of this layout fits the other's record"


def test_the_check_needs_enough_points_to_judge() -> None:
    rng = np.random.default_rng(1)
    wild = (10.0 ** rng.uniform(-3, 20, (1000, 4))).astype(np.float32)  # sizes of 23 decades
    assert layout_problem(wild[:999]) is None  # too few points to say
    assert "beyond 500 m" in layout_problem(wild)
    nan = np.full((1000, 4), np.nan, np.float32)
    assert "not numbers" in layout_problem(nan)
    assert "at the sensor" in layout_problem(np.zeros((1000, 4), np.float32))
    # A scan moved whole into a far frame (a map's, 10 km away) is no wrong layout: the
    # search refuses it later for having no point in range.
    scan = rng.uniform(-60.0, 60.0, (2000, 4)).astype(np.float32)
    assert layout_problem(scan) is None
    scan[:, 0] += 10_000.0
    assert layout_problem(scan) is None


@pytest.mark.parametrize("fmt", ["nclt", "oxford"])
def test_query_with_a_wrong_scan_format_is_refused_in_one_line(
    samples: Path, tmp_path: Path, fmt: str
) -> None:
    db = tmp_path / "map.db"
    runner = CliRunner()
    assert runner.invoke(app, ["build-db", str(samples / "00"), "-o", str(db), "-q"]).exit_code == 0
    scan = samples / "01" / "velodyne" / "000005.bin"
    res = runner.invoke(app, ["query", str(scan), "--db", str(db), "--scan-format", fmt])
    assert res.exit_code == 1
    assert res.stdout == ""  # no match printed for it
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "--scan-format" in lines[0] and str(scan) in lines[0]
