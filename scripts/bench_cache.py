"""Throughput of the radiance cache: inference and training points/s per encoding and MLP shape.

Measures, at 2^16 points per call (one warm-up call excluded, best of ``--reps`` timed calls):

* inference: ``RadianceCache.query`` (EMA weights, no autograd);
* training: ``RadianceCache.train_step`` (forward, backward, fused Adam step, EMA update);

for the position encodings T2, T12 (triangle wave, 2 / 12 frequencies), F12 (frequency), and the hash
grid with 8 / 12 / 16 levels (F = 2, T = 2^19, N_min = 16, per-level scale 2: Spindler's grid), each
with one-blob (4 bins) on the direction, times MLP width {64, 128} x hidden layers {3, 4, 5, 6}; plus
the hash-grid encoding alone (forward + backward) for L = 8, 12, 16. Results go to stdout and to the
``## Radiance cache throughput`` section of ``docs/measurements/speed.md``.

    python scripts/bench_cache.py            # full table (~4 min on 2 cores)
    python scripts/bench_cache.py --quick    # width 64, depths 3 and 6, one timed call each
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from lab import REPO

from nrc.cache import build_radiance_cache  # noqa: E402
from nrc.cache.allocator import retain_freed_memory  # noqa: E402
from nrc.cache.encodings.hashgrid import HashGridEncoding  # noqa: E402
from nrc.volume.grid import DensityGrid  # noqa: E402

N_POINTS = 1 << 16
SECTION = "## Radiance cache throughput"
ONEBLOB4 = {"otype": "OneBlob", "n_bins": 4}


def _hashgrid(levels: int) -> dict:
    return {"otype": "HashGrid", "n_levels": levels, "n_features_per_level": 2, "log2_hashmap_size": 19,
            "base_resolution": 16, "per_level_scale": 2.0}


ENCODINGS = {
    "T2/OB4": {"otype": "TriangleWave", "n_frequencies": 2},
    "T12/OB4": {"otype": "TriangleWave", "n_frequencies": 12},
    "F12/OB4": {"otype": "Frequency", "n_frequencies": 12},
    "HG8/OB4": _hashgrid(8),
    "HG12/OB4": _hashgrid(12),
    "HG16/OB4": _hashgrid(16),
}


def _best_seconds(fn: Callable[[], object], reps: int, warmup: int = 1) -> float:
    """Shortest of ``reps`` timed calls after ``warmup`` untimed ones (the least disturbed by other load)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def _inputs(grid: DensityGrid, device: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    x = grid.box.lo.cpu() + grid.box.extent.cpu() * torch.rand(N_POINTS, 3, generator=g)  # drawn on the CPU
    d = torch.nn.functional.normalize(torch.randn(N_POINTS, 3, generator=g), dim=1)
    t = torch.rand(N_POINTS, 3, generator=g)
    return x.to(device), d.to(device), t.to(device)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def bench_cache(position: dict, width: int, depth: int, grid: DensityGrid, device: str, reps: int) -> tuple[float, float]:
    """(inference, training) points/s of one configuration."""
    cache_cfg = {"network": {"n_neurons": width, "n_hidden_layers": depth}, "optimizer": {"lr": 1e-2, "eps": 1e-15,
                 "weight_decay": 1e-6}, "ema": {"alpha": 0.99}, "loss": {"target_clamp": 1000.0}, "query_chunk": N_POINTS}
    cache = build_radiance_cache(cache_cfg, {"position": position, "direction": ONEBLOB4}, {}, grid, device, 0)
    x, d, t = _inputs(grid, device)

    def infer() -> None:
        cache.query(x, d)
        _sync(device)

    def train() -> None:
        cache.train_step(x, d, t)
        _sync(device)

    return N_POINTS / _best_seconds(infer, reps), N_POINTS / _best_seconds(train, reps)


def bench_hashgrid(levels: int, device: str, reps: int) -> float:
    """Forward + backward points/s of the hash-grid encoding alone."""
    enc = HashGridEncoding(levels, 2, 19, 16, 2.0).to(device)
    x = torch.rand(N_POINTS, 3, generator=torch.Generator().manual_seed(0)).to(device)

    def step() -> None:
        enc.table.grad = None
        enc(x).sum().backward()
        _sync(device)

    return N_POINTS / _best_seconds(step, reps)


def _fmt(points_per_s: float) -> str:
    return f"{points_per_s / 1e3:.0f}"


def _machine(device: str) -> str:
    from lab.machine import machine

    return f"{machine(device)}, Python {platform.python_version()}"


def run(widths: list[int], depths: list[int], reps: int, device: str, command: str) -> str:
    grid = DensityGrid(torch.rand(32, 32, 32, generator=torch.Generator().manual_seed(0)), center=(0, 0, 0),
                       diagonal=2.0, density_scale=1.0, device=device)
    load_before = os.getloadavg()[0]
    started = time.perf_counter()
    shapes = [(w, d) for w in widths for d in depths]
    results: dict[str, list[tuple[float, float]]] = {}
    for name, position in ENCODINGS.items():
        results[name] = []
        for w, d in shapes:
            inf, train = bench_cache(position, w, d, grid, device, reps)
            results[name].append((inf, train))
            print(f"{name:9s} {w:4d}x{d}  inference {_fmt(inf):>6s} k/s  training {_fmt(train):>6s} k/s", flush=True)
    hash_only = {levels: bench_hashgrid(levels, device, reps) for levels in (8, 12, 16)}
    for levels, pps in hash_only.items():
        print(f"hash grid L={levels:2d} forward+backward {_fmt(pps)} k/s", flush=True)
    elapsed = time.perf_counter() - started
    load_after = os.getloadavg()[0]

    header = "| encoding | " + " | ".join(f"{w}x{d}" for w, d in shapes) + " |"
    rule = "|---|" + "---:|" * len(shapes)
    lines = [
        SECTION,
        "",
        f"Machine: {_machine(device)}; device `{device}`. Command: `{command}` (best of {reps} timed "
        f"call(s) after one warm-up call; {elapsed:.0f} s in total; 1-minute load average {load_before:.1f} "
        f"before, {load_after:.1f} after: other processes on the machine slow the numbers down).",
        "",
        "Thousands of points per second at 2^16 points per call. Columns: MLP width x hidden layers. "
        "Position encodings: T = triangle wave, F = frequency (sin, cos), n = frequencies; HG = hash grid, "
        "n = levels, F = 2, T = 2^19, N_min = 16, per-level scale 2. Direction: one-blob, 4 bins (OB4), "
        "on the spherical angles. No extra inputs. On a machine shared with other jobs repeated runs differ "
        "by up to ~25 %: read the trends (width, depth, levels), not single cells. With 2 intra-op threads "
        "while other jobs keep a core busy, every parallel op waits for that core, so `--threads 1` gives "
        "the more faithful numbers then.",
        "",
        "**Inference** (`RadianceCache.query`: EMA weights, no autograd)",
        "",
        header,
        rule,
        *(f"| {name} | " + " | ".join(_fmt(i) for i, _ in row) + " |" for name, row in results.items()),
        "",
        "**Training** (`RadianceCache.train_step`: forward, backward, fused Adam step, EMA update)",
        "",
        header,
        rule,
        *(f"| {name} | " + " | ".join(_fmt(t) for _, t in row) + " |" for name, row in results.items()),
        "",
        "**Hash-grid encoding alone**, forward + backward (table gradient), F = 2, T = 2^19",
        "",
        "| levels | 8 | 12 | 16 |",
        "|---|---:|---:|---:|",
        "| k points/s | " + " | ".join(_fmt(hash_only[lv]) for lv in (8, 12, 16)) + " |",
        "",
    ]
    return "\n".join(lines)


def write_section(section: str, path: Path) -> None:
    """Replace (or append) the ``## Radiance cache throughput`` section of ``path``, keeping the rest."""
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.strip() == SECTION), None)
    if start is None:
        out = text.rstrip("\n") + "\n\n" + section
    else:
        end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
        out = "\n".join(lines[:start] + section.rstrip("\n").splitlines() + ([""] + lines[end:] if end < len(lines) else []))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(out.rstrip("\n") + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="width 64, depths 3 and 6, one timed call")
    parser.add_argument("--reps", type=int, default=5, help="timed calls per configuration (full run)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--no-write", action="store_true", help="print only; leave docs/measurements/speed.md alone")
    parser.add_argument("--markdown", type=Path, help="also write the section to this file")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    if args.device == "cpu":
        retain_freed_memory()
    widths, depths, reps = ([64], [3, 6], 1) if args.quick else ([64, 128], [3, 4, 5, 6], args.reps)
    command = " ".join(["python scripts/bench_cache.py", *sys.argv[1:]])
    section = run(widths, depths, reps, args.device, command)
    if not args.no_write:
        write_section(section, REPO / "docs" / "measurements" / "speed.md")
    if args.markdown is not None:
        args.markdown.write_text(section)
    print("\n" + section)


if __name__ == "__main__":
    main()
