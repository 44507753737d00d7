"""Generation time of the procedural clouds (median of repeats, this process's threads).

Usage::

    python scripts/bench_procedural.py [--resolutions 128 256] [--repeats 3]
"""

import argparse
import statistics
import time


import torch  # noqa: E402

from nrc.volume.procedural import KINDS, procedural_cloud  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--resolutions", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    print("| kind | resolution | grid (cropped) | filled (> 0.01) | time (median) |")
    print("|---|---|---|---|---|")
    for kind in KINDS:
        for res in args.resolutions:
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                d = procedural_cloud(res, 0, kind)
                times.append(time.perf_counter() - t0)
            filled = float((d > 0.01).float().mean())
            print(f"| {kind} | {res} | {'x'.join(map(str, d.shape))} | {filled:.0%} | {statistics.median(times):.2f} s |")


if __name__ == "__main__":
    main()
