"""Copy a folder of recordings with Gaussian noise added to the pillar tip displacements.

A launcher: the code lives in ``sliplab.noisy_displacements`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.noisy_displacements import main

if __name__ == "__main__":
    raise SystemExit(main())
