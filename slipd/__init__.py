"""slipd: incipient-slip detection for the Contactile PapillArray.

The runtime (daemon, replay, features, ONNX ensemble) depends on numpy and onnxruntime only;
torch is used by the offline training tools alone.
"""

__version__ = "0.1.0"
