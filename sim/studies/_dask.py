"""Run independent study cases as dask.distributed tasks (or serially).

Each case is one task; a task vectorises its replicates inside one numba
kernel, so the number of tasks stays small and each is worth scheduling.
By default a LocalCluster with threads (``processes=False``; the numba
kernels release the GIL with ``nogil=True``) uses the cores of this machine;
``scheduler="tcp://host:8786"`` sends the tasks to a running cluster.
Every task seeds its own generator, so results do not depend on where or in
which order the tasks ran.
"""
from __future__ import annotations

import logging
import os
import sys

from ptrack.errors import UserError


def add_study_arguments(p) -> None:
    """The options shared by the studies."""
    p.add_argument("--out", default=None, help="output directory for the table (CSV) and figure (PNG)")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the results as JSON to PATH")
    p.add_argument("--replicates", type=int, default=None, help="replicates per case (see the study's description)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="address of a running dask scheduler (default: a local cluster)")
    p.add_argument("--no-dask", action="store_true", help="run the cases serially in this process")
    p.add_argument("--workers", type=int, default=None, help="threads of the local cluster (default: all cores)")
    p.add_argument("--quick", action="store_true", help="reduced run (fewer replicates/frames) for a fast check")
    p.add_argument("--seed", type=int, default=0, help="base seed (same seed, same numbers)")


def run_cases(func, cases: list, scheduler: str | None = None, use_dask: bool = True, workers: int | None = None,
              progress: bool = True, desc: str = "cases") -> list:
    """Apply ``func`` to every case; return the results in the order of ``cases``.

    Parameters
    ----------
    func : callable
        Picklable function of one case (a dict); must seed its own generator.
    cases : list
    scheduler : str, optional
        Address of a running dask scheduler.
    use_dask : bool
        False: a plain serial loop (tests, debugging).
    workers : int, optional
        Threads of the local cluster (default: CPU count).
    """
    from tqdm import tqdm

    if not use_dask:
        return [func(c) for c in tqdm(cases, desc=desc, disable=not progress, file=sys.stderr)]
    from dask.distributed import Client, LocalCluster, as_completed

    logging.getLogger("distributed").setLevel(logging.ERROR)
    cluster = None
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise UserError(f"cannot reach the dask scheduler at {scheduler}: {exc}",
                                "check the address, or leave out --scheduler to use a local cluster")
        else:
            n = workers or os.cpu_count() or 1
            cluster = LocalCluster(n_workers=1, threads_per_worker=n, processes=False, dashboard_address=":0")
            client = Client(cluster)
        try:
            futures = client.map(func, cases, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            results = [None] * len(cases)
            with tqdm(total=len(cases), desc=desc, disable=not progress, file=sys.stderr) as bar:
                for fut in as_completed(futures):
                    results[index[fut.key]] = fut.result()
                    bar.update(1)
            return results
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()


def case_seed(base_seed: int, index: int) -> int:
    """Independent integer seed for case ``index`` of a study with ``base_seed``."""
    import numpy as np

    return int(np.random.SeedSequence([int(base_seed), int(index)]).generate_state(1)[0] & 0x7FFFFFFF)
