import subprocess
import sys

from ptrack.cli import COMMANDS, STUDIES, main


def test_help_lists_every_command(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_unknown_command_is_one_line_exit_2(capsys):
    assert main(["frobnicate"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: unknown command 'frobnicate'")


def test_unknown_study(capsys):
    assert main(["study", "nope"]) == 2
    assert "choose one of" in capsys.readouterr().err


def test_every_registered_command_has_a_module_with_help():
    import importlib

    for name, (mod, _) in list(COMMANDS.items()) + list(STUDIES.items()):
        if mod is None:
            continue
        m = importlib.import_module(mod)
        assert callable(m.add_arguments) and callable(m.run), mod


def test_console_entry_point_runs():
    r = subprocess.run([sys.executable, "-m", "ptrack", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and "ptrack" in r.stdout
