"""`disco bev` end to end through typer's CliRunner, and the PNG writer it uses.

PNGs are decoded here with zlib and struct alone (an independent decoder), and
the BEV is checked against NumPy's own binning of the documented formulas."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.io.png import BACKGROUND, colormap, encode_png, upscale

runner = CliRunner()

# Points chosen well inside cells (never on an edge): five in the BEV window
# and outside it four (too near, too far, too low, too high) and a thousand more within
# the sensor's 3 m blind radius, which the BEV drops: a .bin is read as a scan when it
# holds 1,000 points or more (io/readers/plausible.py).
INSIDE = np.array(
    [
        [11.0, 0.3, 0.2, 0.5],  # ahead
        [0.3, 21.0, 3.1, 0.1],  # to the left
        [-31.0, -0.3, 7.1, 0.9],  # behind
        [0.3, -45.0, -1.1, 0.2],  # to the right
        [25.1, 26.0, 12.1, 0.4],  # ahead-left, 46 degrees
    ],
    dtype=np.float32,
)
_BLIND = np.arange(1000) * (2 * np.pi / 1000)
OUTSIDE = np.vstack(
    [
        [[1.0, 1.0, 0.0, 0], [100.0, 0.0, 0.0, 0], [10.0, 10.0, -5.0, 0], [10.0, 10.0, 40.0, 0]],
        np.c_[2.5 * np.cos(_BLIND), 2.5 * np.sin(_BLIND), np.full((1000, 2), -1.0)],
    ]
).astype(np.float32)


def decode_png(data: bytes) -> np.ndarray:
    """A minimal PNG decoder for 8-bit gray/RGB, filter 0 rows: checks every CRC."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, kind
        chunks.append((kind, body))
        pos += 12 + length
    assert chunks[0][0] == b"IHDR" and chunks[-1] == (b"IEND", b"")
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert depth == 8 and interlace == 0 and colour in (0, 2)
    channels = 3 if colour == 2 else 1
    raw = zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT"))
    rows = np.frombuffer(raw, np.uint8).reshape(height, 1 + width * channels)
    assert (rows[:, 0] == 0).all()  # filter type None on every row
    pixels = rows[:, 1:].reshape(height, width, channels)
    return pixels[:, :, 0] if channels == 1 else pixels


def reference_occupancy(points: np.ndarray, c) -> np.ndarray:
    """[H, R, S] occupancy from the formulas in docs/architecture and polar_bev.hpp."""
    x, y, z = (points[:, i].astype(np.float64) for i in range(3))
    r = np.hypot(x, y)
    keep = (r >= c.min_range) & (r < c.max_range) & (z >= c.z_min) & (z < c.z_max)
    ring = np.floor(r / (c.max_range / c.rings)).astype(int)
    sector = np.floor(np.mod(np.arctan2(y, x), 2 * np.pi) / (2 * np.pi / c.sectors)).astype(int)
    height = np.floor((z - c.z_min) / ((c.z_max - c.z_min) / c.heights)).astype(int)
    out = np.zeros((c.heights, c.rings, c.sectors), np.float32)
    out[height[keep], ring[keep], sector[keep]] = 1.0
    return out


@pytest.fixture()
def scan(tmp_path: Path) -> Path:
    path = tmp_path / "velodyne" / "000003.bin"
    path.parent.mkdir()
    np.concatenate([INSIDE, OUTSIDE]).tofile(path)  # KITTI float32 x4 records
    return path


def _stderr(result) -> str:
    return result.stderr if hasattr(result, "stderr") else result.output


# -- the command ---------------------------------------------------------------


def test_npy_output_is_the_bev_of_the_points(scan: Path, tmp_path: Path) -> None:
    from disco_cli.model.bev import BEVConfig, polar_bev

    out = tmp_path / "out" / "bev.npy"
    out.parent.mkdir()  # a missing folder is refused, as by every -o (test_output_paths.py)
    result = runner.invoke(app, ["bev", str(scan), "-o", str(out), "--bev-mode", "occupancy"])
    assert result.exit_code == 0, result.output
    grid = np.load(out)
    config = BEVConfig(mode="occupancy")
    points = np.concatenate([INSIDE, OUTSIDE])
    np.testing.assert_array_equal(grid, polar_bev(points, config))
    np.testing.assert_array_equal(grid, reference_occupancy(points, config))
    assert grid.sum() == len(INSIDE)
    err = _stderr(result)
    # What a new user needs to see: points read, points in the window, what was written.
    assert f"read {len(points)} points (kitti)" in err
    assert f"{len(INSIDE)} in the BEV window" in err
    assert str(out) in err and "[" + ", ".join(map(str, grid.shape)) + "]" in err


@pytest.mark.parametrize("mode", ["density", "max_height"])
def test_npy_output_follows_the_mode(scan: Path, tmp_path: Path, mode: str) -> None:
    from disco_cli.model.bev import BEVConfig, polar_bev

    out = tmp_path / f"{mode}.npy"
    result = runner.invoke(app, ["bev", str(scan), "-o", str(out), "--bev-mode", mode])
    assert result.exit_code == 0, result.output
    points = np.concatenate([INSIDE, OUTSIDE])
    np.testing.assert_array_equal(np.load(out), polar_bev(points, BEVConfig(mode=mode)))


def test_model_option_uses_that_models_bev_config(scan: Path, tmp_path: Path) -> None:
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    config = load_model("scancontext").bev_config
    out = tmp_path / "sc.npy"
    result = runner.invoke(app, ["bev", str(scan), "-o", str(out), "--model", "scancontext"])
    assert result.exit_code == 0, result.output
    grid = np.load(out)
    assert grid.shape == config.shape
    np.testing.assert_array_equal(grid, polar_bev(np.concatenate([INSIDE, OUTSIDE]), config))

    missing = str(tmp_path / "no.pt")
    result = runner.invoke(app, ["bev", str(scan), "-o", str(out), "--model", missing])
    assert result.exit_code == 1 and "no.pt" in _stderr(result)


def test_png_shows_the_occupied_cells(scan: Path, tmp_path: Path) -> None:
    from disco_cli.model.bev import BEVConfig

    c = BEVConfig(mode="occupancy")
    out = tmp_path / "bev.png"
    result = runner.invoke(
        app, ["bev", str(scan), "-o", str(out), "--bev-mode", "occupancy", "-s", "3"]
    )
    assert result.exit_code == 0, result.output
    image = decode_png(out.read_bytes())
    assert image.shape == (c.rings * 3, c.sectors * 3, 3)
    occupied = reference_occupancy(INSIDE, c).any(axis=0)
    # Each cell is a 3 x 3 block of one colour: coloured exactly where occupied.
    cells = image[1::3, 1::3]
    painted = (cells != np.array(BACKGROUND, np.uint8)).any(axis=2)
    np.testing.assert_array_equal(painted, occupied)
    assert (image[::3, ::3] == cells).all()
    assert len(np.unique(image.reshape(-1, 3), axis=0)) >= 2  # not blank


def test_polar_png_puts_points_where_they_are(scan: Path, tmp_path: Path) -> None:
    from disco_cli.model.bev import BEVConfig

    c = BEVConfig(mode="occupancy")
    out = tmp_path / "polar.png"
    result = runner.invoke(
        app, ["bev", str(scan), "-o", str(out), "--polar", "-s", "4", "--bev-mode", "occupancy"]
    )
    assert result.exit_code == 0, result.output
    image = decode_png(out.read_bytes())
    size = 2 * c.rings * 4
    assert image.shape == (size, size, 3)
    bg = np.array(BACKGROUND, np.uint8)
    metres_per_px = c.max_range / (size / 2)

    def cell_pixel(x: float, y: float) -> np.ndarray:
        # The pixel at the centre of the BEV cell holding (x, y); top-down view,
        # +x up and +y left, the sensor at the image centre.
        ring_w, sector_w = c.max_range / c.rings, 2 * np.pi / c.sectors
        r = (np.floor(np.hypot(x, y) / ring_w) + 0.5) * ring_w
        t = (np.floor(np.mod(np.arctan2(y, x), 2 * np.pi) / sector_w) + 0.5) * sector_w
        xc, yc = r * np.cos(t), r * np.sin(t)
        return image[int(size / 2 - xc / metres_per_px), int(size / 2 - yc / metres_per_px)]

    for x, y, *_ in INSIDE.tolist():
        assert (cell_pixel(x, y) != bg).any(), (x, y)
    # The points turned by 90 degrees land in empty cells (each ring holds one point).
    for x, y, *_ in INSIDE.tolist():
        assert (cell_pixel(-y, x) == bg).all(), (x, y)
    assert (image[0, 0] == bg).all()  # outside the disc


def test_missing_and_bad_files_give_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "absent.bin"
    result = runner.invoke(app, ["bev", str(missing), "-o", str(tmp_path / "x.png")])
    assert result.exit_code == 1
    err = _stderr(result).strip()
    assert str(missing) in err and len(err.splitlines()) == 1 and "Traceback" not in err

    bad = tmp_path / "short.bin"
    bad.write_bytes(b"\0" * 20)
    result = runner.invoke(app, ["bev", str(bad), "-o", str(tmp_path / "x.png")])
    assert result.exit_code == 1 and "multiple of" in _stderr(result)
    assert not (tmp_path / "x.png").exists()

    result = runner.invoke(app, ["bev", str(bad), "-o", str(tmp_path / "x.jpg")])
    assert result.exit_code == 1 and ".png or .npy" in _stderr(result)

    # An output under a regular file cannot be written: one line, no traceback.
    good = tmp_path / "good.npy"
    np.save(good, INSIDE)
    blocked = tmp_path / "good.npy" / "out.png"
    result = runner.invoke(app, ["bev", str(good), "-o", str(blocked)])
    assert result.exit_code == 1 and not isinstance(result.exception, OSError)
    err = _stderr(result)
    assert f"{blocked}: {good} is not a folder" in err and "Traceback" not in err


def test_points_outside_the_window_are_reported(tmp_path: Path) -> None:
    # Millimetres instead of metres: everything lands outside the window.
    path = tmp_path / "mm.npy"
    np.save(path, INSIDE[:, :3] * 1000)
    result = runner.invoke(app, ["bev", str(path), "-o", str(tmp_path / "mm.npy.png")])
    assert result.exit_code == 0, result.output
    err = _stderr(result)
    assert "read 5 points (npy)" in err and "0 in the BEV window" in err
    assert "no point falls in the BEV window" in err


def test_real_scan_bev(realdata: Path, tmp_path: Path) -> None:
    from disco_cli.model.bev import BEVConfig, polar_bev

    scan = realdata / "kitti00" / "velodyne" / "000000.bin"
    out = tmp_path / "real.png"
    result = runner.invoke(
        app, ["bev", str(scan), "-o", str(out), "-s", "2", "--bev-mode", "occupancy"]
    )
    assert result.exit_code == 0, result.output
    points = np.fromfile(scan, np.float32).reshape(-1, 4)
    c = BEVConfig(mode="occupancy")
    xyz = points[:, :3].astype(np.float64)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    window = (r >= c.min_range) & (r < c.max_range) & (xyz[:, 2] >= c.z_min) & (xyz[:, 2] < c.z_max)
    assert f"read {len(points)} points (kitti)" in _stderr(result)
    assert f"; {window.sum()} in the BEV window" in _stderr(result)
    image = decode_png(out.read_bytes())
    assert image.shape == (2 * c.rings, 2 * c.sectors, 3)
    painted = (image[::2, ::2] != np.array(BACKGROUND, np.uint8)).any(axis=2)
    np.testing.assert_array_equal(painted, polar_bev(points, c).any(axis=0))
    assert 0.05 < painted.mean() < 0.9  # a street scene: neither blank nor full


# -- the PNG writer ----------------------------------------------------------------


def test_png_round_trip_gray_and_rgb() -> None:
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, size=(7, 13), dtype=np.uint8)
    np.testing.assert_array_equal(decode_png(encode_png(gray)), gray)
    rgb = rng.integers(0, 256, size=(5, 3, 3), dtype=np.uint8)
    np.testing.assert_array_equal(decode_png(encode_png(rgb)), rgb)
    bads = [np.zeros((4, 4), np.float32), np.zeros((4, 4, 4), np.uint8), np.zeros((0, 3), np.uint8)]
    for bad in bads:
        with pytest.raises(ValueError):
            encode_png(bad)


def test_colormap_and_upscale() -> None:
    rgb = colormap(np.array([0.0, 1.0, 0.5, 2.0, np.nan]), empty=np.array([0, 0, 0, 0, 1], bool))
    # Viridis ends: dark purple (68, 1, 84) and yellow (253, 231, 37); out-of-range clips.
    assert rgb[0].tolist() == [68, 1, 84] and rgb[1].tolist() == [253, 231, 37]
    assert rgb[3].tolist() == rgb[1].tolist() and rgb[4].tolist() == list(BACKGROUND)
    assert rgb[2].tolist() == [33, 144, 141]  # the middle anchor
    big = upscale(np.arange(6, dtype=np.uint8).reshape(2, 3), 2)
    assert big.tolist() == [[0, 0, 1, 1, 2, 2]] * 2 + [[3, 3, 4, 4, 5, 5]] * 2


def test_console_entry_point_prints_one_line_for_a_bad_file(tmp_path: Path) -> None:
    # Through `python -m disco_cli.cli` (the `disco` script's main()), not CliRunner.
    import subprocess
    import sys

    bad = tmp_path / "garbage.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n")
    proc = subprocess.run(
        [sys.executable, "-m", "disco_cli.cli", "bev", str(bad), "-o", str(tmp_path / "o.png")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and "no property 'y'" in lines[0]
    assert proc.stdout == ""
