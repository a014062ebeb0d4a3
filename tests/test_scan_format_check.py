"""A headerless .bin read in the wrong layout is refused, naming --scan-format.

Every bundled sample scan is written here in each of the three .bin layouts (KITTI as
shipped; NCLT's 5 mm uint16 records; a PointNetVLAD-style Oxford submap, as
test_protocols makes them), so which layout a file is in is known. Read in its own
layout it must pass; read in another whose record size fits, it must be refused."""

from __future__ import annotations

import json
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
    assert "only 999 points" in layout_problem(wild[:999])  # too few to be a scan
    assert "beyond 500 m" in layout_problem(wild)
    nan = np.full((1000, 4), np.nan, np.float32)
    assert "100% not numbers" in layout_problem(nan)
    assert "100% at the sensor" in layout_problem(np.zeros((1000, 4), np.float32))
    # A scan moved whole into a far frame (a map's, 10 km away) is no wrong layout: the
    # search refuses it later for having no point in range.
    scan = rng.uniform(-60.0, 60.0, (2000, 4)).astype(np.float32)
    assert layout_problem(scan) is None
    scan[:, 0] += 10_000.0
    assert layout_problem(scan) is None


def _ground_scan(n: int, seed: int = 0) -> np.ndarray:
    """n returns a scan could hold: the ground 3-60 m around the sensor."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(3.0, 60.0, n), rng.uniform(-np.pi, np.pi, n)
    return np.c_[r * np.cos(a), r * np.sin(a), np.full(n, -1.7), rng.random(n)].astype(np.float32)


def test_a_periodic_nan_pattern_is_judged_as_it_is() -> None:
    """Every third point NaN and every seventh x infinite: 43 % not numbers, at every
    length. An even stride of n // 4096 read only NaN wherever it was a multiple of 3
    (25,944 points: a stride of 6), and refused the scan as "100% not numbers"."""
    refused = {}
    for n in [*range(12_288, 40_000, 401), 25_944]:
        pts = _ground_scan(n)
        pts[::3, :3] = np.nan
        pts[::7, 0] = np.inf
        if layout_problem(pts) is not None:
            refused[n] = layout_problem(pts)
    assert refused == {}


@pytest.mark.parametrize("marker", [np.nan, 0.0])
def test_organized_clouds_are_judged_on_their_returns_up_to_the_stated_share(marker) -> None:
    """No return marked NaN or 0 (x, y, z), in a periodic pattern: a scan up to
    MAX_NO_RETURN (90 %) of them, refused past it; and at least MIN_POINTS returns."""
    from disco_cli.io.readers.plausible import MAX_NO_RETURN, MIN_POINTS

    assert MAX_NO_RETURN == 0.9 and MIN_POINTS == 1000
    for every, keep, ok in ((20, 3, True), (10, 2, True), (20, 1, False), (40, 3, False)):
        # `keep` returns in each run of `every` points: 85 %, 80 %, 95 %, 92.5 % no return
        pts = _ground_scan(40 * 1024)
        no_return = np.arange(len(pts)) % every >= keep
        pts[no_return, :3] = marker
        problem = layout_problem(pts)
        assert (problem is None) == ok, (every, keep, problem)
        if not ok:
            assert "no return" in problem and "at most 90%" in problem
    # 1,500 rows, 1,000 of them NaN: 33 % no return but only 500 returns.
    pts = _ground_scan(1500)
    pts[500:, :3] = marker
    assert "only about 500 of its 1500 points are returns" in layout_problem(pts)


def test_a_4096_point_submap_is_a_scan() -> None:
    """PointNetVLAD's Oxford submaps (ground removed, 4096 points) are the smallest real
    scans here: well above MIN_POINTS, and judged whole (under SAMPLE points)."""
    rng = np.random.default_rng(2)
    sub = rng.uniform(-20.0, 20.0, (4096, 4)).astype(np.float32)
    sub[:, 2] = rng.uniform(-1.0, 8.0, 4096)
    assert layout_problem(sub) is None
    assert "only 62 points" in layout_problem(sub[:62])


def test_text_is_no_scan_whatever_its_size() -> None:
    from disco_cli.io.readers.plausible import is_text

    assert is_text(b"0.123 4.567 -8.9 0.25\n" * 20)
    assert is_text("x,y,z\nGr\u00f6\u00dfe\t1\r\n".encode())
    assert not is_text(b"")
    assert not is_text(_ground_scan(32).tobytes())  # float32 mantissas hold control bytes


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


# -- through the command line: answered, or refused in one line -----------------------


def _query(scan: Path, db: Path, *extra: str):
    res = CliRunner().invoke(app, ["query", str(scan), "--db", str(db), "-k", "1",
                                   "--format", "jsonl", *extra])  # fmt: skip
    return res


def _top1(res) -> int:
    assert res.exit_code == 0, res.stderr
    return json.loads(res.stdout.splitlines()[0])["match_id"]


def _sample(samples: Path) -> np.ndarray:
    return np.fromfile(samples / "01" / "velodyne" / "000005.bin", "<f4").reshape(-1, 4)


def test_a_scan_with_43_percent_nan_is_answered_as_the_clean_scan(
    samples: Path, samples_spectral_db: Path, tmp_path: Path
) -> None:
    """25,944 KITTI records, every third NaN and every seventh x infinite (43 % not
    finite), the rest the sample scan's points: the clean scan's top 1."""
    clean = _sample(samples)
    n = 25_944
    rows = np.zeros((n, 4), np.float32)
    i = np.arange(n)
    nan, inf = i % 3 == 0, (i % 7 == 0) & (i % 3 != 0)
    real = ~nan & ~inf
    rng = np.random.default_rng(0)
    rows[real] = clean[np.sort(rng.choice(len(clean), real.sum(), replace=False))]
    rows[inf] = clean[rng.choice(len(clean), inf.sum())]
    rows[nan, :3] = np.nan
    rows[inf, 0] = np.inf
    assert abs((~np.isfinite(rows[:, :3]).all(axis=1)).mean() - 9 / 21) < 1e-3
    path = tmp_path / "nan43.bin"
    rows.tofile(path)
    want = _top1(_query(samples / "01" / "velodyne" / "000005.bin", samples_spectral_db))
    assert _top1(_query(path, samples_spectral_db)) == want


@pytest.mark.parametrize("marker", [np.nan, 0.0])
def test_an_organized_scan_is_answered_as_the_clean_scan(
    samples: Path, samples_spectral_db: Path, tmp_path: Path, marker: float
) -> None:
    """The sample scan put into its sensor's image (the simulator's HDL-32E: 32 beams
    from -30.67 to +10.67 degrees, 600 columns of 0.6 degree), every ray that hit nothing
    marked NaN or 0: 11 % no return, as real sensors' layouts (7-15 %)."""
    clean = _sample(samples)
    x, y, z = clean[:, 0].astype(np.float64), clean[:, 1], clean[:, 2]
    ring = np.round((np.degrees(np.arctan2(z, np.hypot(x, y))) + 30.67) / (41.34 / 31))
    col = np.round(np.mod(np.degrees(np.arctan2(y, x)), 360.0) / 0.6) % 600
    cell = (ring * 600 + col).astype(np.int64)
    assert ring.min() >= 0 and ring.max() <= 31
    image = np.full((32 * 600, 4), marker, np.float32)
    image[:, 3] = 0.0
    image[cell] = clean
    share = 1.0 - len(np.unique(cell)) / len(image)
    assert 0.08 < share < 0.14 and len(np.unique(cell)) == len(clean), share  # no return
    path = tmp_path / "organized.bin"
    image.tofile(path)
    want = _top1(_query(samples / "01" / "velodyne" / "000005.bin", samples_spectral_db))
    assert _top1(_query(path, samples_spectral_db)) == want


def test_a_cut_scan_and_a_text_file_are_refused_in_one_line(
    samples: Path, samples_spectral_db: Path, tmp_path: Path
) -> None:
    cut = tmp_path / "cut.bin"
    cut.write_bytes(_sample(samples)[:62].tobytes())
    text = tmp_path / "notes.bin"
    body = "".join(f"{v:.3f} {-v:.3f} {v / 7:.3f} 0.5\n" for v in range(4000)).encode()
    text.write_bytes(body[: len(body) // 16 * 16])  # a multiple of 16 bytes
    for path, problem in ((cut, "only 62 points"), (text, "its first bytes are text")):
        res = _query(path, samples_spectral_db)
        assert res.exit_code == 1 and res.stdout == "", res.stdout
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and str(path) in lines[0] and problem in lines[0], res.stderr
        assert "Traceback" not in res.stderr
