"""An extrinsic file with a huge number is refused as not rigid, without an overflow warning
(found by the fuzz test: `1e308` in the rotation overflowed R @ R.T)."""

from __future__ import annotations

import warnings

import pytest

from disco_cli.errors import DiscoError
from disco_cli.io.poses.scans import read_extrinsic


@pytest.mark.parametrize("first", ["1e308", "-1e308", "2.0"])
def test_a_rotation_entry_beyond_one_is_refused_quietly(tmp_path, first):
    path = tmp_path / "ext.txt"
    path.write_text(f"{first} 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(DiscoError, match="not a rigid transform"):
            read_extrinsic(path)


def test_an_identity_is_read(tmp_path):
    path = tmp_path / "ext.txt"
    path.write_text("1 0 0 0.5\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    assert read_extrinsic(path)[0, 3] == 0.5
