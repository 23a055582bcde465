"""`cloudtrack-companion service install`: write the systemd unit and an example configuration.

The installer itself is `cloudtrack.service_install`, shared with `cloudtrack-backend service install`.
"""

from __future__ import annotations

import argparse

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
    install = service_install.add_install_parser(
        subparsers,
        help="install the systemd unit and an example configuration",
        description="Run CloudTrack under systemd (Type=notify, watchdog, restart on failure).",
        examples=EXAMPLES,
        config_name="companion.toml (backend.toml with --backend)",
    )
    install.add_argument(
        "--backend", action="store_true", help="the back-end's unit instead of the companion's"
    )
