"""Packages of the distribution, with the shipped scenes and synthetic datasets as package data.

Everything else is in pyproject.toml. The data folders stay where they are in
the source tree (``scenes/``, ``data/synthetic/``) and are installed as
``sim/scenes/`` and ``ptrack/datasets/<name>/``, so that a non-editable
``pip install`` can run ``ptrack study deposition --example 1`` and
``python -m ptrack.mainjob``.
"""
from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).resolve().parent
DATA = {"sim.scenes": "scenes", "ptrack.datasets": "data/synthetic"}
for d in sorted((ROOT / "data" / "synthetic").iterdir()):
    if d.is_dir():
        DATA[f"ptrack.datasets.{d.name}"] = f"data/synthetic/{d.name}"

setup(
    packages=find_packages(include=["ptrack*", "sim*"]) + list(DATA),
    package_dir=DATA,
    package_data={k: ["*.toml", "*.tif", "*.json", "*.csv", "*.parquet", "*.txt"] for k in DATA},
)
