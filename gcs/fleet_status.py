"""`cloudtrack-gcs status --all`: one line per vehicle, from the back-end the vehicles report to.

It asks the back-end (`GET /v1/vehicles`, supervisor token), not the MAVLink link: a GCS hears one link, and
a fleet's vehicles may be on several. A line gives the vehicle id, its mission, the companion's state, the
autopilot's mode, its position, how much of its part the camera has seen (and the POD map's share at the
target POD, where it keeps one) and how long ago it last reported (by the back-end's clock, from its `Date`
header, so a GCS clock that is off does not age a report). Below them, for a vehicle that left its mission's
search with part of its area unflown (the back-end's /dropouts), the re-plan it offers: "REPLAN OFFERED:
drone-3 left the search (mode RTL), 0.03 ha unflown; onto drone-1, drone-2: cloudtrack-gcs replan ...".

The supervisor token is a secret: it is read from a file (--supervisor-token-file, e.g. the one
`cloudtrack-sim up` writes) or from $CLOUDTRACK_GCS_SUPERVISOR_TOKEN, never from the command line (every
user of the machine sees it in `ps`), and never printed; nor is a password in the back-end's URL.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from email.utils import parsedate_to_datetime
from pathlib import Path

import requests
from pydantic import TypeAdapter, ValidationError

from cloudtrack.api_models import VehicleStatus
from cloudtrack.config_files import hide_url_secrets
from cloudtrack.connection_errors import connection_cause
from cloudtrack.plain_text import without_controls

BACKEND_ENV = "CLOUDTRACK_GCS_BACKEND_URL"
TOKEN_ENV = "CLOUDTRACK_GCS_SUPERVISOR_TOKEN"
EXIT_USAGE, EXIT_REFUSED, EXIT_UNREACHABLE = 2, 1, 3
TIMEOUT_S = 10.0
MAX_OFFER_MISSIONS = 16  # missions asked for their drop-outs per `status --all`
SILENT_AFTER_S = 10.0  # a companion reports every [backend] status_interval_s (1 s by default)
_STATUSES = TypeAdapter(list[VehicleStatus])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--all", action="store_true",
        help="one line per vehicle of the back-end (or of --mission), asked of the back-end, not the link",
    )  # fmt: skip
    parser.add_argument(
        "--backend", metavar="URL",
        help=f"with --all: the back-end's address (default: ${BACKEND_ENV})",
    )  # fmt: skip
    parser.add_argument(
        "--supervisor-token-file", type=Path, metavar="PATH",
        help=f"with --all: file holding the back-end's supervisor token (default: ${TOKEN_ENV})",
    )  # fmt: skip
    # A token in argv is visible to every user (ps, /proc/*/cmdline): only there to say so.
    parser.add_argument("--supervisor-token", help=argparse.SUPPRESS)
    parser.add_argument("--mission", metavar="ID", help="with --all: only the vehicles of this mission")
    parser.add_argument(
        "--silent-after", type=float, default=SILENT_AFTER_S, metavar="S",
        help=f"with --all: mark a vehicle SILENT when its last report is older (default {SILENT_AFTER_S:g})",
    )  # fmt: skip


class StatusError(Exception):
    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


def backend_url(args: argparse.Namespace, command: str = "status --all") -> str:
    """The back-end's address for a supervisor's command (`command`, as the operator typed it)."""
    url = (args.backend or os.environ.get(BACKEND_ENV, "")).strip().rstrip("/")
    if not url:
        raise ValueError(
            f"{command} asks the back-end: give its address with --backend URL or ${BACKEND_ENV}"
        )
    if not url.startswith(("http://", "https://")):
        raise ValueError(f"--backend must be an http:// or https:// URL, not {hide_url_secrets(url)!r}")
    return url


def supervisor_token(args: argparse.Namespace, command: str = "status --all") -> str:
    """The supervisor token from a file only its owner reads, or the environment; never the command line."""
    if args.supervisor_token is not None:
        raise ValueError(
            "a token on the command line is visible to every user of this machine (ps, /proc); put the "
            f"supervisor token in a file only you can read (--supervisor-token-file PATH) or in ${TOKEN_ENV}"
        )
    if args.supervisor_token_file is not None:
        try:
            token = str(args.supervisor_token_file.expanduser().read_text()).strip()
        except OSError as exc:
            raise ValueError(
                f"cannot read the supervisor token file {args.supervisor_token_file}: {exc.strerror}"
            ) from None
        if not token:
            raise ValueError(f"the supervisor token file {args.supervisor_token_file} is empty")
        return token
    token = os.environ.get(TOKEN_ENV, "").strip()
    if not token:
        raise ValueError(
            f"{command} needs the back-end's supervisor token: in a file (--supervisor-token-file PATH) "
            f"or in ${TOKEN_ENV}"
        )
    return token


def check_arguments(args: argparse.Namespace) -> None:
    """ValueError for what would stop `status --all` before it asks anything."""
    if not args.all:
        if args.backend or args.supervisor_token_file or args.mission or args.supervisor_token is not None:
            raise ValueError("--backend, --supervisor-token-file and --mission go with status --all")
        return
    backend_url(args)
    supervisor_token(args)


def _text(value: object, limit: int = 64) -> str:
    """Text from the back-end on one line of a terminal: no control character (escape sequences), no break."""
    return " ".join(without_controls(str(value)).split())[:limit] or "-"


def _age(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 120:
        return f"{seconds:.0f} s ago"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min ago"
    return f"{seconds / 3600:.1f} h ago"


def status_line(status: VehicleStatus, now: float, silent_after_s: float = SILENT_AFTER_S) -> str:
    """One vehicle, one line; SILENT at its end when it has not reported for `silent_after_s`."""
    parts = [_text(status.vehicle_id), f"mission {_text(status.mission_id or '-')}", _text(status.state)]
    search = status.search
    parts.append(f"mode {_text(search.mode) if search is not None and search.mode else '-'}")
    if status.position is not None:
        where = f"at {status.position[0]:.6f},{status.position[1]:.6f}"
        if status.altitude_m is not None:
            where += f" {status.altitude_m:.0f} m"
        parts.append(where)
    else:
        parts.append("position unknown")
    if search is not None and search.area:
        share = f"coverage {search.coverage * 100:.0f} %"
        if search.pod is not None:
            pod = search.pod
            share += f", POD >= {pod.target_pod:.2f} on {pod.at_target * 100:.0f} % (mean {pod.mean:.2f})"
        parts.append(share)
    else:
        parts.append("no search area")
    age = now - status.updated_at
    parts.append(f"last report {_age(age)}" + (", SILENT" if age > silent_after_s else ""))
    return "  ".join(parts)


def _server_time(response: requests.Response) -> float:
    """The back-end's clock from its Date header (1 s resolution), else ours."""
    try:
        return parsedate_to_datetime(response.headers["Date"]).timestamp()
    except (KeyError, TypeError, ValueError, IndexError):
        return time.time()


def supervisor_get(url: str, path: str, token: str, timeout_s: float = TIMEOUT_S) -> requests.Response:
    """GET a supervisor's route of the back-end; StatusError with one line for a person when it does not
    answer, cannot be reached or refuses (its own words), never with the token or a password of the URL."""
    shown = hide_url_secrets(url)
    try:
        response = requests.get(
            f"{url}{path}", headers={"Authorization": f"Bearer {token}"}, timeout=timeout_s
        )
    except requests.Timeout:
        raise StatusError(f"back-end {shown}: no answer within {timeout_s:g} s", EXIT_UNREACHABLE) from None
    except requests.RequestException as exc:
        raise StatusError(
            f"back-end {shown} unreachable: {connection_cause(exc)}", EXIT_UNREACHABLE
        ) from None
    if response.status_code >= 400:
        try:
            detail = response.json().get("detail", "")
        except (ValueError, AttributeError):
            detail = ""
        detail = _text(detail if isinstance(detail, str) else "", 200)
        why = {401: "refused the supervisor token", 403: "refused the supervisor token"}.get(
            response.status_code, "refused the request"
        )
        code = EXIT_UNREACHABLE if response.status_code >= 500 else EXIT_REFUSED
        raise StatusError(f"back-end {shown} {why} (HTTP {response.status_code}): {detail}", code)
    return response


def fetch(url: str, token: str, timeout_s: float = TIMEOUT_S) -> tuple[list[VehicleStatus], float]:
    """Every vehicle's last status and the back-end's time; StatusError with a line for a person."""
    shown = hide_url_secrets(url)
    response = supervisor_get(url, "/v1/vehicles", token, timeout_s)
    try:
        statuses = _STATUSES.validate_json(response.content)
    except ValidationError as exc:
        problem = exc.errors()[0]
        where = ".".join(map(str, problem["loc"]))
        raise StatusError(
            f"back-end {shown}: its answer is not a list of vehicle statuses ({where}: {problem['msg']}); "
            "is this the CloudTrack back-end, and of the same version?",
            EXIT_UNREACHABLE,
        ) from None
    return statuses, _server_time(response)


def run_all(args: argparse.Namespace) -> int:
    url = backend_url(args)
    try:
        statuses, now = fetch(url, supervisor_token(args), timeout_s=args.timeout)
    except StatusError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return exc.code
    if args.mission is not None:
        statuses = [s for s in statuses if s.mission_id == args.mission]
    if not statuses:
        which = f" in mission {_text(args.mission)}" if args.mission is not None else ""
        print(f"no vehicle{which} has reported to {hide_url_secrets(url)}", flush=True)
        return 0
    for status in sorted(statuses, key=lambda s: s.vehicle_id):
        print(status_line(status, now, args.silent_after), flush=True)
    for line in replan_offers(url, supervisor_token(args), statuses, args.timeout):
        print(line, flush=True)
    return 0


def replan_offers(url: str, token: str, statuses: list[VehicleStatus], timeout_s: float) -> list[str]:
    """The GCS offers the re-plan: for each mission of these vehicles, a line per vehicle that left its
    search with part of its area unflown (the back-end's /dropouts), naming the vehicles it would go onto
    and the command that does it. A mission the back-end has no map of offers nothing."""
    from gcs.fleet_replan import ReplanError, fetch_dropouts  # replan builds on this module

    lines = []
    for mission in sorted({s.mission_id for s in statuses if s.mission_id})[:MAX_OFFER_MISSIONS]:
        try:
            answer = fetch_dropouts(url, token, mission, timeout_s)
        except ReplanError:
            continue
        for dropout in answer.dropouts:
            if not dropout.area_known:
                lines.append(
                    f"DROPPED OUT: {_text(dropout.vehicle_id)} left the search ({_text(dropout.reason)}); its part "
                    "of the area is unknown (it reported none): what it left unflown is not known"
                )
                continue
            if dropout.area_m2 <= 0:
                continue
            onto = ", ".join(_text(v) for v in answer.searching) or "no vehicle still searching"
            lines.append(
                f"REPLAN OFFERED: {_text(dropout.vehicle_id)} left the search ({_text(dropout.reason)}), "
                f"{dropout.area_m2 / 1e4:.2f} ha unflown; onto {onto}: cloudtrack-gcs replan --mission "
                f"{shlex.quote(_text(mission))} --fleet FLEET_FILE --altitude SURVEY_ALTITUDE"
            )
    return lines
