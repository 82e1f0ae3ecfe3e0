"""Export a SlipNet ensemble as ONE fused ONNX graph plus its manifest.

A launcher: the code lives in ``sliplab.export`` (the offline lab; ``pip install -e '.[train]'``).
"""

from sliplab.export import main

if __name__ == "__main__":
    raise SystemExit(main())
