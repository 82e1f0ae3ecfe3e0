"""Copy a folder of recordings with Gaussian noise added to the pillar tip displacements.

A launcher: the code lives in ``slipd.lab.noisy_displacements`` (the offline lab; ``pip install -e '.[train]'``).
"""

from slipd.lab.noisy_displacements import main

if __name__ == "__main__":
    raise SystemExit(main())
