"""Yaw by phase correlation: sign convention, sub-bin accuracy, batching, real scans."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.model.yaw import (
    correlation_curves,
    correlation_curves_torch,
    estimate_yaw,
    peak_shift,
    wrap_deg,
)

R, S = 40, 120


def rotate(points: np.ndarray, deg: float) -> np.ndarray:
    """Points R(deg) p about z (the scan seen by a sensor turned by -deg)."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def angle_diff(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    return np.abs((np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0)


def test_integer_roll_gives_exact_yaw_with_the_documented_sign():
    rng = np.random.default_rng(1)
    match = rng.random((R, S)).astype(np.float32)
    for k in (1, 7, 30, 59, 61, 100, 119):
        query = np.roll(match, k, axis=-1)  # the match scan rotated by +3k degrees
        got = estimate_yaw(query, match[None])[0]
        expected = wrap_deg(-3.0 * k)
        assert abs(got - expected) < 1e-3, (k, got, expected)


def test_half_turn_is_plus_180_not_minus_180():
    rng = np.random.default_rng(2)
    match = rng.random((R, S)).astype(np.float32)
    got = estimate_yaw(np.roll(match, S // 2, axis=-1), match[None])[0]
    assert got == pytest.approx(180.0, abs=1e-3)
    assert wrap_deg(-180.0) == 180.0


def test_fractional_shift_is_refined_below_one_bin():
    # A smooth ring pattern shifted by a fractional number of sectors (Fourier shift).
    rng = np.random.default_rng(3)
    theta = np.arange(S) * 2 * np.pi / S
    base = np.zeros((R, S))
    for r in range(R):
        for _ in range(3):
            c = rng.uniform(0, 2 * np.pi)
            base[r] += np.exp(4 * (np.cos(theta - c) - 1))
    for shift in (0.3, 10.5, 47.8, -20.25):
        freq = np.fft.rfftfreq(S) * S
        shifted = np.fft.irfft(
            np.fft.rfft(base, axis=-1) * np.exp(-2j * np.pi * freq * shift / S), n=S
        )
        got = estimate_yaw(shifted.astype(np.float32), base[None].astype(np.float32))[0]
        assert angle_diff(got, -3.0 * shift) < 0.5, (shift, got)


def test_batched_candidates_each_get_their_own_yaw():
    rng = np.random.default_rng(4)
    query = rng.random((R, S)).astype(np.float32)
    shifts = np.array([0, 5, 33, 90, 119, 60, 2, 47, 71, 118])
    matches = np.stack([np.roll(query, -k, axis=-1) for k in shifts])  # query = roll(match, k)
    got = estimate_yaw(query, matches)
    assert got.shape == (10,)
    np.testing.assert_allclose(angle_diff(got, wrap_deg(-3.0 * shifts)), 0, atol=1e-3)


def test_parabolic_peak_matches_a_sampled_parabola():
    # A curve that is an exact parabola near its top: the fit must return its vertex.
    x = np.arange(S, dtype=np.float64)
    vertex = 37.3
    curves = -((x - vertex) ** 2)[None]
    assert peak_shift(curves)[0] == pytest.approx(vertex, abs=1e-9)


def test_torch_curves_equal_a_direct_numpy_reference():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(5)
    q = rng.random((3, 6, 16)).astype(np.float32)
    m = rng.random((3, 6, 16)).astype(np.float32)
    # Reference: whitened cross-power per ring through complex DFTs, rings weighted by
    # radius (ring index + 1/2), weights summing to 1.
    fq, fm = np.fft.fft(q, axis=-1), np.fft.fft(m, axis=-1)
    cross = fq * np.conj(fm)
    mag = np.abs(cross)
    floor = 1e-3 * mag.max(axis=(1, 2), keepdims=True) + 1e-12
    w = np.array([0.5, 1.5, 2.5, 3.5, 4.5, 5.5]) / 18.0
    ref = (np.fft.ifft(cross / (mag + floor), axis=-1).real * w[None, :, None]).sum(axis=1)
    got_t = correlation_curves_torch(torch.from_numpy(q), torch.from_numpy(m)).numpy()
    np.testing.assert_allclose(got_t, ref, atol=1e-5)
    for b in range(3):
        np.testing.assert_allclose(correlation_curves(q[b], m[b][None])[0], ref[b], atol=1e-5)


def _models() -> list[str]:
    from disco_cli.model import DEFAULT_WEIGHTS

    return ["spectral"] + (["default"] if DEFAULT_WEIGHTS.is_file() else [])


@pytest.mark.parametrize("name", _models())
def test_real_scan_rotated_over_the_whole_circle(realdata, name):
    from disco_cli.io.readers import read_scan
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    model = load_model(name)
    points = read_scan(realdata / "kitti00" / "velodyne" / "000000.bin")
    _, f0 = model.embed(polar_bev(points)[None])
    rng = np.random.default_rng(6)
    angles = np.concatenate([[30.0, -90.0, 180.0], rng.uniform(-180.0, 180.0, 9)])
    bevs = np.stack([polar_bev(rotate(points, a)) for a in angles])
    _, feats = model.embed(bevs)
    for a, f in zip(angles, feats):
        got = model.yaw(f, f0)[0]
        assert -180.0 < got <= 180.0
        assert angle_diff(got, -a) < 1.5, (a, got)
    # The sign, spelled out: points turned by +30 degrees mean the sensor turned by -30.
    assert model.yaw(feats[0], f0)[0] == pytest.approx(-30.0, abs=1.5)


@pytest.mark.parametrize("name", _models())
def test_consecutive_real_frames_give_the_ground_truth_yaw(realdata, name):
    from disco_cli.io.poses import read_kitti_poses, relative_yaw_deg
    from disco_cli.io.readers import read_scan
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    seq = realdata / "kitti00"
    poses = read_kitti_poses(seq / "poses.txt", seq / "calib.txt")
    model = load_model(name)
    rng = np.random.default_rng(7)
    for i in (0, 4, 8):
        spin = float(rng.uniform(-180.0, 180.0))
        m_pts = read_scan(seq / "velodyne" / f"{i:06d}.bin")
        q_pts = rotate(read_scan(seq / "velodyne" / f"{i + 1:06d}.bin"), spin)
        _, feats = model.embed(np.stack([polar_bev(q_pts), polar_bev(m_pts)]))
        truth = wrap_deg(relative_yaw_deg(poses[i], poses[i + 1]) - spin)
        assert angle_diff(model.yaw(feats[0], feats[1:])[0], truth) < 1.5, (i, spin)
