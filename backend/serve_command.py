"""`cloudtrack-backend serve`: run the HTTP service."""

from __future__ import annotations

import argparse
import json
import logging
import sys

from cloudtrack.config_files import ConfigError
from cloudtrack.model_store import MODEL_DIR_HELP, ModelError

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from backend.cli import add_config_flags

    parser = subparsers.add_parser(
        "serve",
        help="run the HTTP service (OpenAPI docs at /docs)",
        description="Serve POST /v1/detect, /health, /v1/models and the session endpoints. TLS: put a reverse "
        "proxy in front (docs/backend.md).",
        epilog="examples:\n  cloudtrack-backend serve --config /etc/cloudtrack/backend.toml\n"
        "  cloudtrack-backend serve --set verifier.kind=vlm --set vlm.base_url=http://gpu:11434/v1 "
        "--set vlm.model=llava:13b\n"
        "  CLOUDTRACK_BACKEND_SERVER__PORT=9000 cloudtrack-backend serve",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--model-dir", metavar="DIR", help=MODEL_DIR_HELP)
    add_config_flags(parser)
    parser.set_defaults(func=_serve)


def _serve(args: argparse.Namespace) -> int:
    from backend.app import create_app
    from backend.cli import config_from_args
    from backend.serving import serve

    try:
        extra = [f"detector.model_dir={json.dumps(args.model_dir)}"] if args.model_dir else []
        config = config_from_args(args, *extra)
        app = create_app(config)
    except (ConfigError, ModelError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not config.auth.tokens:
        log.warning("no vehicle tokens configured ([auth] tokens): every /v1/detect request will get 401")
    log.info(
        "serving on http://%s:%d (detector %s, verifier %s)",
        config.server.host,
        config.server.port,
        app.state.pipeline.detector.name,
        app.state.pipeline.verifier_name,
    )
    serve(app, config.server.host, config.server.port, args.log_level)
    return 0
