"""Yaw without parallax: the query's feature image re-centred on the match's position.

Phase correlation along sectors (`yaw.py`) is exact only when the two scans were taken
at the same spot. A revisit a few metres to the side sees every object under another
bearing (about t / r for an object at range r): facades 5-10 m away in a street move by
tens of degrees, and the correlation peak lands one or two degrees off, or on the
opposite heading in a street that looks alike both ways.

Here the query's polar image is resampled as seen from candidate positions around the
query sensor (bilinear in ring and sector, in the query's own frame, so the unknown yaw
stays a circular shift), each resampled image is phase-correlated with the match's, and
the position whose correlation peaks highest wins: a 3 x 3 grid 3 m apart, then two
rounds of its 8 neighbours at 1.5 m and 0.5 m. Its peak is the yaw. 25 resamplings of a
40 x 120 image cost about 1.5 ms; docs/research/model-history.md has the figures.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from disco_cli.model import fft
from disco_cli.model.yaw import (
    curves_of_cross_power,
    margin,
    peak_shift,
    ring_weights,
    second_peak,
    shift_to_yaw,
)

# Bumped whenever the refined yaw can change for the same weights (cached evaluations
# key on it: benchmarks/ood_suite.py). 4: the second heading checked (`refine_checked`).
VERSION = 4
# Below this yaw confidence the best other heading is searched for too, and the two are
# told apart by the plain correlation of the images (`refine_checked`). A street alike on
# both sides gives 0.1-0.55, an asymmetric one 0.8-0.95 (tests/test_yaw_flip.py).
CHECK_BELOW = 0.6
# The first grid's half width (m) of the check's searches: 6 + 1.5 + 0.5 = 8 m reached.
CHECK_REACH = 6.0

# Search schedule (m): the first grid's spacing and half width, then the finer steps.
COARSE_STEP = 3.0
COARSE_REACH = 3.0
FINE_STEPS = (1.5, 0.5)
_NEIGHBOURS = np.array(
    [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1) if (a, b) != (0, 0)], np.float32
)


@lru_cache(maxsize=8)
def _grid(rings: int, sectors: int, max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Cartesian centres (x, y) [R, S] of the polar cells, in m."""
    dr = max_range / rings
    r = (np.arange(rings) + 0.5) * dr
    theta = (np.arange(sectors) + 0.5) * (2.0 * np.pi / sectors)
    x = (r[:, None] * np.cos(theta)[None]).astype(np.float32)
    y = (r[:, None] * np.sin(theta)[None]).astype(np.float32)
    return x, y


def recentre(image: np.ndarray, positions: np.ndarray, max_range: float) -> np.ndarray:
    """Polar image [R, S] as seen from `positions` [M, 2] (m, the image's own frame).

    Cell (ring, sector) of view m holds the image's bilinear sample at the point that
    lies at that ring and sector from positions[m]. Beyond the outer ring, and inside
    the inner ring's centre, is empty (0).
    """
    img = np.asarray(image, dtype=np.float32)
    return _sample(img, _sampling(*img.shape, float(max_range), positions))


def _sampling(rings: int, sectors: int, max_range: float, positions: np.ndarray) -> tuple:
    """Where `recentre` reads: flat indices into `_pairs`' table and the weights."""
    x0, y0 = _grid(rings, sectors, max_range)
    pos = np.asarray(positions, dtype=np.float32).reshape(-1, 2)
    x = x0[None] + pos[:, 0, None, None]
    y = y0[None] + pos[:, 1, None, None]
    # Fractional ring index, shifted by one for the zero row padded in front; sector
    # index shifted by one turn so that it is positive (arctan2 >= -pi).
    ring_f = np.sqrt(x * x + y * y) * np.float32(rings / max_range) + np.float32(0.5)
    sector_f = np.arctan2(y, x) * np.float32(sectors / (2.0 * np.pi)) + np.float32(sectors - 0.5)
    # Both are >= 0: truncation is the floor. Weights stay float32 (int32 would promote).
    ring_f = np.minimum(ring_f, np.float32(rings + 1))
    r0 = ring_f.astype(np.int32)
    s0 = sector_f.astype(np.int32)
    fr = ring_f - r0.astype(np.float32)
    fs = sector_f - s0.astype(np.float32)
    width = 2 * sectors + 1
    i0 = r0 * width + s0
    i1 = np.minimum(r0 + 1, rings + 1) * width + s0
    return i0, i1, fs, fr


@lru_cache(maxsize=8)
def _coarse_sampling(
    rings: int, sectors: int, max_range: float, reach: float = COARSE_REACH
) -> tuple[np.ndarray, tuple]:
    """The first search grid's positions [M, 2] and their `_sampling`, computed once."""
    k = np.arange(-reach, reach + 1e-6, COARSE_STEP, dtype=np.float32)
    positions = np.stack(np.meshgrid(k, k, indexing="ij"), -1).reshape(-1, 2)
    return positions, _sampling(rings, sectors, max_range, positions)


def _pairs(img: np.ndarray) -> np.ndarray:
    """The image padded (a zero ring before the first and after the last; the sectors
    twice and the first once more, so that sector indices in [S - 1, 2 S] never wrap),
    each cell paired with its next sector and read as one float64: two gathers, not four."""
    rings, sectors = img.shape
    padded = np.zeros((rings + 2, 2 * sectors + 1), np.float32)
    padded[1 : rings + 1, :sectors] = img
    padded[1 : rings + 1, sectors : 2 * sectors] = img
    padded[1 : rings + 1, 2 * sectors] = img[:, 0]
    flat = padded.ravel()
    return np.stack([flat[:-1], flat[1:]], axis=-1).view(np.float64).ravel()


def _sample(img: np.ndarray, sampling: tuple, pairs: np.ndarray | None = None) -> np.ndarray:
    i0, i1, fs, fr = sampling
    table = _pairs(img) if pairs is None else pairs
    near = np.take(table, i0).view(np.float32).reshape(*i0.shape, 2)
    far = np.take(table, i1).view(np.float32).reshape(*i1.shape, 2)
    near = near[..., 0] + (near[..., 1] - near[..., 0]) * fs
    far = far[..., 0] + (far[..., 1] - far[..., 0]) * fs
    return near + (far - near) * fr


def _curves(views: np.ndarray, match_spectrum: np.ndarray) -> np.ndarray:
    """Phase-correlation curves [M, S] of views [M, R, S] against one match's spectrum
    (yaw.py's curves; float32 weights keep the sums in single precision)."""
    cross = fft.rfft(views, axis=-1) * np.conj(match_spectrum)[None]
    weights = ring_weights(views.shape[1]).astype(np.float32)
    return curves_of_cross_power(cross, weights, views.shape[-1])


def refine_one(
    query: np.ndarray, match: np.ndarray, max_range: float
) -> tuple[float, np.ndarray, float]:
    """(yaw_deg, position [2] of the match's sensor in the query frame (m), peak value)."""
    q = np.asarray(query, dtype=np.float32)
    m = np.asarray(match, dtype=np.float32)
    if q.ndim != 2 or q.shape != m.shape:
        raise ValueError(
            f"query and match must be [R, S] images of one shape: {q.shape}, {m.shape}"
        )
    fm = fft.rfft(m, axis=-1)
    best_pos, best_val, best_curve = _search(q, fm, _pairs(q), float(max_range))
    yaw = float(shift_to_yaw(peak_shift(best_curve[None]), q.shape[1])[0])
    return yaw, np.asarray(best_pos, np.float64), best_val


def _search(
    q: np.ndarray,
    fm: np.ndarray,
    table: np.ndarray,
    max_range: float,
    window: np.ndarray | None = None,
    reach: float = COARSE_REACH,
) -> tuple[np.ndarray, float, np.ndarray]:
    """The re-centring search: (position, peak value, curve) of the view whose curve
    peaks highest; with `window` (sector shifts), the peak is sought among those only;
    `reach`: the first grid's half width (m)."""
    rings, sectors = q.shape
    positions, sampling = _coarse_sampling(rings, sectors, max_range, reach)
    best_pos, best_val, best_curve = positions[0], -np.inf, None
    for step in (None, *FINE_STEPS):
        if step is not None:
            positions = best_pos + _NEIGHBOURS * np.float32(step)
            sampling = _sampling(rings, sectors, max_range, positions)
        curves = _curves(_sample(q, sampling, table), fm)
        peaks = (curves if window is None else curves[:, window]).max(axis=1)
        i = int(np.argmax(peaks))
        if peaks[i] > best_val:
            best_pos, best_val, best_curve = positions[i], float(peaks[i]), curves[i]
    return best_pos, best_val, best_curve


def refine_checked(
    query: np.ndarray, match: np.ndarray, max_range: float
) -> tuple[float, np.ndarray, float]:
    """(yaw_deg, position [2] of the match's sensor in the query frame (m), yaw confidence
    in [0, 1]): `refine_one`, with the opposite heading (or any other strong one) ruled
    out by evidence that does not share phase correlation's failure.

    On a street alike on both sides, the whitened phase correlation (every frequency
    weighted alike) can peak as high on theta + 180 degrees as on theta, and the greedy
    position search may settle near the wrong one. When the best other heading comes
    within CHECK_BELOW of the best (the confidence, 1 - other / best), each of the two
    headings gets searches of its own, one as wide as the first and one reaching
    CHECK_REACH + 2 m (revisits 4-8 m aside lie beyond the first search's 5 m); the
    other heading wins only where both its own phase-correlation peak is the higher and
    its re-centred query correlates better with the match in the plain normalized
    correlation of the images (large structures weigh most there, as in the
    training-free floor's occupancy correlation). The confidence is then the margin
    between the two headings' own peaks."""
    q = np.asarray(query, dtype=np.float32)
    m = np.asarray(match, dtype=np.float32)
    if q.ndim != 2 or q.shape != m.shape:
        raise ValueError(
            f"query and match must be [R, S] images of one shape: {q.shape}, {m.shape}"
        )
    sectors = q.shape[1]
    fm = fft.rfft(m, axis=-1)
    table = _pairs(q)
    pos, val, curve = _search(q, fm, table, float(max_range))
    best = int(np.argmax(curve))
    idx, peak = second_peak(curve[None], np.array([best]))
    other, other_val = int(idx[0]), float(peak[0])
    conf = float(margin(val, other_val))
    if conf < CHECK_BELOW:
        v1, ncc1, _, _ = _heading(q, m, fm, table, float(max_range), best)
        v2, ncc2, pos2, curve2 = _heading(q, m, fm, table, float(max_range), other)
        v1 = max(v1, val)
        if v2 > v1 and ncc2 > ncc1:
            pos, curve, conf = pos2, curve2, float(margin(v2, v1))
        else:
            conf = float(margin(v1, max(v2, other_val)))
    yaw = float(shift_to_yaw(peak_shift(curve[None]), sectors)[0])
    return yaw, np.asarray(pos, np.float64), conf


def _heading(
    q: np.ndarray, m: np.ndarray, fm: np.ndarray, table: np.ndarray, max_range: float, centre: int
) -> tuple[float, float, np.ndarray, np.ndarray]:
    """The evidence for one heading (sector `centre`, +-2 sectors): (its highest phase-
    correlation peak over the two searches, the higher plain correlation of their
    re-centred views, the position and curve, peak kept in the window, of the first)."""
    sectors = q.shape[1]
    window = (centre + np.arange(-2, 3)) % sectors
    best_val, best_ncc, best_pos, best_curve = -np.inf, -np.inf, None, None
    for reach in (COARSE_REACH, CHECK_REACH):
        p, v, c = _search(q, fm, table, max_range, window, reach)
        inside = np.full(sectors, c[window].min(), c.dtype)  # the peak stays in the window
        inside[window] = c[window]
        best_ncc = max(best_ncc, _aligned_ncc(q, m, p, int(np.argmax(inside)), max_range))
        if v > best_val:
            best_val, best_pos, best_curve = v, p, inside
    return best_val, best_ncc, best_pos, best_curve


def _aligned_ncc(
    q: np.ndarray, m: np.ndarray, position: np.ndarray, shift: int, max_range: float
) -> float:
    """Normalized correlation of the query re-centred at `position` and turned by `shift`
    sectors onto the match, with the match."""
    view = np.roll(recentre(q, np.asarray(position)[None], max_range)[0], -shift, axis=1)
    a = view - view.mean()
    b = m - m.mean()
    norm = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float((a * b).sum()) / norm if norm > 0 else 0.0


def refine_yaw_conf(
    query: np.ndarray, matches: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """(yaw [K] in degrees, (-180, 180], yaw confidence [K] in [0, 1]) of the query
    [R, S] relative to each match [K, R, S] (`refine_checked`)."""
    m = np.asarray(matches)
    if m.ndim == 2:
        m = m[None]
    out = [refine_checked(query, mk, max_range) for mk in m]
    yaw = np.array([o[0] for o in out], np.float32)
    return _wrapped(yaw), np.array([o[2] for o in out], np.float32)


def _wrapped(yaw: np.ndarray) -> np.ndarray:
    # Rounding to float32 can turn -179.99999 into -180, which is outside (-180, 180].
    return np.where(yaw <= -180.0, np.float32(180.0), yaw)


def query_in_match_frame(
    query: np.ndarray, match: np.ndarray, max_range: float
) -> tuple[float, np.ndarray]:
    """(yaw_deg, position [2] of the query sensor in the match's frame (m)): where the
    query was taken, seen from the match, to the accuracy of the search (median 0.26 m
    on the suite's hits, docs/research/model-history.md); reaches 5 m (3 + 1.5 + 0.5)
    at most."""
    yaw, position, _ = query_in_match_frame_conf(query, match, max_range)
    return yaw, position


def query_in_match_frame_conf(
    query: np.ndarray, match: np.ndarray, max_range: float
) -> tuple[float, np.ndarray, float]:
    """`query_in_match_frame` and the yaw's confidence (`refine_checked`)."""
    yaw, match_in_query, conf = refine_checked(query, match, max_range)
    c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    # The match sensor sits at p in the query frame, so the query sits at -R p in the
    # match frame, R turning query axes into match axes (the yaw).
    px, py = match_in_query
    position = -np.array([c * px - s * py, s * px + c * py])
    return float(_wrapped(np.float32(yaw))), position, conf


def refine_yaw(query: np.ndarray, matches: np.ndarray, max_range: float) -> np.ndarray:
    """Yaw [K] in degrees, (-180, 180], of the query [R, S] relative to each match [K, R, S],
    with the parallax of the offset between the two sensors removed."""
    return refine_yaw_conf(query, matches, max_range)[0]
