"""Infrastructure shared by every CloudTrack process: configuration files, logging, the model store, the
back-end API's models and its HTTP client, sd_notify and the systemd installer. It may use the pure core's
value types (`behaviors`) and never imports a process package (`companion`, `backend`, `sitl`)."""

__version__ = "0.1.0"


def init(mpstate: object) -> object:
    """MAVProxy's entry point for `module load cloudtrack` (gcs/mavproxy_cloudtrack.py)."""
    from gcs.mavproxy_cloudtrack import init as load

    return load(mpstate)
