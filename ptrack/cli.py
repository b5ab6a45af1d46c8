"""The ``ptrack`` command line: one subcommand per task.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; it is imported only when invoked, so ``ptrack --help``
and small commands start fast.

What every command gets here, once:

- negative numbers in scientific notation after a space (``--calib-z0 -3e-6``)
  are values (:func:`ptrack.options.normalise_negative_numbers`);
- every numeric option is range-checked against :mod:`ptrack.options` after
  parsing and before the command runs (NaN and infinity refused);
- a :class:`~ptrack.errors.UserError` raised anywhere, an argparse usage error,
  and an OSError the user can act on (full disk, permission denied, read-only
  file system) become one line ``error: cause; fix`` on stderr, exit status 2;
- Ctrl-C becomes one line and exit status 130, also when it arrives inside a
  compiled (numba) kernel and surfaces as a SystemError.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from . import __version__
from .errors import EXIT_INTERRUPTED, EXIT_USER_ERROR, UserError, os_error_message
from .options import OptionParser, check_namespace, normalise_negative_numbers

# name -> (module, one-line help)
COMMANDS = {
    "msd": ("ptrack.commands.msd_cmd", "MSD and diffusion coefficients of a trajectories table"),
    "wall": ("ptrack.commands.wall_cmd", "hindered diffusion near a wall: ratios for a height, or the height for a ratio"),
    "track": ("ptrack.commands.track", "microscope TIFF series -> trajectories table (2D, or 3D with a calibration stack)"),
    "analyze": ("ptrack.commands.analyze", "track + MSD + Stokes-Einstein + wall correction, with plots and a summary"),
    "velocity": ("ptrack.commands.velocity_cmd", "drift velocities: per particle (GLS), ensemble, against height"),
    "simulate": ("ptrack.commands.simulate", "run a simulation scene (TOML) and stream its trajectories"),
    "study": (None, "verification studies of the simulator (see 'ptrack study --help')"),
    "render": ("ptrack.commands.render", "render a trajectories table as a synthetic microscope movie"),
    "render-calibration": ("ptrack.commands.render_calibration", "render a defocus calibration stack"),
    "sweep": ("ptrack.commands.sweep_cmd", "run a grid of scenes (--set KEY=V1,V2 ...) as dask tasks, one summary table"),
    "compare": ("ptrack.commands.compare_cmd", "compare trajectories tables (experiment vs simulation): MSD, D, van Hove, drift"),
    "twin": ("ptrack.commands.twin_cmd", "a movie's simulated twin: infer parameters, simulate, render, track, compare"),
    "warmup": ("ptrack.commands.warmup", "compile the simulator's kernels into numba's cache (make venv runs it)"),
}

# study name -> (module, one-line help)
STUDIES = {
    "diffusion": ("sim.studies.diffusion", "Brownian diffusion vs Stokes-Einstein (seed Table 3.1)"),
    "electrophoresis": ("sim.studies.electrophoresis", "terminal velocity vs Henry's law (seed Table 3.2)"),
    "deposition": ("sim.studies.deposition", "the seed's deposition examples 1-3"),
    "hamaker": ("sim.studies.hamaker", "deposited number per area vs Hamaker's law"),
    "epd-order": ("sim.studies.epd_order", "deposit order vs Peclet number and Debye length"),
}


def _top_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ptrack",
        description="Particle tracking of colloids and a simulator of field-driven deposition. SI units in files and options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="commands:\n" + "\n".join(f"  {k:<20s}{v[1]}" for k, v in COMMANDS.items())
        + "\n\n'ptrack COMMAND --help' describes a command.",
    )
    p.add_argument("--version", action="version", version=f"ptrack {__version__}")
    p.add_argument("command", nargs="?", help="one of the commands below")
    return p


def _sub_parser(prog: str, module, help_text: str) -> OptionParser:
    p = OptionParser(prog=prog, description=(module.__doc__ or help_text).strip().split("\n\n")[0])
    module.add_arguments(p)
    return p


def command_parser(name: str) -> tuple[str, OptionParser]:
    """(command key, parser) of ``name`` ("track", "study deposition"): for the CLI, tests and docs."""
    if name.startswith("study "):
        modname, help_text = STUDIES[name.split(" ", 1)[1]]
    else:
        modname, help_text = COMMANDS[name]
    return name, _sub_parser(f"ptrack {name}", _load(modname, f"ptrack {name}"), help_text)


def _interrupted(exc: BaseException) -> bool:
    """True if ``exc`` is, or was raised while handling, a KeyboardInterrupt.

    numba reports a Ctrl-C that arrives inside a compiled kernel as
    ``SystemError: CPUDispatcher(...) returned a result with an exception set``
    whose cause is the KeyboardInterrupt.
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _load(modname: str, what: str):
    return importlib.import_module(modname)


def _headless_plots() -> None:
    """Plots from the command line go to files: the Agg backend, set here once for every command
    (the plotting functions leave the backend alone, so a notebook keeps its own)."""
    if "matplotlib" in sys.modules:
        import matplotlib

        matplotlib.use("Agg")
    else:
        os.environ.setdefault("MPLBACKEND", "Agg")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = _top_parser()
    if not argv or argv[0] in ("-h", "--help"):
        top.print_help()
        return 0
    if argv[0] == "--version":
        print(f"ptrack {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    args = None
    try:
        if name not in COMMANDS:
            raise UserError(f"unknown command '{name}'", "run 'ptrack --help' for the list")
        if name == "study":
            if not rest or rest[0] in ("-h", "--help"):
                print("usage: ptrack study NAME [options]\n\nstudies:")
                for k, v in STUDIES.items():
                    print(f"  {k:<18s}{v[1]}")
                return 0
            sname, rest = rest[0], rest[1:]
            if sname not in STUDIES:
                raise UserError(f"unknown study '{sname}'", f"choose one of: {', '.join(STUDIES)}")
            modname, help_text = STUDIES[sname]
            prog = f"ptrack study {sname}"
        else:
            modname, help_text = COMMANDS[name]
            prog = f"ptrack {name}"
        module = _load(modname, prog)
        parser = _sub_parser(prog, module, help_text)
        args = parser.parse_args(normalise_negative_numbers(rest, parser.option_strings()))
        check_namespace(prog[len("ptrack "):], args, parser.numeric_actions)
        _headless_plots()
        return int(module.run(args) or 0)
    except UserError as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:
        return _fail(_INTERRUPTED, EXIT_INTERRUPTED)
    except SystemExit as exc:  # --help, --version of a subcommand
        if exc.code in (None, 0):
            return 0
        raise
    except OSError as exc:  # the last resort for the environment: full disk, permissions, read-only
        msg = os_error_message(exc)
        if msg is None:
            raise
        cause, fix = msg
        if not exc.filename and args is not None:  # pyarrow, tifffile... do not say which file
            outs = [f"--{d.replace('_', '-')} {getattr(args, d)}" for d in _OUTPUT_DESTS if getattr(args, d, None)]
            if outs:
                cause += f" (writing {', '.join(outs)})"
        return _fail(f"{cause}; {fix}")
    except SystemError as exc:
        if _interrupted(exc):
            return _fail(_INTERRUPTED,
                         EXIT_INTERRUPTED)
        raise


_INTERRUPTED = "interrupted; files already written are complete (a streamed table is kept, marked incomplete)"

# options that name output files or folders, for messages about a failed write
_OUTPUT_DESTS = ("out", "report", "json", "plot", "tracks_out")


def _fail(message: str, code: int = EXIT_USER_ERROR) -> int:
    """Print ``error: message`` as one line on stderr; return ``code``."""
    line = " ".join(message.split())  # one line, whatever the message holds
    sys.stdout.flush()
    print(f"error: {line}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
