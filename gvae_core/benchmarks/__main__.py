"""Run the benchmarks: all of them, or the ones named on the command line."""

import argparse
import importlib
import os
import platform
import time

from . import BENCHMARKS


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks")
    parser.add_argument("names", nargs="*",
                        help=f"benchmarks to run (default: all of {', '.join(BENCHMARKS)})")
    parser.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke run")
    args = parser.parse_args()
    names = args.names or list(BENCHMARKS)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        parser.error(f"unknown benchmark(s) {unknown}; choose from {list(BENCHMARKS)}")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {load:.2f} at start")
    for name in names:
        start = time.perf_counter()
        print(f"\n## {name}")
        importlib.import_module(f"{__package__}.{name}").run(args)
        print(f"({name}: {time.perf_counter() - start:.1f} s in all)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
