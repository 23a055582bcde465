"""`cloudtrack-companion models list|verify|download`: the weight files in the model directory."""

from __future__ import annotations

import argparse
import sys

from cloudtrack.model_store import (
    MODEL_DIR_HELP,
    REGISTRY,
    FileStatus,
    ModelError,
    download,
    file_status,
    resolve_model_dir,
)


def add_model_dir_flag(parser: argparse.ArgumentParser) -> None:
    """The one --model-dir flag every command that loads weights takes (same name, same help, same default)."""
    parser.add_argument("--model-dir", metavar="DIR", help=MODEL_DIR_HELP)


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "models",
        help="list, verify or download model weights",
        epilog="examples:\n  cloudtrack-companion models list --model-dir ../shared/models\n"
        "  cloudtrack-companion models download nano\n  cloudtrack-companion models verify",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    for name, func, text in (
        ("list", _list, "show every known model and the state of its files"),
        ("verify", _verify, "exit non-zero unless every non-user-supplied model is present and verified"),
    ):
        sub = actions.add_parser(name, help=text)
        add_model_dir_flag(sub)
        sub.set_defaults(func=func)
    dl = actions.add_parser(
        "download", help="fetch NAME from its upstream URL, verify sha256, install atomically"
    )
    dl.add_argument("name", choices=sorted(REGISTRY))
    add_model_dir_flag(dl)
    dl.set_defaults(func=_download)


def _report(args: argparse.Namespace, required_only: bool) -> int:
    model_dir = resolve_model_dir(args.model_dir)
    print(f"model directory: {model_dir}")
    bad = 0
    for spec in REGISTRY.values():
        statuses = [(mf, file_status(model_dir, mf)) for mf in spec.files]
        origin = "user-supplied" if spec.user_supplied else "downloadable"
        for mf, status in statuses:
            print(f"  {spec.name:<12} {origin:<13} {status.value:<38} {model_dir / mf.relpath}")
            if (
                status is FileStatus.CORRUPT
                or status is FileStatus.MISSING
                and required_only
                and not spec.user_supplied
            ):
                bad += 1
        if any(s is FileStatus.CORRUPT for _, s in statuses) or (
            required_only and not spec.user_supplied and any(s is FileStatus.MISSING for _, s in statuses)
        ):
            print(f"    fix: cloudtrack-companion models download {spec.name} --model-dir {model_dir}")
    user = ", ".join(spec.name for spec in REGISTRY.values() if spec.user_supplied)
    print(
        f"user-supplied ({user}): large, no stable checksum upstream; you place their files "
        "(README, 'Model weights')"
    )
    return 1 if bad else 0


def _list(args: argparse.Namespace) -> int:
    return _report(args, required_only=False)


def _verify(args: argparse.Namespace) -> int:
    return _report(args, required_only=True)


def _download(args: argparse.Namespace) -> int:
    model_dir = resolve_model_dir(args.model_dir)
    try:
        written = download(args.name, model_dir)
    except (ModelError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # anything else from requests: report, do not trace back
        print(f"error: download of {args.name} failed: {exc}", file=sys.stderr)
        return 1
    for path in written:
        print(f"installed {path}")
    if not written:
        print(f"{args.name}: already present and verified in {model_dir}")
    return 0
