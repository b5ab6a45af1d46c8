"""Figures of the fault suite: cases tried, clean, and what each fault class does; the kill/resume table.

Runs every case of ``tests/test_faults.py`` (the same corpus, built in a
temporary folder, the same checks, but ignoring the xfail marks so the figures
say what the code does today) and prints per fault class how many cases were
tried and how many ended cleanly (exit 2, or 130 for Ctrl-C; one ``error:``
line; no traceback; nothing left behind), then each case that did not, with
why. Then a DEM run (80 spheres, 13 frames, a checkpoint every 3 frames) is
killed by SIGKILL, SIGTERM, SIGINT and twice by SIGKILL, each resumed with
``--resume`` (always: a resume of a run that finished before the second
signal says "run already complete" and exits 0), and compared with an
uninterrupted run.

Usage::

    .venv/bin/python bench/bench_faults.py            # everything (~2-3 min on 2 loaded cores)
    .venv/bin/python bench/bench_faults.py --no-kill  # the fault classes only
"""
from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_faults as tf  # noqa: E402


def _classify(problems: list[str]) -> str:
    for key, word in (("traceback", "traceback"), ("too slow / hangs", "still running"), ("wrong exit", "exit "),
                      ("left files", "left behind"), ("wrong blame", "wrong blame"), ("message misses the file", "does not name"),
                      ("not one line", "not one 'error:' line"), ("started before checking", "checked only after")):
        if any(word in p for p in problems):
            return key
    return "other"


def fault_table(suite: tf.Suite) -> list:
    rows = defaultdict(lambda: {"tried": 0, "clean": 0, "skipped": 0, "seconds": 0.0, "bad": defaultdict(int)})
    failures = []
    suite.start_background(tf.CASES, kill_resume=False)
    for case in tf.CASES:
        r = rows[case.kind]
        if suite.skip_reason(case):
            r["skipped"] += 1
            continue
        o = suite.run(case)
        probs = o.problems(case.exit_code, case.not_words, case.expected_text(suite.corpus))
        if case.kind in ("read-only", "unwritable") and o.started_work():
            probs.append("the output was checked only after the work")
        r["tried"] += 1
        r["seconds"] += o.seconds
        if probs:
            r["bad"][_classify(probs)] += 1
            failures.append((case, probs))
        else:
            r["clean"] += 1
    return rows, failures


def kill_table(suite: tf.Suite) -> list:
    out = []
    for name, sigs in (("SIGKILL", [signal.SIGKILL]), ("SIGTERM", [signal.SIGTERM]), ("SIGINT", [signal.SIGINT]),
                       ("SIGKILL twice", [signal.SIGKILL, signal.SIGKILL])):
        work = suite.root / f"kill_{name.replace(' ', '_')}"
        work.mkdir()
        r = tf.kill_and_resume(suite.corpus["dem"], work, sigs)
        ref, got = r["reference"], r["resumed"]
        cols = ["frame", "particle", "x", "y", "z", "vx", "vy", "vz"]
        same = got is not None and len(got) == len(ref) and np.array_equal(got[cols].to_numpy(), ref[cols].to_numpy())
        out.append({"kill": name, "codes": r["codes"], "frames": None if got is None else got["frame"].nunique(),
                    "of": ref["frame"].nunique(), "identical": same,
                    "incomplete": None if got is None else got.attrs["ptrack"].get("incomplete"),
                    "seconds": r["seconds"], "stderr": r["stderr"]})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--no-kill", action="store_true", help="skip the kill/resume table")
    a = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_faults_") as tmp:
        suite = tf.Suite(Path(tmp))
        try:
            rows, failures = fault_table(suite)
            kills = [] if a.no_kill else kill_table(suite)
        finally:
            suite.close()
        mounts = ", ".join(f"{k}: {v}" for k, v in suite.mount_errors.items()) or "tmpfs mounted (2 MiB)"
    print(f"fault suite (tests/test_faults.py, xfail marks ignored; {mounts}); machine shared and loaded\n")
    print(f"{'fault class':<12} {'tried':>6} {'clean':>6} {'skip':>5} {'s':>6}  not clean, by kind")
    tot_t = tot_c = 0
    for kind, r in rows.items():
        bad = ", ".join(f"{k} {v}" for k, v in sorted(r["bad"].items())) or "-"
        print(f"{kind:<12} {r['tried']:>6} {r['clean']:>6} {r['skipped']:>5} {r['seconds']:>6.1f}  {bad}")
        tot_t += r["tried"]
        tot_c += r["clean"]
    print(f"{'all':<12} {tot_t:>6} {tot_c:>6}")
    if failures:
        print("\ncases that are not clean:")
        for case, probs in failures:
            print(f"  {case.id}: {'; '.join(probs)[:300]}")
    if kills:
        print("\nDEM kill/resume (80 spheres, 13 frames, checkpoint every 3 frames; exit codes: reference, each "
              "killed run, the final resume)")
        print(f"{'kill':<14} {'exit codes':<22} {'frames':>7} {'identical':>10} {'marked incomplete':>18} {'s':>6}")
        for k in kills:
            print(f"{k['kill']:<14} {str(k['codes']):<22} {str(k['frames']) + '/' + str(k['of']):>7} "
                  f"{str(k['identical']):>10} {str(bool(k['incomplete'])):>18} {k['seconds']:>6.1f}"
                  + (f"  final resume: {k['stderr'][0][:120]}" if k["stderr"] else ""))
    print(f"\ntotal wall time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
