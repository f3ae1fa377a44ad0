"""VLAQuantBench: closed-loop evaluation of post-training quantization for VLA policies."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("vlaquantbench")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
