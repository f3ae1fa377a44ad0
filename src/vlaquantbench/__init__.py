"""VLAQuantBench: closed-loop evaluation of post-training quantization for VLA policies."""


def __getattr__(name: str) -> str:
    # The version is looked up on first use (PEP 562): importlib.metadata costs every workflow job ~0.1 s of
    # start-up, and only `vqb --version` asks for it.
    if name != "__version__":
        raise AttributeError(f"module 'vlaquantbench' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("vlaquantbench")
    except PackageNotFoundError:  # running from a source tree that was never installed
        return "0.0.0+unknown"
