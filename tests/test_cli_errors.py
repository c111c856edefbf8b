"""How every command ends when its output cannot be written or Ctrl-C stops it: one line, exit 2 or 130.

The export's own cases (an interrupted re-export, camera-only and unfinished runs) are in test_export.py;
``tools/stress_inputs.py`` runs reconstruct's in real processes.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from carvi_torch import cli, datasets, evaluate
from carvi_torch import report as report_cmd

VOC = Path(__file__).resolve().parent / "data" / "voc"


def _one_line(capsys, start: str) -> str:
    """The command's stderr: exactly one line, starting ``start``; no traceback anywhere."""
    cap = capsys.readouterr()
    lines = [line for line in cap.err.splitlines() if line.strip()]
    assert "Traceback" not in cap.err + cap.out
    assert len(lines) == 1 and lines[0].startswith(start), cap.err
    return lines[0]


@pytest.fixture
def afile(tmp_path) -> Path:
    p = tmp_path / "afile"
    p.write_text("mine")
    return p


@pytest.mark.parametrize("argv", [
    ["datasets", "procedural", "--instances", "1", "--views", "1", "--out", "{file}"],
    ["datasets", "procedural", "--instances", "1", "--views", "1", "--out", "{file}/sub"],
    ["datasets", "synthetic", "--meshes", "{tmp}", "--out", "{file}"],
    ["datasets", "voc", "--keypoints", str(VOC / "keypoints"), "--out", "{tmp}"],
    ["evaluate", "--data", "{tmp}/none.json", "--recon", "{tmp}", "--out", "{file}"],
    ["evaluate", "--data", "{tmp}/none.json", "--recon", "{tmp}", "--out", "{file}/sub"],
], ids=["procedural-file", "procedural-under-a-file", "synthetic-file", "voc-folder", "evaluate-file",
        "evaluate-under-a-file"])
def test_an_output_that_cannot_be_written_is_one_error_line(argv, tmp_path, afile, capsys, monkeypatch):
    """Checked before any work: the work functions are never called; exit 2, one ``error:`` line naming
    --out, the file in the way unchanged."""
    called = []
    monkeypatch.setattr(evaluate, "evaluate", lambda *a, **k: called.append("evaluate"))
    monkeypatch.setattr("carvi_torch.synthetic.procedural.write_default_collection",
                        lambda *a, **k: called.append("procedural"))
    monkeypatch.setattr("carvi_torch.synthetic.meshes.load_models", lambda *a, **k: called.append("synthetic"))
    monkeypatch.setattr("carvi_torch.io.voc.run", lambda *a, **k: called.append("voc"))
    argv = [a.format(file=afile, tmp=tmp_path) for a in argv]
    assert cli.main(argv) == 2
    assert "--out" in _one_line(capsys, "error:")
    assert called == [] and afile.read_text() == "mine"


@pytest.mark.parametrize("argv, option", [
    (["reconstruct", "--out", ""], "--out"), (["reconstruct", "--data", ""], "--data"),
    (["evaluate", "--data", "", "--recon", "{tmp}"], "--data"),
    (["evaluate", "--data", "a.json", "--recon", ""], "--recon"),
    (["evaluate", "--data", "a.json", "--recon", "A="], "--recon A=:"),
    (["evaluate", "--data", "a.json", "--recon", "{tmp}", "--out", ""], "--out"),
    (["export", "--recon", "", "--out", "{tmp}/x"], "--recon"), (["export", "--recon", "{tmp}", "--out", ""], "--out"),
    (["report", "--recon", ""], "--recon"), (["report", "--recon", "{tmp}", "--out", ""], "--out"),
    (["datasets", "procedural", "--out", ""], "--out"), (["datasets", "synthetic", "--meshes", "", "--out", "x"],
                                                         "--meshes"),
    (["datasets", "voc", "--keypoints", str(VOC / "keypoints"), "--out", ""], "--out"),
])
def test_an_empty_path_is_one_error_line(argv, option, tmp_path, capsys, monkeypatch):
    """An empty path (``--out ""``, a shell variable that was not set) is a user error in every command, before any
    work: it used to be taken as the current folder, or as the option's default, without a word."""
    def work(*a, **k):
        raise cli.CommandError("the work started")
    for target in ("carvi_torch.executors.run", "carvi_torch.evaluate._evaluate_and_write",
                   "carvi_torch.export.run.export", "carvi_torch.report.build_report",
                   "carvi_torch.synthetic.procedural.write_default_collection",
                   "carvi_torch.synthetic.meshes.load_models", "carvi_torch.io.voc.run"):
        monkeypatch.setattr(target, work)
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    assert cli.main([a.format(tmp=tmp_path) for a in argv]) == 2
    assert _one_line(capsys, f"error: {option} ").startswith(f"error: {option} ")
    assert list(here.iterdir()) == []


def test_an_os_error_during_the_work_is_one_error_line(tmp_path, capsys, monkeypatch):
    """An output that fails only when written (a read-only place, a full disk) is one ``error:`` line with the
    path and the system's reason, exit 2, in every command (their shared ending)."""
    def fail(*a, **k):
        raise PermissionError(13, "Permission denied", str(tmp_path / "out" / "annotations.json"))

    monkeypatch.setattr("carvi_torch.synthetic.procedural.write_default_collection", fail)
    assert datasets.main(["procedural", "--out", str(tmp_path / "out")]) == 2
    assert _one_line(capsys, "error:") == f"error: {tmp_path / 'out' / 'annotations.json'}: Permission denied"


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc (a folder no one can write)")
def test_reconstruct_into_an_impossible_folder_is_exit_2(capsys):
    """``reconstruct --out /proc/...`` (a folder that cannot be made): one ``error:`` line, exit 2."""
    from carvi_torch import reconstruct

    assert reconstruct.main(["--out", "/proc/carvi-no-such/run", "procedural_instances=2"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("error: /proc/carvi-no-such")


def test_ctrl_c_is_one_line_and_exit_130(tmp_path, capsys, monkeypatch):
    """Ctrl-C in evaluate, report and datasets: the line saying what is kept, exit 130, no traceback; evaluate
    leaves no --out folder it made."""
    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate, "evaluate", interrupt)
    out = tmp_path / "results"
    assert evaluate.main(["--data", str(tmp_path / "a.json"), "--recon", str(tmp_path), "--out", str(out)]) == 130
    assert _one_line(capsys, "interrupted;") == evaluate.INTERRUPTED
    assert not out.exists()
    monkeypatch.setattr(report_cmd, "build_report", interrupt)
    assert report_cmd.main(["--recon", str(tmp_path)]) == 130
    assert "incomplete" in _one_line(capsys, "interrupted;")
    monkeypatch.setattr("carvi_torch.synthetic.procedural.write_default_collection", interrupt)
    assert datasets.main(["procedural", "--out", str(tmp_path / "proc")]) == 130
    _one_line(capsys, "interrupted;")


def test_report_replaces_an_earlier_report_and_refuses_any_other_folder(tmp_path, capsys):
    """As the export: --out is new, empty or an earlier report (written again); a folder holding anything
    else is refused (exit 2, one line, nothing written)."""
    recon = tmp_path / "run"
    recon.mkdir()
    (recon / "summary.json").write_text(json.dumps({"classes": {}}))
    out = tmp_path / "rep"
    assert report_cmd.main(["--recon", str(recon), "--out", str(out), "--quiet", "--workers", "0"]) == 0
    assert (out / "index.html").is_file()
    assert report_cmd.main(["--recon", str(recon), "--out", str(out), "--quiet", "--workers", "0"]) == 0
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    capsys.readouterr()
    assert report_cmd.main(["--recon", str(recon), "--out", str(mine), "--quiet", "--workers", "0"]) == 2
    assert "not an earlier report" in _one_line(capsys, "error:")
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


def test_deferred_interrupt_leaves_an_ignored_sigint_ignored():
    """Where SIGINT is ignored (a job started with ``&``), holding Ctrl-C back must not turn one into a
    ``KeyboardInterrupt``; where it is handled, the interrupt comes after the block."""
    import signal

    from carvi_torch.runtime import deferred_interrupt

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        try:
            with deferred_interrupt():
                signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            pytest.fail("an ignored SIGINT became a KeyboardInterrupt")
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
    with pytest.raises(KeyboardInterrupt):
        with deferred_interrupt():
            signal.raise_signal(signal.SIGINT)


def test_report_and_export_refuse_a_file_or_a_foreign_folder_in_the_same_words(tmp_path, afile, capsys):
    """One rule for both: --out may be new, empty or the command's earlier output; a file or a folder holding
    anything else is refused before anything is written, naming what it holds."""
    from carvi_torch.export.store import StoreWriter

    recon = tmp_path / "run"
    recon.mkdir()
    (recon / "summary.json").write_text(json.dumps({"classes": {}}))
    mine = tmp_path / "mine"
    mine.mkdir()
    for name in ("notes.txt", "b.txt"):
        (mine / name).write_text("keep")
    said = {}
    for out in (afile, mine):
        assert report_cmd.main(["--recon", str(recon), "--out", str(out), "--quiet", "--workers", "0"]) == 2
        said["report", out] = _one_line(capsys, "error:").removeprefix("error: ")
        with pytest.raises(ValueError) as e:
            StoreWriter(out)
        said["export", out] = str(e.value)
    assert said["report", afile] == said["export", afile] == f"--out {afile} is a file, not a folder"
    for command in ("report", "export"):
        assert said[command, mine] == (f"--out {mine}: not empty and not an earlier {command} (it holds 'b.txt' "
                                       "and 1 more); choose another --out (nothing was written)")
    assert afile.read_text() == "mine" and sorted(p.name for p in mine.iterdir()) == ["b.txt", "notes.txt"]


@pytest.mark.parametrize("failed", ["out", "parent"])
def test_an_output_folder_that_cannot_be_made_names_the_path_that_failed_once(failed, tmp_path, capsys,
                                                                              monkeypatch):
    """The report's and the export's --out that cannot be made: the system's reason, with the path that failed
    where it is not --out itself (a parent folder), never --out twice."""
    from carvi_torch.export.store import StoreWriter

    recon = tmp_path / "run"
    recon.mkdir()
    (recon / "summary.json").write_text(json.dumps({"classes": {}}))
    make = Path.mkdir

    def mkdir(self, *a, **k):
        if self.name in ("rep", "store"):
            raise PermissionError(13, "Permission denied", str(self if failed == "out" else self.parent))
        return make(self, *a, **k)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    said = "" if failed == "out" else f"{tmp_path / 'ro'}: "
    out = tmp_path / "ro" / "rep"
    assert report_cmd.main(["--recon", str(recon), "--out", str(out), "--quiet", "--workers", "0"]) == 2
    assert _one_line(capsys, "error:") == f"error: cannot make --out {out}: {said}Permission denied"
    out = tmp_path / "ro" / "store"
    with pytest.raises(ValueError) as e:
        StoreWriter(out)
    assert str(e.value) == f"{out}: cannot write the store there ({said}Permission denied; nothing was written)"


@pytest.mark.parametrize("wrapper", ["watch_interrupts", "deferred_interrupt"])
def test_sigint_wrappers_leave_an_ignored_sigint_and_other_threads_alone(wrapper):
    """Both SIGINT wrappers follow one rule: an ignored SIGINT stays ignored, and outside the main thread
    (where Python cannot install a handler) the block runs as it is."""
    import signal
    import threading

    from carvi_torch import runtime

    block = getattr(runtime, wrapper)
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with block():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            signal.raise_signal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, previous)
    errors = []

    def in_a_thread():
        try:
            with block():
                pass
        except Exception as e:  # noqa: BLE001 - a handler installed off the main thread raises ValueError
            errors.append(e)

    thread = threading.Thread(target=in_a_thread)
    thread.start()
    thread.join()
    assert errors == [] and signal.getsignal(signal.SIGINT) is previous


def test_a_failed_output_check_leaves_no_folder_it_made(tmp_path, monkeypatch):
    """When the write probe fails after the output folder was made, the folders the check made are removed
    (those that were there before are kept)."""
    kept = tmp_path / "kept"
    kept.mkdir()

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(cli.tempfile, "TemporaryFile", refuse)
    with pytest.raises(cli.CommandError, match="cannot write there"):
        cli.writable_folder(kept / "a" / "b")
    assert kept.is_dir() and list(kept.iterdir()) == []


@pytest.mark.parametrize("text, said", [
    ("123: 4\n", "config key '123' at line 1 is not a setting name"),
    ("on: true\n", "config key 'on' at line 1 is not a setting name"),
    ("carv: {resolution: 16}\n", "unknown config key 'carv'; did you mean 'carve'?"),
    ("resolution: 16\nresolution: 20\n", "config key 'resolution' is given twice (lines 1 and 2)"),
    ("out: [a, b]\n", "out: expected text, got a list"),
], ids=["number", "boolean", "misspelt-section", "twice", "list-for-text"])
def test_a_bad_config_file_is_one_error_line(text, said, tmp_path, capsys):
    """A key that is not text (``on:`` is True to YAML 1.1) was an AttributeError traceback, exit 1."""
    p = tmp_path / "c.yaml"
    p.write_text(text)
    assert cli.main(["reconstruct", "--config", str(p), "--out", str(tmp_path / "run")]) == 2
    assert said in _one_line(capsys, "error:")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("text", ["123: 4\n", "on: true\n"])
def test_export_of_a_run_whose_config_has_a_key_that_is_not_text_is_one_error_line(text, tmp_path, capsys):
    recon = tmp_path / "run"
    recon.mkdir()
    (recon / "config.yaml").write_text(text)
    status = cli.main(["export", "--recon", str(recon), "--out", str(tmp_path / "x"), "--workers", "0", "--quiet"])
    assert status == 2
    assert f"{recon / 'config.yaml'}: config key '{text.split(':')[0]}'" in _one_line(capsys, "error:")
