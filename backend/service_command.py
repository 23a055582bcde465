"""`cloudtrack-backend service install`: the back-end's systemd unit and example configuration.

The same installer as `cloudtrack-companion service install --backend` (which keeps working): the unit
from the package with ExecStart naming this install's `cloudtrack-backend`, and /etc/cloudtrack/backend.toml
unless it exists (`--force` overwrites it). Under the unit the SQLite session store lives in
$STATE_DIRECTORY (/var/lib/cloudtrack).
"""

from __future__ import annotations

import argparse

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
    install = service_install.add_install_parser(
        subparsers,
        help="install the back-end's systemd unit and an example configuration",
        description="Run the back-end under systemd (Type=notify, watchdog, restart on failure).",
        examples=EXAMPLES,
        config_name="backend.toml",
    )
    install.set_defaults(backend=True)  # one installer for both units
