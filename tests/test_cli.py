"""cli.py: one ``carvi`` command; each front end names itself as it was invoked; one version."""
from __future__ import annotations

import importlib
import os
import subprocess
import sys
import time
from importlib.metadata import version
from typing import Optional

import pytest

import carvi_torch
from carvi_torch.cli import COMMANDS, main


def _help(fn, argv, capsys) -> str:
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        fn(argv)
    assert e.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_usage_names_the_command_as_invoked(command, capsys):
    module = importlib.import_module(COMMANDS[command][0])
    assert _help(main, [command, "--help"], capsys).startswith(f"usage: carvi {command} ")
    assert _help(module.main, ["--help"], capsys).startswith(f"usage: python -m {COMMANDS[command][0]} ")


def test_subcommand_of_a_subcommand_and_errors_name_it_too(capsys):
    assert _help(main, ["datasets", "voc", "--help"], capsys).startswith("usage: carvi datasets voc ")
    with pytest.raises(SystemExit):
        main(["report"])  # --recon is required
    assert "carvi report: error:" in capsys.readouterr().err


def test_one_version(capsys):
    assert carvi_torch.__version__ == version("carvi_torch") != "unknown"
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"carvi_torch {carvi_torch.__version__}"


def test_reconstruct_help_lists_every_file_of_a_run():
    from carvi_torch.io.layout import RUN_NAMES
    from carvi_torch.reconstruct import EPILOG_HEAD

    listed = EPILOG_HEAD.split("key=value settings")[0]
    assert [n for n in RUN_NAMES if n not in listed] == []


def test_closing_table_cuts_reasons_at_a_word_and_marks_the_cut():
    """A long warning or skip reason in reconstruct's closing table ends at a whole word with ``…``: a number is
    never cut in two (``from 15 to 2`` of ``from 15 to 24`` would read as another number)."""
    from carvi_torch.reconstruct import format_table

    warning = "the views kept by the refinement of the camera: from 15 to 24 after pruning"  # [:60]: "...to 2"
    reason = "no usable camera: its SfM residual grew from 13.25 to 17.5 pixels"  # [:48]: "... from 13."
    summary = {"classes": {"car": {"objects": 1, "reconstructed": 1, "warnings": [warning]},
                           "bus": {"objects": 1, "failures": [{"reason": reason}]}}}
    rows = {line.split()[0]: line for line in format_table(summary).splitlines()[2:]}
    car = rows["car"].split("warning: ", 1)[1].rstrip()
    bus = rows["bus"].rstrip().split("  ")[-1]
    assert car == "the views kept by the refinement of the camera: from 15 to…"
    assert bus == "no usable camera: its SfM residual grew from… (x1)"


@pytest.mark.parametrize("threads, said", [(1, "(1 thread)"), (2, "(2 threads)")])
def test_closing_table_counts_threads_in_words(threads, said):
    from carvi_torch.reconstruct import format_table

    summary = {"classes": {}, "total_seconds": 1.0, "device": "cpu", "torch_threads": threads}
    assert f"total 1.0 s on cpu {said}" in format_table(summary)



def test_reconstruct_takes_settings_on_both_sides_of_an_option(monkeypatch, capsys):
    """``--out D a=1 --quiet b=2`` (README's ``--quiet preview=false`` after a setting) hands every setting to
    the configuration, not a usage error."""
    from carvi_torch import reconstruct
    from carvi_torch.config import ConfigError

    seen = []

    def load_config(path, overrides):
        seen.extend(overrides)
        raise ConfigError("stop here")

    monkeypatch.setattr(reconstruct, "load_config", load_config)
    try:
        status = reconstruct.main(["--out", "D", "procedural_instances=3", "--quiet", "preview=false", "report=false"])
    except SystemExit as e:  # argparse's usage error
        status = e.code
    assert seen == ["procedural_instances=3", "preview=false", "report=false"]
    assert status == 2 and "error: stop here" in capsys.readouterr().err


def test_readme_commands_name_every_option(capsys):
    """README's *Commands* block gives each command (and each ``datasets`` subcommand) exactly the options its
    ``--help`` usage lists, ``--help`` and ``--version`` aside."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = text[text.index("## Commands"):].split("```")[1]
    entries: dict[tuple, set] = {}
    key = None
    for line in block.strip().splitlines():
        if line.startswith("carvi "):
            words = line.split()
            key = (words[1], words[2]) if words[1] == "datasets" else (words[1],)
        entries.setdefault(key, set()).update(re.findall(r"--[a-z][a-z-]*", line))
    assert {k[0] for k in entries} == set(COMMANDS)
    for key, listed in entries.items():
        usage = _help(main, [*key, "--help"], capsys).split("\n\n")[0]
        assert listed == set(re.findall(r"--[a-z][a-z-]*", usage)) - {"--help", "--version"}, key


@pytest.mark.parametrize("executor", ["local", "ray"])
@pytest.mark.parametrize("data", [False, True], ids=["embedded", "data"])
def test_reconstruct_refuses_a_class_the_data_lacks(executor, data, tmp_path, monkeypatch, capsys):
    """``--classes`` with a name that is no class of the data (a typo, another case), on either executor: exit 2
    before any work, one ``error:`` line naming the unknown names and the data's classes, as evaluate's and the
    export's; nothing written (the embedded collection is not even generated)."""
    import contextlib
    import json

    from carvi_torch import reconstruct
    from carvi_torch.executors import ray as ray_executor

    generated = []
    monkeypatch.setattr("carvi_torch.synthetic.procedural.write_default_collection",
                        lambda *a, **k: generated.append(a))
    monkeypatch.setattr(ray_executor, "import_ray", lambda: None)  # no cluster: the check comes before the work
    monkeypatch.setattr(ray_executor, "connect", lambda address: contextlib.nullcontext("local"))
    argv = ["--out", str(tmp_path / "run"), "--classes", "car,Chair,nosuch", "--quiet", f"executor={executor}"]
    known = "aeroplane, bottle, car, chair"
    if data:
        cats = [{"id": i, "name": n, "keypoints": ["a", "b", "c"]} for i, n in enumerate(["car", "chair"], 1)]
        (tmp_path / "ann.json").write_text(json.dumps({"images": [], "annotations": [], "categories": cats}))
        argv, known = argv + ["--data", str(tmp_path / "ann.json")], "car, chair"
    capsys.readouterr()
    assert reconstruct.main(argv) == 2
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert "Traceback" not in cap.err + cap.out and len(lines) == 1, cap.err
    assert lines[0].startswith("error: --classes: 'Chair', 'nosuch' are not classes of "), lines[0]
    assert f"(its classes: {known};" in lines[0]
    assert generated == [] and sorted(p.name for p in tmp_path.iterdir()) == (["ann.json"] if data else [])


def _start_then_ctrl_c(argv0: str) -> subprocess.CompletedProcess:
    """A Python whose ``argv[0]`` is ``argv0`` while it imports the package, then Ctrl-C (SIGINT) to itself."""
    import signal

    code = (f"import sys; sys.argv[0] = {argv0!r}; import carvi_torch, os, signal, time; "
            "os.kill(os.getpid(), signal.SIGINT); time.sleep(10)")
    # Ctrl-C as a terminal gives it, also where this test runs with SIGINT ignored (a background job)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def test_ctrl_c_while_a_command_starts_is_one_line_and_130():
    """``python -m carvi_torch.X`` imports the package while ``argv[0]`` is ``-m`` (the ``carvi`` script: its
    name): a Ctrl-C in the seconds of imports before the command's own handling is one line, exit 130."""
    for argv0 in ("-m", "/usr/local/bin/carvi"):
        done = _start_then_ctrl_c(argv0)
        assert done.returncode == 130, (argv0, done.stderr)
        assert done.stderr == "interrupted while starting; nothing was written\n", argv0


def test_importing_the_package_elsewhere_leaves_ctrl_c_alone():
    done = _start_then_ctrl_c("-c")
    assert done.returncode != 130 and "KeyboardInterrupt" in done.stderr


def test_a_command_takes_ctrl_c_over_from_the_start(capsys):
    """Once a command's body runs, Ctrl-C is its own: ``run_command`` gives Python's handler back, so the
    body's ``KeyboardInterrupt`` ends in the command's line (what is kept), not the start's."""
    import signal

    import carvi_torch
    from carvi_torch.cli import run_command

    def body():
        if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
            return 7  # a real Ctrl-C now would end this test process
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)

    before = signal.signal(signal.SIGINT, carvi_torch.interrupted_while_starting)
    try:
        assert run_command(body, "interrupted; the run's objects are kept") == 130
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
    assert capsys.readouterr().err == "interrupted; the run's objects are kept\n"


def test_reconstruct_help_shows_defaults_as_they_are_typed(capsys):
    """``--help`` showed ``data=None``, ``classes=None``, ``imprint=True`` (Python's spellings, some of which a
    ``key=value`` reads as text): every default it shows, typed back, gives the default."""
    import re

    from carvi_torch.config import Config, _get, all_keys
    from carvi_torch.reconstruct import settings_help

    text = settings_help()
    shown = dict(re.findall(r"^  (\S+?)=(.*)$", text, flags=re.M))
    assert sorted(shown) == sorted(all_keys())
    assert "None" not in shown.values() and "True" not in shown.values() and "'" not in "".join(shown.values())
    assert shown["data"] == shown["classes"] == shown["gt"] == "null" and shown["carve.imprint"] == "true"
    typed_back = Config().override([f"{k}={v}" for k, v in shown.items()])
    assert {k: _get(typed_back, k) for k in shown} == Config().flat()


@pytest.mark.parametrize("value", [None, True, False, 0, 7, 1e-07, 0.1, "outputs/default", "007", "null", "",
                                   " x", "'q'", ["car", "chair"], ["a,b", "007"], [], ["[x"]])
def test_override_text_types_back(value):
    from carvi_torch.config import _coerce, _typed, override_text

    annotation = Optional[type(value) if value is not None else str]
    assert _coerce("k", _typed("k", override_text(value), annotation), annotation) == value
