"""Tune the synchronous controller's gains by gradient (thin wrapper over ``jaxsync tune``).

python experiments/tune_gains.py --iterations 60 --out results/tune
"""

import sys

from jaxsync.cli import main

if __name__ == "__main__":
    sys.exit(main(["tune", *sys.argv[1:]]))
