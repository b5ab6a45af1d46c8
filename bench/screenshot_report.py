"""Screenshot an HTML report of ``ptrack compare`` / ``ptrack twin`` in headless Chromium (a dev check; CI does not need it).

Renders the page offline (no network: the figures are embedded as base64
PNG) and writes a PNG screenshot, then checks in the page itself that every
figure decoded (naturalWidth > 0) and that the verdict table is present,
using Chromium's DOM dump.

    python bench/screenshot_report.py REPORT.html [--out shot.png] [--width 1300] [--height 2400]

Without a report, it makes one first from two simulated tables (the second with
D 30 % higher) with ``ptrack compare``. Needs Debian's ``chromium`` package
(``apt-get install -y chromium``).
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

_CHECK = """<script>window.addEventListener('load', function () {
  var imgs = document.images, bad = 0;
  for (var i = 0; i < imgs.length; i++) { if (!(imgs[i].complete && imgs[i].naturalWidth > 0)) bad++; }
  var rows = document.querySelectorAll('tr.differs, tr.consistent, tr.insufficient').length;
  document.body.setAttribute('data-check', 'images=' + imgs.length + ' broken=' + bad + ' verdict_rows=' + rows);
});</script>"""


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    sys.exit("chromium not found: apt-get install -y chromium")


def sample_report(d: Path) -> Path:
    import numpy as np

    from ptrack.cli import main
    from ptrack.table import write_table
    from ptrack.velocity import drifting_tracks

    for i, f in enumerate((1.0, 1.3)):
        t = drifting_tracks(60, 100, 8.6e-13 * f, 0.1, 0.0, sigma=20e-9, seed=i)
        t["z"] = np.nan
        write_table(t, d / f"sim{i}.parquet")
    main(["compare", str(d / "sim0.parquet"), str(d / "sim1.parquet"), "--names", "sim D,sim 1.3 D",
          "--report", str(d / "report"), "--n-perm", "500"])
    return d / "report" / "report.html"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report", nargs="?", help="report.html (default: make one from simulated tables)")
    ap.add_argument("--out", default="report_screenshot.png")
    ap.add_argument("--width", type=int, default=1300)
    ap.add_argument("--height", type=int, default=2400)
    a = ap.parse_args(argv)
    exe = chromium()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        report = Path(a.report) if a.report else sample_report(tmp)
        page = report.read_text()
        checked = tmp / "checked.html"
        checked.write_text(page.replace("</body>", _CHECK + "</body>"))
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--disable-extensions",
                 "--no-first-run", "--disable-background-networking", "--virtual-time-budget=5000",
                 f"--user-data-dir={tmp / 'profile'}"]
        subprocess.run([exe, *flags, f"--window-size={a.width},{a.height}", f"--screenshot={Path(a.out).resolve()}",
                        checked.resolve().as_uri()], check=True, capture_output=True, timeout=120)
        dom = subprocess.run([exe, *flags, "--dump-dom", checked.resolve().as_uri()], check=True,
                             capture_output=True, text=True, timeout=120).stdout
    m = re.search(r'data-check="([^"]+)"', dom)
    check = m.group(1) if m else "no check result (script did not run)"
    print(f"{report}: {len(page) / 1e6:.2f} MB, external references: "
          f"{len(re.findall(r'(?:src|href)=.(?:https?:)?//', page))}; in Chromium: {check}")
    print(f"wrote {a.out}")
    ok = m and " broken=0 " in check + " " and "verdict_rows=0" not in check
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
