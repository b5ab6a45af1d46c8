"""Writing a study's outputs: CSV tables, the PNG figure and the JSON summary.

Every file appears only when complete (:func:`ptrack.errors.atomic_output`),
and every writer returns the path it wrote so a study can list its outputs.
"""
from __future__ import annotations

import json
from pathlib import Path

from ptrack.errors import atomic_output


def write_csv(df, path) -> Path:
    """Write a DataFrame to ``path`` as CSV without the index."""
    path = Path(path)
    with atomic_output(path, "w") as fh:
        df.to_csv(fh, index=False)
    return path


def save_figure(fig, path, dpi: int = 120) -> Path:
    """Save a matplotlib figure to ``path`` as PNG and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_output(path, None) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return path


def case_records(cases: list, keys) -> list[dict]:
    """The ``keys`` of every case dict, in order (the per-case part of a study's JSON)."""
    return [{k: c[k] for k in keys} for c in cases]


def write_json(doc: dict, path) -> Path:
    """Write ``doc`` to ``path`` as indented JSON."""
    path = Path(path)
    with atomic_output(path, "w") as fh:
        json.dump(doc, fh, indent=2)
    return path
