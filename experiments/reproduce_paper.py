"""Reproduce the paper's comparison (section 5): classical vs synchronous control.

Thin wrapper over ``jaxsync compare`` (same options), e.g.

    python experiments/reproduce_paper.py --out results/paper
    python experiments/reproduce_paper.py --object-mass 0.8 --out results/paper_heavy
"""

import sys

from jaxsync.cli import main

if __name__ == "__main__":
    sys.exit(main(["compare", *sys.argv[1:]]))
