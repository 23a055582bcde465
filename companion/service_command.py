"""`cloudtrack-companion service install`: write the systemd unit and an example configuration.

The installer itself is `cloudtrack.service_install`, shared with `cloudtrack-backend service install`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cloudtrack import service_install

EXAMPLES = """\
examples:
  sudo cloudtrack-companion service install                 # /etc/systemd/system + /etc/cloudtrack
  cloudtrack-companion service install --print              # show what would be written
  sudo cloudtrack-companion service install --backend       # the back-end's unit on the server
  cloudtrack-companion service install --unit-dir out/units --config-dir out/etc
then:
  sudo useradd --system --home /var/lib/cloudtrack --shell /usr/sbin/nologin cloudtrack
  sudo systemctl daemon-reload && sudo systemctl enable --now cloudtrack-companion
  journalctl -u cloudtrack-companion -f
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "service",
        help="install the systemd unit and an example configuration",
        description="Run CloudTrack under systemd (Type=notify, watchdog, restart on failure).",
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
        "--backend", action="store_true", help="the back-end's unit instead of the companion's"
    )
    install.add_argument("--unit-dir", type=Path, default=Path("/etc/systemd/system"))
    install.add_argument("--config-dir", type=Path, default=Path("/etc/cloudtrack"))
    install.add_argument("--force", action="store_true", help="overwrite an existing configuration file")
    install.set_defaults(func=service_install.install)
