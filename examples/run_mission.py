"""Run a mission from Python: load a mission file, configure it, add to its timeline, run
it (the process set, the ground station playing the timeline over the authenticated
uplink), and read what it recorded.

    .venv/bin/python examples/run_mission.py --steps 12 --out runs/api
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mission import Mission

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=24)
    ap.add_argument("--out", default="runs/api")
    args = ap.parse_args()

    mission = Mission.load(HERE / "mission.toml", steps=args.steps, out=args.out)
    mission.configure(planner={"n_candidates": 32})  # any setting, as in the file
    mission.at_window(2, "set gate.k=3")  # one more command, in the second window
    result = mission.run()

    print(f"final coverage {result.metrics['final_coverage']:.3f} after "
          f"{result.metrics['steps']} steps, {result.metrics['collisions']} collisions")
    for ack in result.acks:
        print(f"command {ack['id']} ({ack['verb']}) {ack['state']} at step "
              f"{ack['executed_step']}: {ack['detail']}")
    print(f"recorded in {result.bag}; replay it with `rovergate replay {result.bag}`")


if __name__ == "__main__":
    main()
