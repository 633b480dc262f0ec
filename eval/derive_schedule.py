"""A searched schedule with its reuse direction changed on the early steps.

    python eval/derive_schedule.py results/schedules/lift_steps_0.93.json --early rollout --until 50 \
        --out results/schedules/lift_steps_0.93_rollout_early.json

Every reuse decision at a step below ``--until`` becomes ``--early`` (e.g. rollout: features of the
previous call of the episode at the high-noise steps), the later steps keep the schedule's own reuse
(timestep for the whole-step searches); compute decisions are unchanged, so the sparsity is the
same. The result is a schedule file for ``--method file:...``, with where it came from.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance, write_json  # noqa: E402

LETTER = {"forward": "F", "timestep": "T", "rollout": "R"}


def derive(doc: dict, early: str, until: int) -> dict:
    """``doc`` (a schedule: ``grid`` of 'CFTR' strings per step, ``directions``) with the reuse
    letters of steps < ``until`` replaced by ``early``'s."""
    grid = doc["grid"]
    if not grid or not isinstance(grid[0], str):
        raise ValueError("expected a schedule whose grid is one 'CFTR' string per step")
    if not 0 < until <= len(grid):
        raise ValueError(f"--until must be in 1..{len(grid)} (the schedule's steps), got {until}")
    letter = LETTER[early]
    new = [row if k >= until else "".join(c if c == "C" else letter for c in row) for k, row in enumerate(grid)]
    used = {name for name, code in LETTER.items() if any(code in row for row in new)}
    return {"method": f"{doc.get('method', 'schedule')}; reuse at steps < {until} along {early}",
            "directions": [d for d in LETTER if d in used], "grid": new,
            "sparsity": doc.get("sparsity"), "compute_steps": doc.get("compute_steps"),
            "calibration_episodes": doc.get("calibration_episodes"), "early": early, "until": until}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("schedule", type=Path)
    ap.add_argument("--early", choices=sorted(LETTER), default="rollout")
    ap.add_argument("--until", type=int, default=50, help="steps below this index take the --early direction")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    doc = derive(json.loads(args.schedule.read_text()), args.early, args.until)
    doc.update(derived_from=str(args.schedule), provenance=provenance())
    write_json(args.out, doc)
    print(f"wrote {args.out}: directions {doc['directions']}")
    return doc


if __name__ == "__main__":
    main()
