"""Infrastructure shared by every CloudTrack process: configuration files, logging, the model store."""

__version__ = "0.1.0"


def init(mpstate: object) -> object:
    """MAVProxy's entry point for `module load cloudtrack` (companion/mavproxy_cloudtrack.py)."""
    from companion.mavproxy_cloudtrack import init as load

    return load(mpstate)
