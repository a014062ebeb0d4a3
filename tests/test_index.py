"""The signature index behind a map: exact, or approximate (faiss) kept beside the map.

Truths: a float64 NumPy brute force (`search.brute_force_topk`); a scan that is in the
map finds itself first at distance 0; the exact index's answers on the same map.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.errors import DiscoError
from disco_cli.maps.index import INSTALL_HINT, choose_kind, sidecar_path
from disco_cli.query.search import brute_force_topk


def clustered(n: int, dim: int, seed: int) -> np.ndarray:
    """Rows around 30 centres (a map's places come in streets, not uniformly)."""
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((30, dim))
    x = centres[rng.integers(0, 30, n)] + 0.4 * rng.standard_normal((n, dim))
    return x.astype(np.float32)


def run(*args: str) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, list(args))
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def query(db, scan, index: str) -> list[dict]:
    code, out, err = run(
        "query", str(scan), "--db", str(db), "--topk", "5", "--format", "jsonl", "--index", index
    )
    assert code == 0, err
    return [json.loads(line) for line in out.splitlines() if line.strip()]


# -- choosing -------------------------------------------------------------------------


def test_auto_is_exact_for_small_maps_and_falls_back_without_faiss(monkeypatch):
    notes: list[str] = []
    assert choose_kind("auto", 1000, notes.append) == "exact"
    assert notes == []
    monkeypatch.setitem(sys.modules, "faiss", None)  # import faiss fails
    assert choose_kind("auto", 5_000_000, notes.append) == "exact"
    assert len(notes) == 1 and "disco-cli[ann]" in notes[0]
    with pytest.raises(DiscoError, match=r"pip install 'disco-cli\[ann\]'"):
        choose_kind("ann", 10, notes.append)
    with pytest.raises(DiscoError, match="--index"):
        choose_kind("fast", 10)


def test_query_index_ann_without_faiss_is_one_line(samples_spectral_db, samples, monkeypatch):
    monkeypatch.setitem(sys.modules, "faiss", None)
    scan = samples / "01" / "velodyne" / "000003.bin"
    code, out, err = run("query", str(scan), "--db", str(samples_spectral_db), "--index", "ann")
    assert code == 1 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and INSTALL_HINT in lines[0]


# -- the approximate index itself -----------------------------------------------------------


def test_full_recall_gives_the_exact_top_k():
    pytest.importorskip("faiss")
    from disco_cli.maps.index.ann import AnnIndex, AnnParams

    x = clustered(3000, 64, seed=1)
    rng = np.random.default_rng(2)
    q = x[rng.choice(len(x), 40, replace=False)] + 0.2 * rng.standard_normal((40, 64))
    exclude = rng.random(len(x)) < 0.1
    # Every cluster scanned, every row re-measured in float32: nothing approximate left.
    for pca in (0, 32):
        full = AnnParams(nlist=16, nprobe=16, pca=pca, k_factor=len(x), refine="Flat")
        index = AnnIndex.build(x, full)
        rows, dists = index.search(q, 10)
        rows_ex, _ = index.search(q, 10, exclude=exclude)
        allowed = np.flatnonzero(~exclude)
        for i in range(len(q)):
            want, want_d = brute_force_topk(x, q[i], 10)
            np.testing.assert_array_equal(rows[i], want)
            np.testing.assert_allclose(dists[i], want_d, rtol=1e-5)
            sub, _ = brute_force_topk(x[allowed], q[i], 10)
            np.testing.assert_array_equal(rows_ex[i], allowed[sub])


def test_default_codes_find_the_near_rows_and_scanning_less_finds_fewer():
    pytest.importorskip("faiss")
    from disco_cli.maps.index.ann import AnnIndex, default_params

    x = clustered(20000, 128, seed=3)
    rng = np.random.default_rng(4)
    q = x[rng.choice(len(x), 50, replace=False)] + 0.05 * rng.standard_normal((50, 128))
    truth = np.array([brute_force_topk(x, v, 10)[0] for v in q])
    index = AnnIndex.build(x, default_params(len(x), 128))

    def recall10(nprobe: int) -> float:
        index.set_search(nprobe, 10)
        rows, _ = index.search(q, 10)
        return np.mean([len(set(a) & set(b)) / 10 for a, b in zip(rows, truth)])

    full, one = recall10(index.params.nlist), recall10(1)
    # 8-bit codes swap only rows closer than their rounding; one cluster of many misses.
    assert full >= 0.95
    assert one < full


# -- beside a map -----------------------------------------------------------------------


def test_sidecar_is_refreshed_after_append_and_rebuilt_when_damaged(samples, tmp_path):
    pytest.importorskip("faiss")
    scans = sorted((samples / "00" / "velodyne").glob("*.bin"))
    first, later = tmp_path / "first", tmp_path / "later"
    first.mkdir()
    later.mkdir()
    for p in scans[:13]:
        (first / p.name).symlink_to(p)
    for p in scans[13:]:
        (later / p.name).symlink_to(p)
    db = tmp_path / "map.db"
    assert run("build-db", str(first), "-o", str(db), "-m", "spectral")[0] == 0
    own = later / scans[20].name  # in the map only after the append
    before = query(db, own, "ann")
    side = sidecar_path(db)
    assert side.is_file()
    assert before[0]["match"] != str(own)

    code, _, err = run("build-db", str(later), "-o", str(db), "-m", "spectral", "--append")
    assert code == 0, err
    code, out, err = run("query", str(own), "--db", str(db), "--format", "jsonl", "--index", "ann")
    assert code == 0 and "changed" in err  # the stale sidecar was noticed and rebuilt
    after = [json.loads(line) for line in out.splitlines() if line.strip()]
    # Itself, appended; at distance 0 up to the 8-bit codes' rounding (the exact: 0 up
    # to the map's 9-bit rounding of stored features, database.py).
    assert after[0]["match_id"] == 21 and after[0]["distance"] < 0.01
    exact = query(db, own, "exact")
    assert exact[0]["match_id"] == 21 and exact[0]["distance"] < 1e-3
    assert [m["match_id"] for m in query(db, own, "ann")] == [m["match_id"] for m in exact]

    # A damaged sidecar is rebuilt, with one line about it and no traceback.
    blob = bytearray(side.read_bytes())
    blob[len(blob) // 3] ^= 0xFF
    side.write_bytes(bytes(blob))
    code, out, err = run("query", str(own), "--db", str(db), "--format", "jsonl", "--index", "ann")
    assert code == 0 and "damaged" in err and "Traceback" not in err
    assert [json.loads(line)["match_id"] for line in out.splitlines()][0] == 21
    side.write_bytes(b"not an index")
    code, _, err = run("query", str(own), "--db", str(db), "--index", "ann")
    assert code == 0 and "rebuilding" in err
    assert "Traceback" not in err


def test_a_sidecar_faiss_cannot_read_is_refused_not_raised(tmp_path):
    pytest.importorskip("faiss")
    import hashlib
    import struct

    from disco_cli.maps.index.ann import AnnIndex, SidecarError

    # Well-formed around a body that is no faiss index (another faiss's, say): the
    # checksum holds, faiss refuses it, and so does the loader, with a reason.
    key = {"rows": 3}
    body = b"IxNotAnIndex" * 10 + np.arange(3, dtype="<i8").tobytes()
    header = {
        "format": 1,
        "key": key,
        "params": {"nlist": 1, "nprobe": 1, "pca": 0, "k_factor": 1, "refine": "SQ8"},
        "rows": 3,
        "dim": 4,
        "index_bytes": 120,
        "ids": 3,
        "owner": 0,
        "sha256": hashlib.sha256(body).hexdigest(),
    }
    blob = json.dumps(header).encode()
    side = tmp_path / "map.db.ann"
    side.write_bytes(body + blob + struct.pack("<Q8s", len(blob), b"DISCOANN"))
    with pytest.raises(SidecarError, match="faiss cannot read it"):
        AnnIndex.load(side, key)
