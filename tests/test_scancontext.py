"""Scan Context: the column-shift distance against a naive loop, and yaw from known rotations."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.model import scancontext as sc


def naive_shift_distance(q: np.ndarray, c: np.ndarray, n: int) -> float:
    """Reference: the paper's formula with candidate c rolled by n sectors, one column at a time."""
    terms = []
    for j in range(q.shape[1]):
        a, b = q[:, j].astype(np.float64), c[:, (j - n) % q.shape[1]].astype(np.float64)
        if np.linalg.norm(a) > 0 and np.linalg.norm(b) > 0:
            terms.append(1.0 - a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.mean(terms)) if terms else 1.0


def random_descriptor(rng: np.random.Generator, rings: int = 20, sectors: int = 60) -> np.ndarray:
    d = rng.random((rings, sectors)) * 5.0
    d[rng.random((rings, sectors)) < 0.4] = 0.0  # empty cells
    d[:, rng.random(sectors) < 0.1] = 0.0  # some empty columns
    return d.astype(np.float32)


def test_shift_distances_match_the_formula():
    rng = np.random.default_rng(0)
    q = random_descriptor(rng)
    cands = np.stack([random_descriptor(rng) for _ in range(3)])
    got = sc.shift_distances(q, cands)
    assert got.shape == (3, 60)
    for k in range(3):
        for n in (0, 1, 17, 59):
            assert got[k, n] == pytest.approx(naive_shift_distance(q, cands[k], n), abs=1e-9)


def test_empty_descriptors_are_at_distance_one():
    q = np.zeros((20, 60), np.float32)
    got = sc.shift_distances(q, np.ones((2, 20, 60), np.float32))
    np.testing.assert_allclose(got, 1.0)


@pytest.mark.parametrize("k", [0, 1, 7, -13, 30, 59])
def test_rolled_descriptor_gives_the_shift_and_the_yaw_sign(k):
    # A query that is the match rotated by +a degrees is the match rolled by +a/6 sectors;
    # the architecture's convention then says yaw_deg = -a.
    rng = np.random.default_rng(1)
    match = random_descriptor(rng)
    query = np.roll(match, k, axis=1)
    other = random_descriptor(rng)
    model = sc.ScanContextModel.__new__(sc.ScanContextModel)  # protocol methods need no config
    dist, yaw = model.rerank(query, np.stack([match, other]))
    assert dist[0] == pytest.approx(0.0, abs=1e-6)
    assert dist[1] > 0.1
    want = -6.0 * k
    err = (yaw[0] - want + 180.0) % 360.0 - 180.0
    assert abs(err) < 1e-6
    assert -180.0 < yaw[0] <= 180.0


def test_ring_keys_count_occupied_cells_and_ignore_rotation():
    d = np.zeros((2, 3, 4), np.float32)
    d[0, 0, :2] = 1.0  # ring 0: 2 of 4 cells
    d[0, 2, :] = 3.0  # ring 2: all 4
    d[1] = np.roll(d[0], 1, axis=1)
    np.testing.assert_allclose(sc.ring_keys(d, "occupancy"), [[0.5, 0.0, 1.0], [0.5, 0.0, 1.0]])
    # Mean cell height: ring 0 (1 + 1 + 0 + 0) / 4, ring 2 all 3.
    np.testing.assert_allclose(sc.ring_keys(d, "mean"), [[0.5, 0.0, 3.0], [0.5, 0.0, 3.0]])
    with pytest.raises(ValueError):
        sc.ring_keys(d, "median")


def test_parabola_refines_between_sectors():
    # Distances of a V shape centred at shift 10.25: the vertex is recovered exactly.
    shifts = np.arange(60)
    d = np.abs(shifts - 10.25)[None] ** 2 * 0.001
    dist, shift = sc.best_shift(d)
    assert shift[0] == pytest.approx(10.25)


# --- through the real voxelizer ------------------------------------------------------------------


def rotate(points: np.ndarray, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    out = points.copy()
    out[:, :3] = points[:, :3] @ rot.T
    return out


def street_scan(seed: int = 0) -> np.ndarray:
    """A small synthetic scene: ground rings, walls and poles of varied heights, 20k points."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, 8000)
    r = rng.uniform(3, 70, 8000)
    ground = np.c_[r * np.cos(ang), r * np.sin(ang), np.full(8000, -1.8)]
    objs = []
    for _ in range(40):
        cx, cy = rng.uniform(-60, 60, 2)
        h = rng.uniform(0.5, 12)
        n = 300
        xy = np.c_[cx + rng.normal(0, 1.0, n), cy + rng.normal(0, 1.0, n)]
        objs.append(np.c_[xy, rng.uniform(-1.8, h, n)])
    pts = np.vstack([ground, *objs])
    return np.c_[pts, np.zeros(len(pts))].astype(np.float32)


@pytest.fixture(scope="module")
def model():
    pytest.importorskip("disco_cli.model.bev")
    return sc.ScanContextModel()


def test_model_protocol(model):
    from disco_cli.model.bev import polar_bev

    assert model.name == "scancontext"
    assert model.query_policy.rerank_candidates > 0
    bev = polar_bev(street_scan(), model.bev_config)
    assert bev.shape == (1, 20, 60)
    sig, feats = model.embed(bev[None])
    assert sig.shape == (1, 20) and sig.dtype == np.float32
    assert feats.shape == (1, 20, 60) and feats.dtype == np.float32
    assert sc.ScanContextModel().fingerprint == model.fingerprint
    assert json_roundtrip(model.config_dict()) == model.config_dict()
    with pytest.raises(ValueError):
        model.embed(np.zeros((1, 2, 20, 60), np.float32))


def json_roundtrip(d: dict) -> dict:
    import json

    return json.loads(json.dumps(d))


@pytest.mark.parametrize("deg", [33.0, -90.0, 150.0, 178.0])
def test_rotated_scan_gives_minus_the_rotation(model, deg):
    from disco_cli.model.bev import polar_bev

    scan = street_scan(2)
    clouds = [scan, rotate(scan, deg), street_scan(3)]
    sig, feats = model.embed(np.stack([polar_bev(c, model.bev_config) for c in clouds]))
    dist, yaw = model.rerank(feats[1], feats[:1])
    err = (yaw[0] - (-deg) + 180.0) % 360.0 - 180.0
    assert abs(err) <= 6.0, (yaw, deg)
    # The ring key hardly moves with the rotation (points change cells at sector edges
    # only): far less than to another scene.
    assert np.linalg.norm(sig[0] - sig[1]) < 0.25 * np.linalg.norm(sig[0] - sig[2])


def test_real_scan_rotated(model, realdata):
    from disco_cli.io.readers import read_scan
    from disco_cli.model.bev import polar_bev

    scan = read_scan(realdata / "kitti00" / "velodyne" / "000000.bin")
    for deg in (47.0, -120.0):
        pair = [polar_bev(scan, model.bev_config), polar_bev(rotate(scan, deg), model.bev_config)]
        _, feats = model.embed(np.stack(pair))
        _, yaw = model.rerank(feats[1], feats[:1])
        assert abs((yaw[0] + deg + 180.0) % 360.0 - 180.0) <= 6.0
