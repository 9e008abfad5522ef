"""Benchmark jaxsync on this machine: MJX vs MuJoCo C throughput, gradient cost,
compile times and tuning-step memory (same as ``jaxsync bench``), e.g.

    python experiments/benchmark.py --out results/bench
    python experiments/benchmark.py --quick --out /tmp/bench   # a smoke test, not a benchmark

Writes bench.json and prints a table; docs/performance.md discusses the numbers.
"""

import sys

from jaxsync.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
