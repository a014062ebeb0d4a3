"""Output paths fail before the work, never after it, and writes leave nothing behind.

Each command below is given inputs that would run, and an output it cannot write. The
truth that the work did not start: the function doing it (patched to record its call)
was never called, nothing went to stdout, and the folder holds only what was there.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.errors import DiscoError
from disco_cli.io.output_paths import (
    atomic_path,
    check_output_file,
    check_output_folder,
    write_text_atomic,
)

runner = CliRunner()
NOWHERE = Path("/nonexistent-disco-test")  # a folder that must not exist (and is not made)


@pytest.fixture(autouse=True)
def _nowhere_is_absent():
    assert not NOWHERE.exists()
    yield
    assert not NOWHERE.exists(), f"{NOWHERE} was created"


def _one_line_error(res, *words: str) -> str:
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


class Never:
    """Stands in for the work: records a call, so a test can assert there was none."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        raise AssertionError("the work ran before the output was checked")


@pytest.fixture
def no_embedding(monkeypatch: pytest.MonkeyPatch) -> Never:
    """Every scan-embedding path of the commands (build-db, query, loops, eval)."""
    from disco_cli.embedding import batches

    never = Never()
    monkeypatch.setattr(batches, "embedded", never)
    monkeypatch.setattr(batches, "embed_paths", never)
    return never


# -- eval --report ----------------------------------------------------------------


@pytest.mark.parametrize("command", ["eval", "eval-loops"])
def test_eval_report_into_proc_fails_before_the_work(
    command: str, samples: Path, samples_spectral_db: Path, no_embedding: Never, monkeypatch
) -> None:
    import disco_cli.evaluation.runs as runs

    monkeypatch.setattr(runs, "multi_session", no_embedding)
    monkeypatch.setattr(runs, "loop_closure", no_embedding)
    args = [command, str(samples / "01"), "--report", "/proc/rep"]
    if command == "eval":
        args += ["-d", str(samples_spectral_db)]
    else:
        args += ["-m", "spectral", "--exclude-frames", "5"]
    _one_line_error(runner.invoke(app, args), "/proc/rep", "cannot write")
    assert no_embedding.calls == 0


def test_eval_report_onto_an_existing_file_fails_before_the_work(
    samples: Path, samples_spectral_db: Path, no_embedding: Never, tmp_path: Path
) -> None:
    report = tmp_path / "rep"
    report.write_text("mine\n")
    args = ["eval", str(samples / "01"), "-d", str(samples_spectral_db), "--report", str(report)]
    _one_line_error(runner.invoke(app, args), str(report), "not a folder")
    assert no_embedding.calls == 0
    assert report.read_text() == "mine\n"


def test_eval_report_in_a_missing_folder_fails_before_the_work(
    samples: Path, samples_spectral_db: Path, no_embedding: Never
) -> None:
    report = NOWHERE / "rep"
    args = ["eval", str(samples / "01"), "-d", str(samples_spectral_db), "--report", str(report)]
    _one_line_error(runner.invoke(app, args), str(NOWHERE), "does not exist")
    assert no_embedding.calls == 0


# -- train -o ------------------------------------------------------------------------


@pytest.fixture
def no_training(monkeypatch: pytest.MonkeyPatch) -> Never:
    import disco_cli.training.data as data

    never = Never()
    monkeypatch.setattr(data, "load_training_data", never)
    return never


def test_train_into_proc_fails_before_training(samples: Path, no_training: Never) -> None:
    res = runner.invoke(app, ["train", str(samples / "00"), "-o", "/proc/x.pt"])
    _one_line_error(res, "/proc/x.pt", "cannot write the checkpoint")
    assert no_training.calls == 0


@pytest.mark.parametrize("resume", [False, True])
def test_train_onto_a_folder_says_so_with_or_without_resume(
    resume: bool, samples: Path, tmp_path: Path, no_training: Never
) -> None:
    out = tmp_path / "ckpt"
    out.mkdir()
    args = ["train", str(samples / "00"), "-o", str(out)] + (["--resume"] if resume else [])
    line = _one_line_error(runner.invoke(app, args), str(out), "is a folder")
    assert "--resume" not in line  # the old advice, which then failed after training
    assert no_training.calls == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt"]  # no ckpt.tmp


def test_train_onto_an_existing_checkpoint_without_resume_advises_resume(
    samples: Path, tmp_path: Path, no_training: Never
) -> None:
    out = tmp_path / "m.pt"
    out.write_bytes(b"x")
    res = runner.invoke(app, ["train", str(samples / "00"), "-o", str(out)])
    _one_line_error(res, str(out), "--resume")
    assert no_training.calls == 0


def test_train_resume_accepts_what_the_advice_names(
    samples: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With --resume a checkpoint of the same network passes the check and training is
    reached."""
    import disco_cli.training.data as data
    from disco_cli.model.bev import BEVConfig
    from disco_cli.model.checkpoint import save_checkpoint
    from disco_cli.model.disco import default_model_config

    out = tmp_path / "m.pt"
    config = {**default_model_config(BEVConfig().heights, 8), "residual": True}
    save_checkpoint(out, {"model_config": config, "state_dict": {}})
    reached = []

    def load_training_data(*args, **kwargs):
        reached.append(True)
        raise DiscoError("stop: the check passed")

    monkeypatch.setattr(data, "load_training_data", load_training_data)
    res = runner.invoke(app, ["train", str(samples / "00"), "-o", str(out), "--resume"])
    _one_line_error(res, "stop: the check passed")
    assert reached == [True]


def test_train_resume_of_a_file_that_cannot_be_resumed_fails_before_training(
    samples: Path, tmp_path: Path, no_training: Never
) -> None:
    from disco_cli.model.bev import BEVConfig
    from disco_cli.model.checkpoint import save_checkpoint
    from disco_cli.model.disco import default_model_config

    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    res = runner.invoke(app, ["train", str(samples / "00"), "-o", str(junk), "--resume"])
    _one_line_error(res, str(junk), "not a disco checkpoint")
    other = tmp_path / "w16.pt"  # a width-16 network, resumed as the default width 8
    config = default_model_config(BEVConfig().heights, 16)
    save_checkpoint(other, {"model_config": {**config, "residual": True}, "state_dict": {}})
    res = runner.invoke(app, ["train", str(samples / "00"), "-o", str(other), "--resume"])
    _one_line_error(res, str(other), "another model configuration")
    assert no_training.calls == 0


# -- loops -o, bev -o, build-db -o ---------------------------------------------------------


@pytest.fixture
def no_loops(monkeypatch: pytest.MonkeyPatch) -> Never:
    from disco_cli.query.loop_detector import LoopDetector

    never = Never()
    monkeypatch.setattr(LoopDetector, "add_files", never)
    return never


def test_loops_onto_a_folder_fails_before_computing(
    samples: Path, tmp_path: Path, no_loops: Never
) -> None:
    out = tmp_path / "d.g2o"
    out.mkdir()
    res = runner.invoke(app, ["loops", str(samples / "00"), "-m", "spectral", "-o", str(out)])
    _one_line_error(res, str(out), "is a folder")
    assert no_loops.calls == 0
    assert res.stdout == ""  # no loop printed


def test_loops_into_a_missing_folder_fails_before_computing(samples: Path, no_loops: Never) -> None:
    out = NOWHERE / "l.g2o"
    res = runner.invoke(app, ["loops", str(samples / "00"), "-m", "spectral", "-o", str(out)])
    _one_line_error(res, str(NOWHERE), "does not exist")
    assert no_loops.calls == 0


def test_bev_into_a_missing_folder_fails_before_reading(
    samples: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import disco_cli.io.readers as readers

    never = Never()
    monkeypatch.setattr(readers, "read_scan", never)
    scan = sorted((samples / "00" / "velodyne").iterdir())[0]
    res = runner.invoke(app, ["bev", str(scan), "-o", str(NOWHERE / "x.png")])
    _one_line_error(res, str(NOWHERE), "does not exist")
    assert never.calls == 0


def test_build_db_into_a_missing_folder_fails_before_embedding(
    samples: Path, no_embedding: Never
) -> None:
    out = NOWHERE / "map.db"
    res = runner.invoke(app, ["build-db", str(samples / "00"), "-o", str(out), "-m", "spectral"])
    _one_line_error(res, str(NOWHERE), "does not exist")
    assert no_embedding.calls == 0


def test_build_db_onto_a_folder_fails_before_embedding(
    samples: Path, tmp_path: Path, no_embedding: Never
) -> None:
    res = runner.invoke(
        app, ["build-db", str(samples / "00"), "-o", str(tmp_path), "-m", "spectral"]
    )
    _one_line_error(res, str(tmp_path), "is a folder")
    assert no_embedding.calls == 0


# -- atomic writes -------------------------------------------------------------------


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old\n")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half of the new")
            raise RuntimeError("disk full, say")
    assert target.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    write_text_atomic(target, "new\n")
    assert target.read_text() == "new\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_a_failed_loop_export_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    import disco_cli.io.loop_export as export

    def half(path: Path, *args) -> None:
        path.write_text("EDGE_SE3:QUAT 0 1")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export, "_write_lines", half)
    with pytest.raises(DiscoError, match="No space left"):
        export.write_loops(tmp_path / "l.g2o", [])
    assert list(tmp_path.iterdir()) == []


def test_a_failed_checkpoint_save_leaves_the_old_one_and_no_temporary(
    tmp_path: Path, monkeypatch
) -> None:
    import torch

    from disco_cli.model import checkpoint

    target = tmp_path / "m.pt"
    checkpoint.save_checkpoint(target, {"epoch": 1})
    before = target.read_bytes()

    def broken_save(obj, f):
        Path(f).write_bytes(b"partial")
        raise RuntimeError("killed mid-write")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(RuntimeError):
        checkpoint.save_checkpoint(target, {"epoch": 2})
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pt"]


def test_written_files_get_the_usual_mode(tmp_path: Path) -> None:
    import os

    mask = os.umask(0)
    os.umask(mask)
    target = tmp_path / "r.json"
    write_text_atomic(target, "{}\n")
    assert target.stat().st_mode & 0o777 == 0o666 & ~mask


def test_checks(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    assert check_output_file(tmp_path / "new.txt") == tmp_path / "new.txt"
    assert check_output_file(tmp_path / "f") == tmp_path / "f"
    with pytest.raises(DiscoError, match="exists; do this"):
        check_output_file(tmp_path / "f", exists_ok=False, hint="do this")
    with pytest.raises(DiscoError, match="is a folder"):
        check_output_file(tmp_path)
    with pytest.raises(DiscoError, match="is not a folder"):
        check_output_file(tmp_path / "f" / "x")
    assert check_output_folder(tmp_path) == tmp_path
    assert check_output_folder(tmp_path / "new") == tmp_path / "new"
    assert not (tmp_path / "new").exists()  # checked, not made
    with pytest.raises(DiscoError, match="not a folder"):
        check_output_folder(tmp_path / "f")
