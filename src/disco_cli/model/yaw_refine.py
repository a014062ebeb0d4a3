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
rounds of its 8 neighbours at 1.5 m and 0.5 m. Its peak is the yaw.

Every position lies on a 0.5 m lattice, so the searches share their work: where a view
reads is kept per position, and the curves per query and match (on the NumPy path also
the query's views and their spectra per query: its matches are searched from the same
positions).

The searches and the heading check's plain correlation run in C++
(`_core.recentre_search`, `_core.recentre_nccs`; GIL released): 1.0-1.2 ms a query of
the streaming benchmark. The NumPy path (`BACKEND = "numpy"`: the tests' reference, and
the fallback without the kernels) costs about 2.9 ms.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from functools import cached_property, lru_cache
from typing import Any

import numpy as np

from disco_cli.model import fft, recentre_places
from disco_cli.model.compiled import compiled_core
from disco_cli.model.recentre_places import grid as _grid
from disco_cli.model.yaw import (
    curves_of_cross_power,
    margin,
    peak_shift,
    ring_weights32,
    second_peak,
    separation_bins,
    shift_to_yaw,
)

# Bumped whenever the refined yaw can change for the same weights (cached evaluations
# key on it: benchmarks/ood_suite.py). 4: the second heading checked (`refine_checked`);
# 5: the first grid reaching SIDE_REACH along the query's y axis.
VERSION = 5
# Below this yaw confidence the best other heading is searched for too, and the two are
# told apart by the plain correlation of the images (`refine_checked`). A street alike on
# both sides gives 0.1-0.55, an asymmetric one 0.8-0.95 (tests/test_yaw_flip.py). The
# query stage passes its policy's `yaw_check_below` (the same by default); 0: no check.
CHECK_BELOW = 0.6
# The first grid's half width (m) of the check's searches: 6 + 1.5 + 0.5 = 8 m reached.
CHECK_REACH = 6.0

# Search schedule (m): the first grid's spacing and half width, then the finer steps.
COARSE_STEP = 3.0
COARSE_REACH = 3.0
# Along the query's own y axis (to its sides) the first grid reaches further, as far as
# the query's side views (`DiscoModel.query_views`): a revisit 6-8 m aside, found by a
# view, peaks 0.3-0.45 where it was taken and 0.1-0.2 within 5 m, where the search
# settled on a wrong heading (docs/research/model-history.md, "Query-side views").
SIDE_REACH = 6.0
FINE_STEPS = (1.5, 0.5)
_NEIGHBOURS = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1) if (a, b) != (0, 0)])

# Which code computes the curves: None, the compiled kernel where the core has it, else
# NumPy; "numpy", the NumPy reference. Read when a query's searches start.
BACKEND: str | None = None
# The compiled kernel's views hold their rings padded to a multiple of this (its
# vectors' lanes at every SIMD level).
_LANES = 16


def _kernel() -> Any:
    """`disco_cli._core` where BACKEND lets it compute the curves and it can, else None."""
    return compiled_core(BACKEND, "yaw_refine", "recentre_curves")


def _padded_rings(rings: int) -> int:
    return -(-rings // _LANES) * _LANES


def recentre(image: np.ndarray, positions: np.ndarray, max_range: float) -> np.ndarray:
    """Polar image [R, S] as seen from `positions` [M, 2] (m, the image's own frame).

    Cell (ring, sector) of view m holds the image's bilinear sample at the point that
    lies at that ring and sector from positions[m]. Beyond the outer ring, and inside
    the inner ring's centre, is empty (0).
    """
    img = np.asarray(image, dtype=np.float32)
    rings, sectors = img.shape
    places = _places(rings, sectors, float(max_range), positions)
    return _resample(_padded(img), places, img.shape)


def _places(rings: int, sectors: int, max_range: float, positions: np.ndarray) -> list:
    """Where each view of `recentre` reads: per position, float32 [2, R * S] holding each
    cell's fractional ring and sector in `_padded`'s image (the C++ reads take the
    corner and the fractions from them)."""
    x0, y0 = _grid(rings, sectors, max_range)
    pos = np.asarray(positions, dtype=np.float32).reshape(-1, 2)
    x = x0[None] + pos[:, 0, None, None]
    y = y0[None] + pos[:, 1, None, None]
    # Fractional ring index, shifted by one for the zero row padded in front; sector
    # index shifted by one turn so that it is positive (arctan2 >= -pi). Beyond the
    # outer ring the corner is the zero row after it and the fraction 0.
    ring_f = np.sqrt(x * x + y * y) * np.float32(rings / max_range) + np.float32(0.5)
    ring_f = np.minimum(ring_f, np.float32(rings + 1))
    sector_f = np.arctan2(y, x) * np.float32(sectors / (2.0 * np.pi)) + np.float32(sectors - 0.5)
    both = np.stack([ring_f, sector_f], axis=1)
    return list(both.reshape(len(pos), 2, rings * sectors))


# Every position a search visits lies on one lattice: the coarse grid's and the fine
# steps' multiples of 0.5 m, out to the widest search's reach (33 x 33 positions).
LATTICE_STEP = 0.5
LATTICE_REACH = max(CHECK_REACH, SIDE_REACH) + sum(FINE_STEPS)
_LATTICE_SIDE = int(round(2 * LATTICE_REACH / LATTICE_STEP)) + 1


# Searches move on the lattice in whole cells: each fine step's length in cells.
_FINE_CELLS = tuple(int(round(step / LATTICE_STEP)) for step in FINE_STEPS)
# The neighbours' offsets in flat lattice indices (`_flat`), in _NEIGHBOURS' order.
_NEIGHBOUR_OFFSETS = tuple(int(a) * _LATTICE_SIDE + int(b) for a, b in _NEIGHBOURS)


def _metres(cells: np.ndarray) -> np.ndarray:
    """Positions [M, 2] (m, float32) of lattice cells [M, 2] (exact: multiples of 0.5)."""
    return (cells * LATTICE_STEP - LATTICE_REACH).astype(np.float32)


def _flat(cells: np.ndarray) -> np.ndarray:
    return cells[:, 0] * _LATTICE_SIDE + cells[:, 1]


# Where each view reads is worked out once per lattice position and kept for the
# process's life: computing it (a square root and an arctan2 per cell) cost as much as
# reading the view itself. All 33 x 33 positions of a 40 x 120 image hold 42 MiB; a
# stream of real queries visits a few near the centre, random images most of them.
# Larger grids (a model of another BEV) keep what fits in PLACES_KEPT_BYTES, and start
# afresh when it is full.
PLACES_KEPT_BYTES = 64 << 20
_places_kept: dict[tuple, dict[int, np.ndarray]] = {}


def _places_at(
    rings: int,
    sectors: int,
    max_range: float,
    index: np.ndarray,
    positions: np.ndarray,
    lanes: bool = False,
) -> list:
    """`_places` of lattice `positions` [M, 2] (flat lattice `index` [M]), each
    position's computed once and kept; `lanes`: in the compiled kernel's layout
    (`_lane_places`), kept beside the other under keys past the lattice's."""
    kept = _places_kept.setdefault((rings, sectors, max_range), {})
    keys = (index + _LATTICE_SIDE**2).tolist() if lanes else index.tolist()
    new = [j for j, key in enumerate(keys) if key not in kept]
    if not new:
        return [kept[key] for key in keys]
    # The compiled searches' places in C++ (NumPy's but for a sector's ulp or two); the
    # NumPy layout's as `recentre`'s, to the bit (the query's side views are compared).
    # Below AVX2 the kernel's double-precision arctan2 is slower than NumPy's.
    core = _kernel() if lanes else None
    if core is not None and hasattr(core, "recentre_places") and core._bev_kernel_level() >= 2:
        computed = recentre_places.compiled(core, rings, sectors, max_range, positions[new], True)
    else:
        computed = _places(rings, sectors, max_range, positions[new])
        computed = _lane_places(computed, rings, sectors) if lanes else computed
    places = dict(zip((keys[j] for j in new), computed))
    out = [kept[key] if key in kept else places[key] for key in keys]
    if (len(kept) + len(places)) * computed[0].nbytes > PLACES_KEPT_BYTES:
        kept.clear()
    kept.update(places)
    return out


def _lane_places(places: list, rings: int, sectors: int) -> list:
    """`_places`' tables [2, R * S] as the compiled kernel reads them: [2, S * R],
    sector-major."""
    both = np.stack(places).reshape(len(places), 2, rings, sectors)
    return list(np.ascontiguousarray(both.transpose(0, 1, 3, 2)).reshape(len(places), 2, -1))


def recentre_kept(image: np.ndarray, positions: np.ndarray, max_range: float) -> np.ndarray:
    """`recentre` at lattice `positions` [M, 2] (multiples of LATTICE_STEP within
    LATTICE_REACH), where each position reads kept as the searches' are: views
    [M, R, S] of an image [R, S], or [K, M, R, S] of a stack [K, R, S] (the reads
    looked up once for all K)."""
    img = np.asarray(image, dtype=np.float32)
    pos = np.asarray(positions, dtype=np.float32).reshape(-1, 2)
    cells = np.rint((pos + LATTICE_REACH) / LATTICE_STEP).astype(np.int64)
    metres = _metres(cells)
    # np.allclose's test, without its set-up (this runs on every query).
    on_lattice = (np.abs(metres - pos) <= 1e-8 + 1e-5 * np.abs(pos)).all()
    if not (on_lattice and ((cells >= 0) & (cells < _LATTICE_SIDE)).all()):
        raise ValueError(
            f"positions must lie on the {LATTICE_STEP} m lattice within {LATTICE_REACH} m"
        )
    rings, sectors = img.shape[-2:]
    places = _places_at(rings, sectors, float(max_range), _flat(cells), metres)
    if img.ndim == 2:
        return _resample(_padded(img), places, img.shape)
    return np.stack([_resample(_padded(one), places, one.shape) for one in img])


@lru_cache(maxsize=8)
def _coarse_cells(reach: float = COARSE_REACH, side: float = SIDE_REACH) -> np.ndarray:
    """The first search grid [M, 2] as lattice cells: `reach` m along x, and the larger
    of that and `side` along y."""
    kx = np.arange(-reach, reach + 1e-6, COARSE_STEP)
    side = max(reach, side)
    ky = np.arange(-side, side + 1e-6, COARSE_STEP)
    metres = np.stack(np.meshgrid(kx, ky, indexing="ij"), -1).reshape(-1, 2)
    return np.rint((metres + LATTICE_REACH) / LATTICE_STEP).astype(np.int64)


_coarse_flats: dict[float, tuple[np.ndarray, list[int]]] = {}


def _coarse_flat(reach: float) -> list[int]:
    """`_coarse_cells(reach)` as flat lattice indices, kept while that grid is the one
    `_coarse_cells` keeps (a test may change it and clear its cache)."""
    cells = _coarse_cells(reach)
    kept = _coarse_flats.get(reach)
    if kept is None or kept[0] is not cells:
        kept = _coarse_flats[reach] = (cells, _flat(cells).tolist())
    return kept[1]


def _padded(img: np.ndarray) -> np.ndarray:
    """The image flat with a zero ring before the first and two after the last, and its
    sectors twice and the first once more, so that sector indices in [S - 1, 2 S] never
    wrap: the table `_places` indexes."""
    rings, sectors = img.shape
    padded = np.zeros((rings + 3, 2 * sectors + 1), np.float32)
    padded[1 : rings + 1, :sectors] = img
    padded[1 : rings + 1, sectors : 2 * sectors] = img
    padded[1 : rings + 1, 2 * sectors] = img[:, 0]
    return padded.ravel()


def _resample(padded: np.ndarray, places: list, shape: tuple[int, int]) -> np.ndarray:
    """Views [M, R, S] of an image of `shape` [R, S], read from its `_padded` table at
    `places` (C++: bilinear reads in float32, each rounded as NumPy would)."""
    # deferred: the package imports without the compiled core (a GPU training box)
    from disco_cli import _core

    rings, sectors = shape
    views = _core.resample_views(padded, 2 * sectors + 1, places, rings * sectors)
    return views.reshape(len(places), rings, sectors)


def _curves(spectra: np.ndarray, match_spectrum: np.ndarray, sectors: int) -> np.ndarray:
    """Phase-correlation curves [M, S] of views given by their spectra along sectors
    [M, R, S // 2 + 1] against one match's spectrum (yaw.py's curves; float32 weights
    keep the sums in single precision)."""
    cross = spectra * np.conj(match_spectrum)[None]
    return curves_of_cross_power(cross, ring_weights32(spectra.shape[1]), sectors)


class _QueryViews:
    """The query re-centred at lattice positions, each view and its spectrum along
    sectors computed once: a query's yaw is refined against several matches (the best,
    and after the snap the scan it moves to), whose searches visit the same positions."""

    def __init__(self, q: np.ndarray, max_range: float):
        self.q, self.max_range = q, float(max_range)
        self.padded = _padded(q)
        self._quads: np.ndarray | None = None
        self.kept_views: dict[int, np.ndarray] = {}
        self.kept_spectra: dict[int, np.ndarray] = {}

    def quads(self, core: Any) -> np.ndarray:
        """The compiled kernel's table of the padded image (`_core.recentre_table`)."""
        if self._quads is None:
            self._quads = core.recentre_table(self.padded, 2 * self.q.shape[1] + 1)
        return self._quads

    def spectra(self, index: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """Spectra [M, R, S // 2 + 1] of the views at lattice `positions` [M, 2] (flat
        lattice `index` [M], no repeats)."""
        keys = index.tolist()
        new = [j for j, key in enumerate(keys) if key not in self.kept_spectra]
        if len(new) == len(keys):
            out = fft.rfft(self.views(index, positions), axis=-1)
            self.kept_spectra.update(zip(keys, out))
            return out
        if new:
            computed = fft.rfft(self.views(index[new], positions[new]), axis=-1)
            self.kept_spectra.update(zip((keys[j] for j in new), computed))
        return np.stack([self.kept_spectra[key] for key in keys])

    def views(self, index: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """The views [M, R, S] at lattice `positions` [M, 2] (flat lattice `index` [M])."""
        keys = index.tolist()
        if all(key in self.kept_views for key in keys):
            return np.stack([self.kept_views[key] for key in keys])
        rings, sectors = self.q.shape
        places = _places_at(rings, sectors, self.max_range, index, positions)
        out = _resample(self.padded, places, self.q.shape)
        self.kept_views.update(zip(keys, out))
        return out


# The last few queries' views (a stream refines each query's matches, then moves on).
_QUERIES_KEPT = 2
_queries_kept: OrderedDict = OrderedDict()
_queries_lock = threading.Lock()  # Map.query may be called from several threads


def _query_views(q: np.ndarray, max_range: float) -> _QueryViews:
    key = (float(max_range), q.shape, q.tobytes())
    with _queries_lock:
        views = _queries_kept.get(key)
        if views is None:
            views = _queries_kept[key] = _QueryViews(q, max_range)
            while len(_queries_kept) > _QUERIES_KEPT:
                _queries_kept.popitem(last=False)
    return views


def forget_kept_views() -> None:
    """Drops the kept query views (benchmarks: a repeated query then costs what a new
    one does)."""
    with _queries_lock:
        _queries_kept.clear()


class _Views:
    """The query's views phase-correlated with one match: each lattice position's curve
    is computed once per pair, since the searches of `refine_checked` (the first, and
    two per heading) revisit the same positions."""

    def __init__(self, q: np.ndarray, m: np.ndarray, max_range: float):
        self.q, self.m = q, m
        self.query = _query_views(q, max_range)
        self.core = _kernel()
        if self.core is None:
            self.fm = fft.rfft(m, axis=-1)
        else:
            self.weights = ring_weights32(q.shape[0])
            self.done_flat = np.zeros(_LATTICE_SIDE**2, np.uint8)
            self.nccs: dict[tuple, float] = {}
        self.kept = np.empty((_LATTICE_SIDE**2, q.shape[1]), np.float32)
        self.done = np.zeros(_LATTICE_SIDE**2, bool)

    @cached_property
    def m_centred(self) -> np.ndarray:
        return self.m - self.m.mean()

    @cached_property
    def m_norm(self) -> float:
        return float(np.linalg.norm(self.m_centred))

    def curves(self, cells: np.ndarray) -> np.ndarray:
        """Curves [M, S] of the views at lattice `cells` [M, 2]."""
        index = _flat(cells)
        todo = ~self.done[index]
        new, first = np.unique(index[todo], return_index=True)
        if len(new):  # all new positions in one batch
            spectra = self.query.spectra(new, _metres(cells[todo][first]))
            self.kept[new] = _curves(spectra, self.fm, self.q.shape[1])
            self.done[new] = True
        return self.kept[index]

    def core_searches(
        self, specs: list[tuple[np.ndarray | None, float]]
    ) -> list[tuple[np.ndarray, float, np.ndarray]]:
        """`_searches` on the compiled kernel (`_core.recentre_search`): the same rounds,
        candidates in the same order and the same choices (the first of equal peaks, as
        np.argmax), all rounds in one call once the places they need are kept."""
        rings, sectors = self.q.shape
        q = self.query
        coarse = [_coarse_flat(reach) for _, reach in specs]
        windows = [None if w is None else w.tolist() for w, _ in specs]
        more: dict[int, np.ndarray] = {}  # places computed here, kept or not
        while True:
            kept_places = _places_kept.setdefault((rings, sectors, q.max_range), {})
            missing, found = self.core.recentre_search(
                q.quads(self.core), 2 * sectors + 1, kept_places, more, _LATTICE_SIDE**2,
                self.m, self.weights, _padded_rings(rings), self.kept, self.done_flat,
                coarse, windows, _FINE_CELLS, _NEIGHBOUR_OFFSETS,
            )  # fmt: skip
            if not missing:
                break
            index = np.array(missing)
            cells = np.stack([index // _LATTICE_SIDE, index % _LATTICE_SIDE], axis=1)
            places = _places_at(rings, sectors, q.max_range, index, _metres(cells), lanes=True)
            more.update(zip((index + _LATTICE_SIDE**2).tolist(), places))
        step, reach, side = LATTICE_STEP, LATTICE_REACH, _LATTICE_SIDE  # _metres of each
        return [
            (np.array([f // side * step - reach, f % side * step - reach], np.float32), v,
             self.kept[f].copy())
            for f, v in found
        ]  # fmt: skip

    def view(self, position: np.ndarray) -> np.ndarray:
        """The query re-centred at one lattice `position` [2] (m)."""
        cells = np.rint((np.asarray(position)[None] + LATTICE_REACH) / LATTICE_STEP)
        cells = cells.astype(np.int64)
        return self.query.views(_flat(cells), _metres(cells))[0]

    def core_aligned_ncc(self, position: np.ndarray, shift: int) -> float:
        """`_aligned_ncc` in C++ (`_core.recentre_nccs`, float64 sums), kept per position
        and turn (a heading's two searches often end on the same)."""
        key = (float(position[0]), float(position[1]), shift)
        if key not in self.nccs:
            self.core_nccs([(position, shift)])
        return self.nccs[key]

    def core_nccs(self, turns: list[tuple[np.ndarray, int]]) -> None:
        """Works out and keeps `core_aligned_ncc` of (position, shift) `turns` at once."""
        todo = {(float(p[0]), float(p[1]), shift) for p, shift in turns} - self.nccs.keys()
        if not todo:
            return
        keys = sorted(todo)
        rings, sectors = self.q.shape
        cells = np.rint((np.array([k[:2] for k in keys]) + LATTICE_REACH) / LATTICE_STEP)
        cells = cells.astype(np.int64)
        q = self.query
        places = _places_at(rings, sectors, q.max_range, _flat(cells), _metres(cells), True)
        shifts = [k[2] for k in keys]
        nccs = self.core.recentre_nccs(q.quads(self.core), 2 * sectors + 1, places, self.m, shifts)
        self.nccs.update(zip(keys, nccs))


def _images(query: np.ndarray, match: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = np.asarray(query, dtype=np.float32)
    m = np.asarray(match, dtype=np.float32)
    if q.ndim != 2 or q.shape != m.shape:
        raise ValueError(
            f"query and match must be [R, S] images of one shape: {q.shape}, {m.shape}"
        )
    return q, m


def refine_one(
    query: np.ndarray, match: np.ndarray, max_range: float
) -> tuple[float, np.ndarray, float]:
    """(yaw_deg, position [2] of the match's sensor in the query frame (m), peak value)."""
    views = _Views(*_images(query, match), max_range)
    best_pos, best_val, best_curve = _search(views)
    yaw = float(shift_to_yaw(peak_shift(best_curve[None]), views.q.shape[1])[0])
    return yaw, np.asarray(best_pos, np.float64), best_val


def _search(
    views: _Views, window: np.ndarray | None = None, reach: float = COARSE_REACH
) -> tuple[np.ndarray, float, np.ndarray]:
    """The re-centring search: (position, peak value, curve) of the view whose curve
    peaks highest; with `window` (sector shifts), the peak is sought among those only;
    `reach`: the first grid's half width (m)."""
    return _searches(views, [(window, reach)])[0]


def _searches(
    views: _Views, specs: list[tuple[np.ndarray | None, float]]
) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """`_search` for each (window, reach) of `specs`, run side by side so that each
    round's new views are computed in one batch; each search's result is what it gives
    alone."""
    if views.core is not None:
        return views.core_searches(specs)
    found = [(_coarse_cells(reach)[0], -np.inf, None) for _, reach in specs]
    for step in (None, *_FINE_CELLS):
        if step is None:
            rounds = [_coarse_cells(reach) for _, reach in specs]
        else:
            rounds = [best + _NEIGHBOURS * step for best, _, _ in found]
        curves = views.curves(np.concatenate(rounds))
        start = 0
        for n, ((window, _), cells) in enumerate(zip(specs, rounds)):
            mine = curves[start : start + len(cells)]
            start += len(cells)
            peaks = (mine if window is None else mine[:, window]).max(axis=1)
            i = int(np.argmax(peaks))
            if peaks[i] > found[n][1]:
                found[n] = (cells[i], float(peaks[i]), mine[i])
    return [(_metres(cell[None])[0], value, curve) for cell, value, curve in found]


def refine_checked(
    query: np.ndarray, match: np.ndarray, max_range: float, check_below: float = CHECK_BELOW
) -> tuple[float, np.ndarray, float]:
    """(yaw_deg, position [2] of the match's sensor in the query frame (m), yaw confidence
    in [0, 1]): `refine_one`, with the opposite heading (or any other strong one) ruled
    out by evidence that does not share phase correlation's failure.

    On a street alike on both sides, the whitened phase correlation (every frequency
    weighted alike) can peak as high on theta + 180 degrees as on theta, and the greedy
    position search may settle near the wrong one. When the best other heading comes
    within `check_below` of the best (the confidence, 1 - other / best), each of the two
    headings gets searches of its own, one as wide as the first and one reaching
    CHECK_REACH + 2 m (revisits 4-8 m aside lie beyond the first search's 5 m); the
    other heading wins only where both its own phase-correlation peak is the higher and
    its re-centred query correlates better with the match in the plain normalized
    correlation of the images (large structures weigh most there, as in the
    training-free floor's occupancy correlation). The confidence is then the margin
    between the two headings' own peaks."""
    views = _Views(*_images(query, match), max_range)
    if views.core is not None:
        return _refine_checked_core(views, check_below)
    sectors = views.q.shape[1]
    pos, val, curve = _search(views)
    best = int(np.argmax(curve))
    idx, peak = second_peak(curve[None], np.array([best]))
    other, other_val = int(idx[0]), float(peak[0])
    conf = float(margin(val, other_val))
    if conf < check_below:
        windows = [(c + np.arange(-2, 3)) % sectors for c in (best, other)]
        found = _searches(views, [(w, r) for w in windows for r in (COARSE_REACH, CHECK_REACH)])
        v1, ncc1, _, _ = _heading(views, windows[0], found[:2])
        v2, ncc2, pos2, curve2 = _heading(views, windows[1], found[2:])
        v1 = max(v1, val)
        if v2 > v1 and ncc2 > ncc1:
            pos, curve, conf = pos2, curve2, float(margin(v2, v1))
        else:
            conf = float(margin(v1, max(v2, other_val)))
    yaw = float(shift_to_yaw(peak_shift(curve[None]), sectors)[0])
    return yaw, np.asarray(pos, np.float64), conf


def _refine_checked_core(views: _Views, check_below: float) -> tuple[float, np.ndarray, float]:
    """`refine_checked`'s steps with the compiled searches, and its small steps on one
    curve in Python scalars (NumPy calls of a few microseconds each): the same
    choices, in the same float32 and float64 roundings."""
    sectors = views.q.shape[1]
    pos, val, curve = views.core_searches([(None, COARSE_REACH)])[0]
    best = int(curve.argmax())
    other, other_val = _second_peak_of(curve, best)
    conf = _margin(val, other_val)
    if conf < check_below:
        windows = [_window(c, sectors) for c in (best, other)]
        specs = [(w, r) for w in windows for r in (COARSE_REACH, CHECK_REACH)]
        found = views.core_searches(specs)
        turns = [_turned(c, windows[i // 2]) for i, (_, _, c) in enumerate(found)]
        views.core_nccs([(p, shift) for (p, _, _), (_, shift) in zip(found, turns)])
        v1, ncc1, _, _ = _heading(views, windows[0], found[:2], turns[:2])
        v2, ncc2, pos2, curve2 = _heading(views, windows[1], found[2:], turns[2:])
        v1 = max(v1, val)
        if v2 > v1 and ncc2 > ncc1:
            pos, curve, conf = pos2, curve2, _margin(v2, v1)
        else:
            conf = _margin(v1, max(v2, other_val))
    return _yaw_of(curve), np.asarray(pos, np.float64), conf


def _yaw_of(curve: np.ndarray) -> float:
    """shift_to_yaw(peak_shift(curve[None]))[0] of one float32 curve [S]."""
    sectors = len(curve)
    idx = int(curve.argmax())
    c0, cm, cp = curve[idx], curve[(idx - 1) % sectors], curve[(idx + 1) % sectors]
    denom = cm - 2.0 * c0 + cp
    offset = 0.5 * (cm - cp) / denom if abs(denom) > 1e-12 else np.float32(0.0)
    a = -(idx + float(min(max(offset, np.float32(-0.5)), np.float32(0.5)))) * 360.0 / sectors
    return a - 360.0 * math.ceil((a - 180.0) / 360.0)


def _second_peak_of(curve: np.ndarray, best: int) -> tuple[int, float]:
    """second_peak(curve[None], [best]) of one curve [S], as (int, float)."""
    others = _others(len(curve), best)
    if not len(others):
        return 0, -np.inf
    j = int(others[curve[others].argmax()])
    return j, float(curve[j])


@lru_cache(maxsize=1024)
def _others(sectors: int, best: int) -> np.ndarray:
    """The sectors `second_peak` looks at for a curve peaking at `best`, ascending."""
    s = np.arange(sectors)
    return s[np.abs((s - best + sectors // 2) % sectors - sectors // 2) > separation_bins(sectors)]


def _margin(best: float, other: float) -> float:
    """`margin` of two Python floats."""
    o = max(float(other), 0.0)
    conf = 1.0 - o / best if best > 0 else 0.0
    return min(max(conf, 0.0), 1.0)


def _heading(
    views: _Views,
    window: np.ndarray,
    found: list[tuple[np.ndarray, float, np.ndarray]],
    turns: list[tuple[np.ndarray, int]] | None = None,
) -> tuple[float, float, np.ndarray, np.ndarray]:
    """The evidence for one heading (the sector shifts `window`, its centre +-2) from its
    two searches `found` (as wide as the first, and reaching CHECK_REACH): (its highest
    phase-correlation peak, the higher plain correlation of their re-centred views, the
    position and curve, peak kept in the window, of the search with that peak); `turns`:
    `_turned` of each search's curve, where the caller has them."""
    best_val, best_ncc, best_pos, best_curve = -np.inf, -np.inf, None, None
    for n, (p, v, c) in enumerate(found):
        inside, shift = _turned(c, window) if turns is None else turns[n]
        best_ncc = max(best_ncc, _aligned_ncc(views, p, shift))
        if v > best_val:
            best_val, best_pos, best_curve = v, p, inside
    return best_val, best_ncc, best_pos, best_curve


@lru_cache(maxsize=1024)
def _window(centre: int, sectors: int) -> np.ndarray:
    """The check's window of sector shifts round `centre`: (centre + [-2, 2]) mod S."""
    window = (centre + np.arange(-2, 3)) % sectors
    window.flags.writeable = False
    return window


def _turned(curve: np.ndarray, window: np.ndarray) -> tuple[np.ndarray, int]:
    """(the curve with its peak kept in `window`: elsewhere the window's least, its
    argmax)."""
    inside = np.full(len(curve), curve[window].min(), curve.dtype)
    inside[window] = curve[window]
    return inside, int(np.argmax(inside))


def _aligned_ncc(views: _Views, position: np.ndarray, shift: int) -> float:
    """Normalized correlation of the query re-centred at `position` and turned by `shift`
    sectors onto the match, with the match."""
    if views.core is not None:
        return views.core_aligned_ncc(position, shift)
    view = np.roll(views.view(position), -shift, axis=1)
    a = view - view.mean()
    norm = float(np.linalg.norm(a)) * views.m_norm
    return float((a * views.m_centred).sum()) / norm if norm > 0 else 0.0


def refine_yaw_conf(
    query: np.ndarray, matches: np.ndarray, max_range: float, check_below: float = CHECK_BELOW
) -> tuple[np.ndarray, np.ndarray]:
    """(yaw [K] in degrees, (-180, 180], yaw confidence [K] in [0, 1]) of the query
    [R, S] relative to each match [K, R, S] (`refine_checked`)."""
    m = np.asarray(matches)
    if m.ndim == 2:
        m = m[None]
    out = [refine_checked(query, mk, max_range, check_below) for mk in m]
    yaw = np.array([o[0] for o in out], np.float32)
    return _wrapped(yaw), np.array([o[2] for o in out], np.float32)


def _wrapped(yaw: np.ndarray) -> np.ndarray:
    # Rounding to float32 can turn -179.99999 into -180, which is outside (-180, 180].
    return np.where(yaw <= -180.0, np.float32(180.0), yaw)


def query_in_match_frame(
    query: np.ndarray, match: np.ndarray, max_range: float
) -> tuple[float, np.ndarray]:
    """(yaw_deg, position [2] of the query sensor in the match's frame (m)), to the
    search's accuracy (median 0.26 m on the suite's hits, docs/research/model-history.md)."""
    yaw, position, _ = query_in_match_frame_conf(query, match, max_range)
    return yaw, position


def query_in_match_frame_conf(
    query: np.ndarray, match: np.ndarray, max_range: float, check_below: float = CHECK_BELOW
) -> tuple[float, np.ndarray, float]:
    """`query_in_match_frame` and the yaw's confidence (`refine_checked`)."""
    yaw, match_in_query, conf = refine_checked(query, match, max_range, check_below)
    c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    # The match sensor sits at p in the query frame, so the query sits at -R p in the
    # match frame, R turning query axes into match axes (the yaw).
    px, py = match_in_query
    position = -np.array([c * px - s * py, s * px + c * py])
    return float(_wrapped(np.float32(yaw))), position, conf


def refine_yaw(query: np.ndarray, matches: np.ndarray, max_range: float) -> np.ndarray:
    """`refine_yaw_conf`'s yaw [K] alone."""
    return refine_yaw_conf(query, matches, max_range)[0]
