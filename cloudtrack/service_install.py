"""Install a CloudTrack process under systemd: its unit and an example configuration.

Shared by `cloudtrack-companion service install` and `cloudtrack-backend service install`. The units
(`config/`, shipped in the package as `cloudtrack/systemd/`) name /opt/cloudtrack/venv; the installer
rewrites ExecStart to the program that is actually installed (the one running the command) so the unit
works for any install location. An existing configuration file is never overwritten without `--force`:
it is the operator's.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

# The units and default configurations, shipped inside the package (links to config/ in the source tree,
# copied into wheels) so `service install` works from any install, not only from a checkout.
TEMPLATE_DIR = Path(__file__).resolve().parent / "systemd"


@dataclass(frozen=True)
class ServiceFiles:
    """What `install` writes: the unit and the example configuration, as (path, text)."""

    unit_path: Path
    unit_text: str
    config_path: Path
    config_text: str


def _program_path(program: str) -> str:
    """The installed console script beside this interpreter, else on PATH, else the bare name."""
    beside = Path(sys.executable).parent / program
    if beside.is_file():
        return str(beside)
    return shutil.which(program) or program


def render_unit(template: str, program: str, config_path: Path) -> str:
    """The unit with ExecStart naming the installed program and the configuration file."""
    lines = []
    for line in template.splitlines():
        if line.startswith("ExecStart="):
            words = line[len("ExecStart=") :].split()
            # Keep the subcommand (run / serve), replace the program and the --config argument.
            subcommand = words[1] if len(words) > 1 else "run"
            line = f"ExecStart={_program_path(program)} {subcommand} --config {config_path}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def _example_config(defaults: str, backend: bool) -> str:
    header = (
        "# Example configuration written by `cloudtrack-companion service install`.\n"
        "# Secrets go in the .env file beside it (mode 0640), not here.\n"
    )
    if backend:
        return header + defaults
    # On the vehicle the autopilot is on the Pi's UART wired to TELEM2 (docs/operations.md). Records need no
    # rewrite: an empty [recording] dir means $STATE_DIRECTORY/records, which the unit's StateDirectory= sets.
    loopback = 'connection = "udpin:127.0.0.1:14540"'
    if loopback not in defaults:
        raise ValueError(f"the companion's default configuration no longer holds {loopback!r}")
    return header + defaults.replace(loopback, 'connection = "/dev/ttyAMA0,921600"', 1)


def service_files(unit_dir: Path, config_dir: Path, backend: bool) -> ServiceFiles:
    name = "backend" if backend else "companion"
    template = (TEMPLATE_DIR / f"cloudtrack-{name}.service").read_text()
    defaults = (TEMPLATE_DIR / f"{name}.toml").read_text()
    config_path = config_dir / f"{name}.toml"
    return ServiceFiles(
        unit_path=unit_dir / f"cloudtrack-{name}.service",
        unit_text=render_unit(template, f"cloudtrack-{name}", config_path),
        config_path=config_path,
        config_text=_example_config(defaults, backend),
    )


def install(args: argparse.Namespace) -> int:
    """Write (or with `print_only`, print) the unit and the example configuration; the exit status."""
    try:
        files = service_files(args.unit_dir, args.config_dir, args.backend)
    except OSError as exc:
        print(f"error: cannot read the unit template: {exc}", file=sys.stderr)
        return 1
    if args.print_only:
        print(f"# {files.unit_path}\n{files.unit_text}\n# {files.config_path}\n{files.config_text}")
        return 0
    try:
        files.unit_path.parent.mkdir(parents=True, exist_ok=True)
        files.unit_path.write_text(files.unit_text)
        print(f"wrote {files.unit_path}")
        if files.config_path.exists() and not args.force:
            print(f"kept {files.config_path} (exists; --force overwrites it)")
        else:
            files.config_path.parent.mkdir(parents=True, exist_ok=True)
            files.config_path.write_text(files.config_text)
            print(f"wrote {files.config_path}")
    except OSError as exc:
        print(f"error: {exc} (run as root for /etc, or pass --unit-dir/--config-dir)", file=sys.stderr)
        return 1
    unit = files.unit_path.stem
    print(f"next: systemctl daemon-reload && systemctl enable --now {unit}  (see docs/operations.md)")
    return 0


def add_install_parser(
    subparsers: argparse._SubParsersAction,  # type: ignore[type-arg]
    *,
    help: str,
    description: str,
    examples: str,
    config_name: str,
) -> argparse.ArgumentParser:
    """`service install` for one process's command line: the flags both processes share; the caller
    adds its own and sets defaults on the returned parser."""
    parser = subparsers.add_parser(
        "service",
        help=help,
        description=description,
        epilog=examples,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    parser_install: argparse.ArgumentParser = actions.add_parser(
        "install",
        help="write the unit and an example configuration (or print them with --print)",
        epilog=examples,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser_install.add_argument(
        "--print", dest="print_only", action="store_true", help="print, write nothing"
    )
    parser_install.add_argument(
        "--unit-dir",
        type=Path,
        default=Path("/etc/systemd/system"),
        help="where the unit goes (default /etc/systemd/system)",
    )
    parser_install.add_argument(
        "--config-dir",
        type=Path,
        default=Path("/etc/cloudtrack"),
        help=f"where {config_name} goes (default /etc/cloudtrack)",
    )
    parser_install.add_argument(
        "--force", action="store_true", help="overwrite an existing configuration file"
    )
    parser_install.set_defaults(func=install)
    return parser_install
