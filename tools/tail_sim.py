"""How far after the balanced end does a Ray job's last worker finish? A simulation of the
driver's hand-out (issue 44): W workers at their own rates (``--rate`` frames/s, +-``--jitter``
relative, drawn per worker), T tasks of L frames whose frames cost 1 +- ``--cost`` of a frame
(drawn per task: sequences of more or fewer points), each worker asking for its next task once
it holds fewer than ``--ahead`` frames (its pipeline's read-ahead). Two rules decide the cuts:
``halve`` (before the ninth session: halved while the queue is shorter than the workers) and
``share`` (the shipped ``lidar/dataset/ray_tail.first_part``, fed with the simulated rates,
held and queued frames). Prints the mean (and worst) over ``--draws`` draws of the last
worker's end after the balanced end (all the work / the summed rate).

    python tools/tail_sim.py                          # 12 workers at 53 frames/s, 96 x 150 frames
    python tools/tail_sim.py --workers 8 --rate 68    # 8 workers at 68
"""

from __future__ import annotations

import argparse

import numpy as np

from floxels_ext.lidar.dataset.ray_tail import TailShare, first_part

MIN_FRAMES = 16  # ray_runner.TAIL_SPLIT_FRAMES


def simulate(rule: str, workers: int, tasks: int, frames: int, rate: float, jitter: float, ahead: int,
             cost: float, seed: int, dt: float = 0.02) -> float:
    """The last worker's end after the balanced end (s), one draw."""
    rng = np.random.default_rng(seed)
    rates = rate * (1 + jitter * rng.standard_normal(workers))
    costs = np.clip(1 + cost * rng.standard_normal(tasks), 0.3, None)
    queue = [[frames, c] for c in costs]          # [frames, cost a frame]
    held: list[list[list[float]]] = [[] for _ in range(workers)]
    ends: list[float | None] = [None] * workers
    tail, names = TailShare(), [f"w{i}" for i in range(workers)]
    for n in names:
        tail.written(n, 1, 0.0)  # the first report starts each clock
    t = 0.0
    while any(e is None for e in ends):
        for w in range(workers):
            if ends[w] is not None:
                continue
            if sum(h[0] for h in held[w]) < ahead and queue:
                n, c = queue.pop(0)
                if rule == "halve":
                    first = n / 2 if len(queue) < workers else None
                else:
                    h = {names[i]: int(sum(x[0] for x in held[i])) for i in range(workers) if ends[i] is None}
                    first = first_part(tail, names[w], n, [q[0] for q in queue], h, t)
                if first is not None and n >= 2 * MIN_FRAMES:
                    a = int(round(min(max(first, MIN_FRAMES), n - MIN_FRAMES)))
                    queue.insert(0, [n - a, c])
                    n = a
                held[w].append([n, c])
            if held[w]:
                step = rates[w] * dt / held[w][0][1]
                held[w][0][0] -= step
                tail.written(names[w], step, t)
                if held[w][0][0] <= 0:
                    held[w].pop(0)
            elif not queue:
                ends[w] = t
        t += dt
    return max(ends) - costs.sum() * frames / rates.sum()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=12)
    ap.add_argument("--tasks", type=int, default=96)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--rate", type=float, default=53.0)
    ap.add_argument("--jitter", type=float, default=0.08)
    ap.add_argument("--ahead", type=int, default=24)
    ap.add_argument("--cost", type=float, nargs="+", default=[0.0, 0.3])
    ap.add_argument("--draws", type=int, default=10)
    args = ap.parse_args()
    print(f"{args.workers} workers at {args.rate:g} frames/s +- {args.jitter:.0%}, {args.tasks} x {args.frames} frames, "
          f"asking below {args.ahead} held; {args.draws} draws: the last worker's end after the balanced end, mean (worst)")
    for cost in args.cost:
        row = []
        for rule in ("halve", "share"):
            r = np.array([simulate(rule, args.workers, args.tasks, args.frames, args.rate, args.jitter, args.ahead, cost, s)
                          for s in range(args.draws)])
            row.append(f"{rule} {r.mean():.2f} s ({r.max():.2f})")
        print(f"  frames' cost +- {cost:.0%}: " + ", ".join(row))


if __name__ == "__main__":
    main()
