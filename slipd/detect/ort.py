"""onnxruntime, loaded with its telemetry off: import it from here, never directly.

onnxruntime (1.32 on Linux) writes a device id and an events database under ``~/.cache/Microsoft/DeveloperTools`` for
every session unless ``ORT_DISABLE_TELEMETRY`` is set before the library loads; ``disable_telemetry_events()`` after
the import does not stop those writes. A daemon under ``ProtectHome=`` has no home to write to, and a replay on a
laptop should leave none behind. A value already in the environment is kept.
"""

import os

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

import onnxruntime as onnxruntime  # after the variable above: the library reads it as it loads

__all__ = ["onnxruntime"]
