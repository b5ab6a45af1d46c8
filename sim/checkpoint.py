"""Atomic checkpoints of a DEM run (state, step counter, dt, RNG key, output position).

A checkpoint is one ``.npz`` file written through
:func:`ptrack.errors.atomic_output` (temporary file + rename), so a run killed
while writing leaves the previous checkpoint intact.  It holds the
neighbour-list-independent state of :meth:`sim.dem.DEMSystem.get_state`
(positions, image counters, velocities, angular velocities, forces and
torques of the integrator, wall springs, contact springs as (i, j, spring)
triples), the step counter and time step, plus a small JSON header with the
output-frame counter and a fingerprint of the scene so that a checkpoint is
never resumed against a different scene.  The Brownian random numbers are
counter-based (keyed by seed, step, particle), so the seed and the step
counter are the complete RNG state.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from ptrack.errors import UserError, atomic_output

FORMAT = "ptrack-dem-checkpoint-1"


def scene_fingerprint(scene_dict: dict) -> str:
    """Stable hash of a resolved scene dict (JSON, sorted keys)."""
    txt = json.dumps(scene_dict, sort_keys=True, default=str)
    return hashlib.sha256(txt.encode()).hexdigest()[:16]


def save_checkpoint(path, state: dict, header: dict) -> Path:
    """Write ``state`` (arrays/scalars) and ``header`` (JSON-able) atomically to ``path``."""
    path = Path(path)
    head = dict(header)
    head["format"] = FORMAT
    arrays = {k: np.asarray(v) for k, v in state.items()}
    arrays["_header"] = np.frombuffer(json.dumps(head, default=float).encode(), dtype=np.uint8)
    with atomic_output(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def load_checkpoint(path, fingerprint: str | None = None):
    """Read a checkpoint; returns ``(state_dict, header)``.

    Raises
    ------
    UserError
        Missing/corrupt file, wrong format, or a scene fingerprint that does
        not match ``fingerprint``.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no checkpoint to resume from: {path}", "run without --resume first")
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # corrupt / truncated
        raise UserError(f"checkpoint {path} is unreadable ({exc})", "delete it and rerun without --resume")
    try:
        head = json.loads(bytes(data.pop("_header")).decode())
    except Exception:
        raise UserError(f"checkpoint {path} has no header", "delete it and rerun without --resume")
    if head.get("format") != FORMAT:
        raise UserError(f"checkpoint {path} has format {head.get('format')!r}, expected {FORMAT!r}",
                        "delete it and rerun without --resume")
    if fingerprint is not None and head.get("fingerprint") != fingerprint:
        raise UserError(f"checkpoint {path} belongs to a different scene",
                        "resume with the scene it was written for, or rerun without --resume")
    return data, head
