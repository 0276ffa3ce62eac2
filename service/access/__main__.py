"""``python -m service.access``: manage the keys of an FFS_API_KEYS_FILE.

    python -m service.access add alice --file keys.json [--role admin]
        [--requests-per-minute N] [--concurrent-jobs N] [--concurrent-sessions N]
        [--max-faces N]
    python -m service.access list --file keys.json

``add`` prints the new key and its webhook secret once, on stdout; the file keeps only the
key's SHA-256 (and the webhook secret, which the service needs to sign). ``--file``
defaults to FFS_API_KEYS_FILE. The service reads the file when it starts.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from service.access.keys import ROLES, KeyLimits, add_key, read_keys_file


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m service.access",
                                     description="Manage the API keys of FFS_API_KEYS_FILE.")
    commands = parser.add_subparsers(dest="command", required=True)
    add = commands.add_parser("add", help="create a key; it is printed once")
    add.add_argument("name", help="the key's name (metrics, ownership, logs)")
    add.add_argument("--role", choices=ROLES, default="user")
    for option in ("requests-per-minute", "concurrent-jobs", "concurrent-sessions",
                   "max-faces"):
        add.add_argument(f"--{option}", type=int, default=None, metavar="N",
                         help=f"this key's {option.replace('-', ' ')} (default: FFS_KEY_*)")
    listing = commands.add_parser("list", help="the keys' names, roles and limits")
    for command in (add, listing):
        command.add_argument("--file", type=Path, default=os.environ.get("FFS_API_KEYS_FILE"),
                             help="the keys file (default FFS_API_KEYS_FILE)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.file is None:
        print("python -m service.access: give --file or set FFS_API_KEYS_FILE", file=sys.stderr)
        return 2
    path = Path(args.file)
    if args.command == "list":
        try:
            document = read_keys_file(path)
        except ValueError as exc:
            print(f"python -m service.access: {exc}", file=sys.stderr)
            return 1
        for entry in document["keys"]:
            print(entry["name"], entry.get("role", "user"),
                  json.dumps(entry.get("limits", {})))
        return 0
    try:
        limits = KeyLimits(args.requests_per_minute, args.concurrent_jobs,
                           args.concurrent_sessions, args.max_faces)
        key, secret = add_key(path, args.name, args.role, limits)
    except ValueError as exc:
        print(f"python -m service.access: {exc}", file=sys.stderr)
        return 1
    print(f"key for {args.name!r} ({args.role}), shown only now:\n{key}\n"
          f"webhook secret (X-FFS-Signature of its jobs' callbacks):\n{secret}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
