"""How do k_rk and k_lk trade resultant force against grip error across object
masses? A grid sweep (same as ``jaxsync sweep``); with no arguments it runs

    --param k_rk=-1:1:11 --param k_lk=-1:1:11 --param object_mass=0.5,1,2 --out results/sweep_gains

(363 rollouts of 4 s). Any ``jaxsync sweep`` option may be given instead, e.g.

    python experiments/sweep_gains.py --param k_rk=-1:1:5 --param k_lk=-1:1:5 --out results/sweep_small

The heatmap (heatmap.png) averages over the object masses; results.csv has every point.
"""

import sys

from jaxsync.cli import main

DEFAULT = [
    "--param",
    "k_rk=-1:1:11",
    "--param",
    "k_lk=-1:1:11",
    "--param",
    "object_mass=0.5,1,2",
    "--out",
    "results/sweep_gains",
]

if __name__ == "__main__":
    sys.exit(main(["sweep", *(sys.argv[1:] or DEFAULT)]))
