"""Ranges of the command-line options: one table, checked once by :func:`ptrack.cli.main`.

Every numeric option of every command (``type=float`` or ``type=int``) has an
entry in :data:`OPTIONS`, keyed by its option string; :data:`COMMAND_OPTIONS`
overrides an entry where one name means something else in one command (e.g.
``render --motion-blur`` counts sub-positions, elsewhere it is the motion-blur
parameter R). :func:`check_namespace` applies the table to parsed arguments
before a command runs, so a bad value fails in a fraction of a second with one
line naming the option, the value and what is expected, and no command needs
its own copy of the rule. NaN and infinity are refused for every float option.

:class:`OptionParser` is an :class:`argparse.ArgumentParser` that records the
numeric options it is given (through the public ``add_argument`` /
``add_argument_group`` / ``add_mutually_exclusive_group`` API only) and turns
argparse's usage errors into one-line :class:`~ptrack.errors.UserError`.
:func:`normalise_negative_numbers` lets ``--calib-z0 -3e-6`` (a negative
number in scientific notation after a space) be read as a value.
"""
from __future__ import annotations

import argparse
import math
import re
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation

from .constants import MOTION_BLUR_MAX
from .errors import UserError


@dataclass(frozen=True)
class Range:
    """An allowed range of one option's values.

    Parameters
    ----------
    expected : str
        What is expected, as shown to the user ("a positive number").
    lo, hi : float, optional
        Bounds (None: unbounded).
    lo_open, hi_open : bool
        Exclude the bound itself.
    integer : bool
        Whole numbers only.
    nonzero : bool
        Refuse 0 (for signed quantities such as a step).
    increasing : bool
        For options with several values (``nargs=2``): strictly increasing.
    """

    expected: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    nonzero: bool = False
    increasing: bool = False

    def check(self, name: str, v) -> None:
        """Raise a one-line UserError naming option ``name`` if ``v`` is outside the range."""
        why = self.problem(v)
        if why:
            raise UserError(f"{name} {_show(v)} is {why}", f"give {name} as {self.expected}")

    def problem(self, v) -> str | None:
        """Why ``v`` is outside the range, or None if it is inside."""
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return "not a number"
        if isinstance(v, float) and not math.isfinite(v):
            return "not a finite number"
        if self.integer and v != int(v):
            return "not a whole number"
        if self.lo is not None and (v < self.lo or (self.lo_open and v == self.lo)):
            return f"not above {_num(self.lo)}" if self.lo_open else f"below {_num(self.lo)}"
        if self.hi is not None and (v > self.hi or (self.hi_open and v == self.hi)):
            return f"not below {_num(self.hi)}" if self.hi_open else f"above {_num(self.hi)}"
        if self.nonzero and v == 0:
            return "zero"
        return None


def _num(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def finite(unit: str) -> Range:
    return Range(f"a finite number ({unit})")


def positive(unit: str, hi: float | None = None) -> Range:
    extra = f" up to {_num(hi)}" if hi is not None else ""
    return Range(f"a positive number{extra} ({unit})", lo=0.0, lo_open=True, hi=hi)


def non_negative(unit: str) -> Range:
    return Range(f"a number >= 0 ({unit})", lo=0.0)


def whole(lo: int, unit: str, hi: int | None = None) -> Range:
    span = f">= {lo}" if hi is None else f"from {lo} to {hi}"
    return Range(f"a whole number {span} ({unit})", lo=lo, hi=hi, integer=True)


@dataclass(frozen=True)
class RuleRange(Range):
    """A range whose check is a function of the library, so the command line and the API share one rule and message.

    ``rule`` is ``"module:function"``; the function takes ``(value, name)``,
    returns the value or raises :class:`~ptrack.errors.UserError`. It is
    imported when a value is checked (the command line stays light until an
    option is given). ``lo``, ``hi`` ... only describe the range (for help
    and tests); they are not a second check.
    """

    rule: str = ""

    def check(self, name: str, v) -> None:
        import importlib

        mod, func = self.rule.split(":")
        getattr(importlib.import_module(mod), func)(v, name)

    def problem(self, v) -> str | None:
        try:
            self.check("value", v)
        except UserError as e:
            return e.cause.removeprefix(f"value = {v!r} ")
        return None


#: The motion-blur parameter R of a camera exposure, 0 (instantaneous) to 1/4 (uniform shutter open the whole
#: frame: R = 1/6): checked by ptrack.motion.tracks.check_motion_blur, the rule of the library.
MOTION_BLUR = RuleRange("a motion-blur parameter R in [0, 1/4) (1/6: full-frame exposure, 0: instantaneous)",
                        lo=0.0, hi=MOTION_BLUR_MAX, hi_open=True, rule="ptrack.motion.tracks:check_motion_blur")
SEED = whole(0, "random seed")

#: option string -> allowed range, for every numeric option of every command
OPTIONS: dict[str, Range] = {
    # physics (analyze, msd, wall, velocity)
    "--radius": positive("particle radius, m"),
    "--viscosity": positive("Pa s"),
    "--temperature": positive("K"),
    "--wall-z": finite("height of the wall, m"),
    "--height": positive("height of the particle centre above the wall, m"),
    "--motion-blur": MOTION_BLUR,
    "--ratio": Range("a ratio D/D0 between 0 and 1, both excluded", lo=0.0, hi=1.0, lo_open=True, hi_open=True),
    "--D0": positive("bulk diffusion coefficient, m^2/s"),
    # msd
    "--max-lag": whole(1, "frames"),
    "--flag-level": Range("a false-positive rate between 0 and 1, both excluded (e.g. 0.01)", lo=0.0, hi=1.0,
                          lo_open=True, hi_open=True),
    "--n-boot": whole(0, "bootstrap resamples; 0: none"),
    "--seed": SEED,
    # compare
    "--level": Range("a family-wise error rate between 0 and 1, both excluded (e.g. 0.05)", lo=0.0, hi=1.0,
                     lo_open=True, hi_open=True),
    "--n-perm": whole(1, "permutations"),
    "--min-particles": whole(2, "particles"),
    # velocity
    "--bins": whole(0, "height bins; 0: none"),
    "--contact": finite("height of a particle centre at contact, m"),
    "--contact-tolerance": non_negative("m"),
    "--min-frames": whole(4, "positions"),
    "--reference": finite("reference velocity, m/s"),
    # track / analyze: calibration
    "--calib-step": Range("a non-zero finite step between calibration pages (m)", nonzero=True),
    "--calib-z0": finite("z of calibration page 0, m"),
    "--cm-min": Range("a correlation from 0 to 1 (e.g. 0.5)", lo=0.0, hi=1.0),
    # track / analyze: image and camera
    "--pixel-size": positive("m per pixel in the sample"),
    "--frame-interval": positive("s between frames"),
    "--diameter": positive("particle image diameter, px"),
    "--snr": positive("detection threshold in noise units"),
    "--gain": positive("ADU per photo-electron"),
    "--offset": non_negative("camera baseline, ADU"),
    "--read-noise": non_negative("e- rms"),
    # track / analyze: linking and workers
    "--search-range": positive("largest step between frames, px"),
    "--memory": whole(0, "frames a particle may be missed"),
    "--min-length": whole(2, "frames"),
    "--workers": whole(1, "worker processes or threads"),
    # render, render-calibration: geometry, optics, camera
    "--shape": whole(1, "pixels"),
    "--focal-plane": finite("height of the focal plane, m"),
    "--exposure": positive("exposure time, s"),
    "--z-range": Range("two finite heights ZMIN < ZMAX (m)", increasing=True),
    "--z-step": positive("height step, m"),
    "--na": positive("numerical aperture"),
    "--wavelength": positive("m"),
    "--medium-index": Range("a refractive index >= 1", lo=1.0),
    "--immersion-index": Range("a refractive index >= 1", lo=1.0),
    "--magnification": positive("magnification"),
    "--astigmatism": finite("wavefront amplitude at the pupil edge, m"),
    "--pixel-pitch": positive("camera pixel pitch, m"),
    "--photons": non_negative("photons per particle per exposure"),
    "--background": non_negative("photons per pixel per exposure"),
    "--qe": Range("a quantum efficiency above 0, up to 1", lo=0.0, hi=1.0, lo_open=True),
    "--bit-depth": whole(1, "bits", hi=16),
    "--scatter-phase": finite("rad"),
    # twin
    "--field": Range("a finite non-zero electric field E_z (V/m)", nonzero=True),
    "--density": positive("particle density, kg/m^3"),
    "--fluid-density": positive("kg/m^3"),
    "--debye-length": positive("m"),
    "--permittivity": Range("a relative permittivity >= 1", lo=1.0),
    "--calibrate": whole(0, "calibration rounds", hi=5),
    # simulate
    "--max-hours": positive("hours of estimated run time on one core"),
    "--threads": whole(1, "threads"),
    # studies
    "--replicates": whole(1, "replicates per case"),
    "--particles": whole(1, "particles"),
    "--frames": whole(3, "output frames"),
    "--example": whole(1, "example number", hi=3),
    "--cn-factor": Range("a factor above 1 (e.g. 1.1)", lo=1.0, lo_open=True),
    "--pe": positive("Peclet number"),
    "--a-over-lambda": positive("radius over Debye length"),
    "--checkpoint-minutes": positive("minutes of wall time between checkpoints"),
}

#: command ("track", "study deposition", ...) -> option -> range, where a name differs in meaning
COMMAND_OPTIONS: dict[str, dict[str, Range]] = {
    # render: sub-positions averaged over the exposure, and a point source allowed
    "render": {"--motion-blur": whole(0, "sub-positions over the exposure; 0: off"),
               "--radius": non_negative("particle radius, m; 0: a point source")},
    "render-calibration": {"--radius": non_negative("particle radius, m; 0: a point source")},
}


def range_for(command: str, option: str) -> Range | None:
    """The range of ``option`` in ``command`` (None: not in the table)."""
    return COMMAND_OPTIONS.get(command, {}).get(option, OPTIONS.get(option))


_NUMERIC_TYPES = (float, int)


def _option_name(action: argparse.Action) -> str:
    longs = [s for s in action.option_strings if s.startswith("--")]
    return max(longs or action.option_strings or [action.dest], key=len)


class _Recorder:
    """Wraps an argument group so the numeric options added to it are recorded."""

    def __init__(self, group, parser: "OptionParser"):
        self._group = group
        self._parser = parser

    def add_argument(self, *args, **kwargs):
        return self._parser.record(self._group.add_argument(*args, **kwargs))

    def add_argument_group(self, *args, **kwargs):
        return _Recorder(self._group.add_argument_group(*args, **kwargs), self._parser)

    def add_mutually_exclusive_group(self, *args, **kwargs):
        return _Recorder(self._group.add_mutually_exclusive_group(*args, **kwargs), self._parser)

    def __getattr__(self, name):
        return getattr(self._group, name)


class OptionParser(argparse.ArgumentParser):
    """ArgumentParser that records its numeric options and raises UserError on usage errors.

    ``numeric_actions`` lists the actions with ``type=float`` or ``type=int``;
    ``option_strings()`` every option string the parser knows.
    """

    def __init__(self, *args, **kwargs):
        self.numeric_actions: list[argparse.Action] = []
        self.all_actions: list[argparse.Action] = []
        self._wrap_groups = False  # argparse's own groups (made in __init__) stay unwrapped
        super().__init__(*args, **kwargs)
        self._wrap_groups = True

    def record(self, action: argparse.Action) -> argparse.Action:
        """Note an action added to this parser or one of its groups; return it."""
        self.all_actions.append(action)
        if action.type in _NUMERIC_TYPES:
            self.numeric_actions.append(action)
        return action

    def add_argument(self, *args, **kwargs):
        return self.record(super().add_argument(*args, **kwargs))

    def add_argument_group(self, *args, **kwargs):
        group = super().add_argument_group(*args, **kwargs)
        return _Recorder(group, self) if self._wrap_groups else group

    def add_mutually_exclusive_group(self, *args, **kwargs):
        return _Recorder(super().add_mutually_exclusive_group(*args, **kwargs), self)

    def option_strings(self) -> set[str]:
        return {s for a in self.all_actions for s in a.option_strings}

    def error(self, message):  # argparse: "should not return"
        raise UserError(f"{self.prog}: {message}", f"see '{self.prog} --help'")


# a float literal argparse (3.11) would take for an option: "-3e-6", "-1.5E+3", "-.5e2"
_SCI_NEGATIVE = re.compile(r"^-(\d+\.?\d*|\.\d+)[eE][-+]?\d+$")
_NONFINITE = {"-inf", "-infinity", "-nan"}


def normalise_negative_numbers(argv: list[str], option_strings=()) -> list[str]:
    """Rewrite argv so negative numbers in scientific notation are read as values.

    argparse (before 3.13) takes ``-3e-6`` after a space for an option string
    and fails with "expected one argument". Such a token, unless the parser
    knows it as an option, is rewritten as the same decimal number in fixed
    notation (``-0.000003``: exactly the same value, parsed by ``float``),
    which argparse reads as a negative number. ``-inf``/``-nan`` after a long
    option become ``--opt=-inf`` so that the range check, not argparse, reports
    them. Tokens after ``--`` are left alone.
    """
    known = set(option_strings)
    out: list[str] = []
    for i, tok in enumerate(argv):
        if tok == "--":
            out.extend(argv[i:])
            break
        if tok not in known and _SCI_NEGATIVE.match(tok):
            try:
                tok = format(Decimal(tok), "f")
            except InvalidOperation:  # pragma: no cover - the regex admits only valid literals
                pass
        elif tok.lower() in _NONFINITE and tok not in known and out and out[-1].startswith("--") \
                and "=" not in out[-1] and out[-1] in known:
            out[-1] = f"{out[-1]}={tok}"
            continue
        out.append(tok)
    return out


def _show(v) -> str:
    return repr(v) if isinstance(v, float) and math.isfinite(v) and v != int(v) else _num(v)


def check_namespace(command: str, args: argparse.Namespace, actions) -> None:
    """Check every numeric option value in ``args`` against the table.

    Parameters
    ----------
    command : str
        Command name as a key of :data:`COMMAND_OPTIONS` ("track", "study deposition").
    args : argparse.Namespace
    actions : iterable of argparse.Action
        The numeric actions of the command's parser (``OptionParser.numeric_actions``).

    Raises
    ------
    UserError
        The first value outside its range, naming the option, the value and what is expected.
    """
    for action in actions:
        value = getattr(args, action.dest, None)
        if value is None:
            continue
        name = _option_name(action)
        rng = range_for(command, name)
        if rng is None:  # not in the table: floats must still be finite
            rng = Range("a finite number") if action.type is float else Range("a whole number", integer=True)
        values = list(value) if isinstance(value, (list, tuple)) else [value]
        for v in values:
            rng.check(name, v)
        if rng.increasing and any(b <= a for a, b in zip(values, values[1:])):
            raise UserError(f"{name} {' '.join(map(_show, values))} is not increasing",
                            f"give {name} as {rng.expected}")
