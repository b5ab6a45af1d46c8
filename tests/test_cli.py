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


# --- CLI-wide parsing and range checks (ptrack.options) ---------------------------------------------

import math

import pytest

from ptrack.cli import command_parser
from ptrack.errors import UserError
from ptrack.options import OPTIONS, Range, normalise_negative_numbers, range_for


def _available_commands():
    import importlib

    names = []
    for n, (mod, _) in COMMANDS.items():
        if mod is None:
            continue
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError:  # registered, module not in this checkout yet (test above reports it)
            continue
        names.append(n)
    return names + [f"study {s}" for s in STUDIES]


def _long(action):
    return max([s for s in action.option_strings if s.startswith("--")] or [action.dest], key=len)


def test_every_numeric_option_of_every_command_has_a_range():
    missing = []
    for name in _available_commands():
        key, parser = command_parser(name)
        assert parser.numeric_actions or name in ("simulate", "warmup"), name
        for a in parser.numeric_actions:
            if range_for(key, _long(a)) is None:
                missing.append(f"{name} {_long(a)}")
    assert not missing, f"numeric options without a range in ptrack.options: {missing}"


def test_every_default_is_inside_its_range():
    from ptrack.options import check_namespace

    for name in _available_commands():
        key, parser = command_parser(name)
        for a in parser.numeric_actions:
            if a.default is None or a.required:
                continue
            ns = argparse_namespace(**{a.dest: a.default})
            check_namespace(key, ns, [a])  # raises on a default outside the table's range


def argparse_namespace(**kw):
    import argparse

    return argparse.Namespace(**kw)


def test_negative_scientific_notation_after_a_space_parses_for_every_float_option():
    n_checked = 0
    for name in _available_commands():
        key, parser = command_parser(name)
        for a in parser.numeric_actions:
            if a.type is not float or a.choices:
                continue
            nargs = a.nargs if isinstance(a.nargs, int) else 1
            vals = ["-3e-6", "-2.5E-7"][:nargs] if nargs <= 2 else ["-3e-6"] * nargs
            argv = [_long(a), *vals]
            # positionals and required options: fill with harmless values
            for b in parser.all_actions:
                if b is a:
                    continue
                if not b.option_strings and b.nargs not in ("?", "*"):
                    argv = ["X"] + argv
                elif b.option_strings and b.required:
                    argv += [_long(b), "1" if b.type in (float, int) else "X"]
            try:
                ns = parser.parse_args(normalise_negative_numbers(argv, parser.option_strings()))
            except UserError as exc:  # a required mutually exclusive group the option is not in
                if "one of the arguments" not in str(exc):
                    raise
                other = str(exc).split("one of the arguments ")[1].split()[0]
                ns = parser.parse_args(normalise_negative_numbers(argv + [other, "1"], parser.option_strings()))
            got = getattr(ns, a.dest)
            want = [float(v) for v in vals]
            assert (list(got) if isinstance(got, (list, tuple)) else [got]) == want, (name, a.dest, got)
            n_checked += 1
    assert n_checked > 30


def test_normalise_keeps_values_exact_and_leaves_other_tokens():
    out = normalise_negative_numbers(["--a", "-3e-6", "-x", "--b", "-1.5E+3", "--", "-1e-3"], {"--a", "--b", "-x"})
    assert out == ["--a", "-0.000003", "-x", "--b", "-1500", "--", "-1e-3"]
    assert float(out[1]) == -3e-6
    assert normalise_negative_numbers(["--a", "-inf"], {"--a"}) == ["--a=-inf"]


@pytest.mark.parametrize("argv, option", [
    (["track", "m.tif", "--snr", "nan"], "--snr"),
    (["track", "m.tif", "--search-range=-5"], "--search-range"),
    (["track", "m.tif", "--gain=-1"], "--gain"),
    (["track", "m.tif", "--gain", "0"], "--gain"),
    (["track", "m.tif", "--memory", "-1"], "--memory"),
    (["track", "m.tif", "--pixel-size", "inf"], "--pixel-size"),
    (["analyze", "m.tif", "--radius", "-1e-6", "--viscosity", "1e-3", "--temperature", "293"], "--radius"),
    (["msd", "t.parquet", "--motion-blur", "0.3"], "--motion-blur"),
    (["velocity", "t.parquet", "--min-frames", "3"], "--min-frames"),
    (["wall", "--radius", "1e-6", "--ratio", "1.5"], "--ratio"),
    (["render", "t.parquet", "--out", "o", "--motion-blur", "-2"], "--motion-blur"),
    (["render-calibration", "--out", "o", "--z-range", "3e-6", "-3e-6"], "--z-range"),
    (["simulate", "s.toml", "--out", "o", "--seed", "-1"], "--seed"),
    (["study", "deposition", "--cn-factor", "0.9"], "--cn-factor"),
])
def test_bad_numbers_are_one_line_naming_the_option(capsys, argv, option):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {option} "), err


def test_usage_errors_are_one_line(capsys):
    assert main(["track", "m.tif", "--snr", "abc"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "invalid float value" in err[0] and "--help" in err[0]
    assert main(["wall"]) == 2  # a required option missing
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_subcommand_help_returns_zero(capsys):
    assert main(["wall", "--help"]) == 0
    assert "--radius" in capsys.readouterr().out


def test_range_messages():
    r = Range("a positive number", lo=0.0, lo_open=True)
    assert r.problem(1e-300) is None and r.problem(0.0) == r.problem(-1.0) == "not above 0"
    assert OPTIONS["--memory"].problem(-1) == "below 0"
    assert r.problem(math.nan) == "not a finite number" and r.problem(math.inf) == "not a finite number"
    assert OPTIONS["--memory"].problem(1.5) == "not a whole number"


def test_user_error_is_a_value_error():
    e = UserError("x is bad", "give a good x")
    assert isinstance(e, ValueError) and str(e) == "x is bad; give a good x" and (e.cause, e.fix) == ("x is bad", "give a good x")
    with pytest.raises(ValueError):
        raise UserError("x")


def _raising(exc):
    def run(args):
        raise exc
    return run


def test_environment_errors_are_one_line(capsys, monkeypatch):
    import errno

    import ptrack.commands.wall_cmd as wall_cmd

    argv = ["wall", "--radius", "1e-6", "--height", "2e-6", "--json", "/x/w.json"]
    monkeypatch.setattr(wall_cmd, "run", _raising(OSError(errno.ENOSPC, "No space left on device", "/x/w.json")))
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: No space left on device: /x/w.json; free some space or write to another disk"]
    # pyarrow's errors carry the errno in the text only, and no file name: the outputs are named
    monkeypatch.setattr(wall_cmd, "run", _raising(OSError("Error writing bytes. Detail: [errno 28] No space left")))
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device (writing --json /x/w.json)" in err[0]
    monkeypatch.setattr(wall_cmd, "run", _raising(OSError(errno.EROFS, "Read-only file system", "/x")))
    assert main(argv) == 2 and "read-only" in capsys.readouterr().err
    monkeypatch.setattr(wall_cmd, "run", _raising(OSError(errno.ECONNREFUSED, "refused")))
    with pytest.raises(OSError):  # not an environment problem the user can fix by a path: a real traceback
        main(argv)


def test_ctrl_c_is_one_line_exit_130_also_from_a_compiled_kernel(capsys, monkeypatch):
    import ptrack.commands.wall_cmd as wall_cmd

    argv = ["wall", "--radius", "1e-6", "--height", "2e-6"]
    monkeypatch.setattr(wall_cmd, "run", _raising(KeyboardInterrupt()))
    assert main(argv) == 130
    assert len(capsys.readouterr().err.strip().splitlines()) == 1

    def numba_like(args):  # numba: "CPUDispatcher(...) returned a result with an exception set"
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("CPUDispatcher(<function k>) returned a result with an exception set") from exc

    monkeypatch.setattr(wall_cmd, "run", numba_like)
    assert main(argv) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: interrupted")


def test_check_writable(tmp_path):
    import os

    from ptrack.errors import check_writable, output_dir

    assert check_writable(tmp_path / "a" / "b.parquet") == tmp_path / "a" / "b.parquet"
    assert list(tmp_path.iterdir()) == []  # nothing created
    (tmp_path / "f").write_text("x")
    with pytest.raises(UserError, match="is a file"):
        check_writable(tmp_path / "f" / "b.parquet")
    with pytest.raises(UserError, match="is a folder"):
        check_writable(tmp_path)
    with pytest.raises(UserError, match="cannot be written"):
        check_writable("/proc/ptrack-nope/out.parquet")
    with pytest.raises(UserError, match="MB are free"):
        check_writable(tmp_path / "big.bin", need_bytes=10**18)
    # output_dir: a refused run leaves no empty folder, a run that wrote something keeps it
    with pytest.raises(UserError):
        with output_dir(tmp_path / "run" / "sub"):
            raise UserError("refused")
    assert not (tmp_path / "run").exists()
    with pytest.raises(RuntimeError):
        with output_dir(tmp_path / "run2") as d:
            (d / "partial.txt").write_text("x")
            raise RuntimeError
    assert (tmp_path / "run2" / "partial.txt").exists()
    assert os.access(tmp_path, os.W_OK)
