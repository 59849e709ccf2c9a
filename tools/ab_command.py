"""A `gvae` command timed in two checkouts in turn (A, B, A, B, ...), each run a fresh process:
wall seconds, CPU seconds (user + system), peak RSS and the load average beside each, then the
medians. For A/B comparisons on a shared machine, where alternation and CPU seconds are what make
them fair. Each checkout may keep its compiled kernels in a cache of its own (`--cache-a`,
`--cache-b`: GVAE_CACHE_DIR): Numba keeps one entry per kernel name and line, so two checkouts whose
kernels differ would otherwise compile them again in every run. A first run of each, not counted,
makes them ready.

    python tools/ab_command.py --a MAIN --b . --cache-b RUNS/cache --runs 3 -- compact IN.ply OUT.ply --keep 0.5
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time


def run_once(tree: str, args: list[str], cache: str | None = None) -> dict:
    """One `python -m gvae_core ARGS` with `tree` first on the path (and GVAE_CACHE_DIR `cache` when
    given): seconds, CPU, peak RSS, last line."""
    env = {**os.environ, "PYTHONPATH": os.path.abspath(tree)}
    if cache:
        env["GVAE_CACHE_DIR"] = os.path.abspath(cache)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()[0]
    t = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "gvae_core", *args], cwd=tree, capture_output=True, text=True,
                          env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"{tree}: exit {done.returncode}: {done.stderr.strip().splitlines()[-1:]}")
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    return {"wall": wall, "cpu": after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime,
            "peak_gib": after.ru_maxrss * 1024 / 2 ** 30, "load": (load, os.getloadavg()[0]),
            "said": lines[-1] if lines else ""}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", required=True, help="checkout A (its root: gvae_core inside)")
    parser.add_argument("--b", required=True, help="checkout B")
    parser.add_argument("--cache-a", default=None, help="GVAE_CACHE_DIR of A's runs (default: as set)")
    parser.add_argument("--cache-b", default=None, help="GVAE_CACHE_DIR of B's runs")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the gvae command and its arguments")
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    rows: dict[str, list[dict]] = {"A": [], "B": []}
    trees = (("A", args.a, args.cache_a), ("B", args.b, args.cache_b))
    for _, tree, cache in trees:  # (the kernels ready, the file in the page cache)
        run_once(tree, command, cache)
    for k in range(args.runs):
        for name, tree, cache in trees:
            r = run_once(tree, command, cache)
            rows[name].append(r)
            print(f"{name} run {k + 1}: wall {r['wall']:.2f} s, CPU {r['cpu']:.2f} s, load {r['load'][0]:.2f} -> "
                  f"{r['load'][1]:.2f} | {r['said'][:150]}", flush=True)
    for name, tree, _ in trees:
        walls, cpus = [r["wall"] for r in rows[name]], [r["cpu"] for r in rows[name]]
        print(f"{name} ({tree}): wall median {statistics.median(walls):.2f} s "
              f"({', '.join(f'{w:.2f}' for w in walls)}), CPU median {statistics.median(cpus):.2f} s "
              f"({', '.join(f'{c:.2f}' for c in cpus)})")
    print("(peak RSS: ru_maxrss of the children, the largest so far, "
          f"{max(r['peak_gib'] for r in rows['A'] + rows['B']):.2f} GiB)")


if __name__ == "__main__":
    main()
