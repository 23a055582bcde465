"""`cloudtrack-backend service install`: the back-end's systemd unit and example configuration.

The same installer as `cloudtrack-companion service install --backend` (which keeps working): the unit
from the package with ExecStart naming this install's `cloudtrack-backend`, and /etc/cloudtrack/backend.toml
unless it exists (`--force` overwrites it). Under the unit the SQLite session store lives in
$STATE_DIRECTORY (/var/lib/cloudtrack).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cloudtrack import service_install

EXAMPLES = """\
examples:
  sudo cloudtrack-backend service install                   # /etc/systemd/system + /etc/cloudtrack
  cloudtrack-backend service install --print                # show what would be written
  cloudtrack-backend service install --unit-dir out/units --config-dir out/etc
then:
  sudo useradd --system --home /var/lib/cloudtrack --shell /usr/sbin/nologin cloudtrack
  echo "CLOUDTRACK_BACKEND_AUTH__SUPERVISOR_TOKEN=$(openssl rand -hex 24)" | sudo tee /etc/cloudtrack/backend.env
  sudo systemctl daemon-reload && sudo systemctl enable --now cloudtrack-backend
  journalctl -u cloudtrack-backend -f
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "service",
        help="install the back-end's systemd unit and an example configuration",
        description="Run the back-end under systemd (Type=notify, watchdog, restart on failure).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    install = actions.add_parser(
        "install",
        help="write the unit and an example configuration (or print them with --print)",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    install.add_argument("--print", dest="print_only", action="store_true", help="print, write nothing")
    install.add_argument(
        "--unit-dir",
        type=Path,
        default=Path("/etc/systemd/system"),
        help="where the unit goes (default /etc/systemd/system)",
    )
    install.add_argument(
        "--config-dir",
        type=Path,
        default=Path("/etc/cloudtrack"),
        help="where backend.toml goes (default /etc/cloudtrack)",
    )
    install.add_argument("--force", action="store_true", help="overwrite an existing configuration file")
    install.set_defaults(func=service_install.install, backend=True)  # one installer for both units
