"""Bus sub-commands: ``psm record``, ``psm replay``, ``psm info``, ``psm export``, ``psm echo``,
``psm secrets``, ``psm serve router``.

Other modules add their own ``psm serve <target>`` with :func:`serve_targets`::

    def register(subparsers):
        from services.bus.cli import serve_targets
        p = serve_targets(subparsers).add_parser("arm", help="simulated arm")
        p.set_defaults(func=run_arm)

Errors are not handled here: they reach :func:`services.cli.dispatch`, which prints one line
(``psm <command>: error: <message>``) and exits with code 2.

Every command that joins the bus takes the common bus flags (``--config``, ``--prefix``, ``--mode``,
``--connect``, ``--listen``, ``--[no-]multicast``, ``--set PATH=VALUE``; see
:mod:`services.bus.config`). Heavy imports (zenoh, mcap) happen inside the command functions.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

__all__ = ["register", "serve_targets"]

_SERVE_TARGETS = "_psm_serve_targets"


def serve_targets(subparsers: Any) -> Any:
    """The sub-parsers action of ``psm serve`` (created on first use), to add targets to."""
    serve = subparsers.choices.get("serve")
    if serve is None:
        serve = subparsers.add_parser(
            "serve", help="run a long-lived bus service (router, ...)",
            description="Run a long-lived bus service until SIGINT/SIGTERM.",
        )
        targets = serve.add_subparsers(dest="target", metavar="TARGET", required=True)
        setattr(serve, _SERVE_TARGETS, targets)
    return getattr(serve, _SERVE_TARGETS)


def _cmd_record(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.bus.recorder import RecorderConfig, run_recorder

    extra = {
        "recorder.output": args.output,
        "recorder.key_exprs": args.key_expr,
        "recorder.split_size_mb": args.split_size_mb,
        "recorder.split_duration_s": args.split_duration_s,
        "recorder.chunk_size": args.chunk_size,
        "recorder.overwrite": True if args.overwrite else None,
        "recorder.history": args.history,
    }
    return run_recorder(config_from_args(RecorderConfig, args, extra))


def _cmd_replay(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.bus.replayer import ReplayerConfig, run_replayer

    extra = {
        "replayer.files": args.files,
        "replayer.speed": args.speed,
        "replayer.as_fast_as_possible": True if args.as_fast_as_possible else None,
        "replayer.topics": args.topics,
        "replayer.exclude": args.exclude,
        "replayer.remap_prefix": args.remap_prefix,
        "replayer.loop": True if args.loop else None,
        "replayer.wait_subscribers_s": args.wait_subscribers,
    }
    return run_replayer(config_from_args(ReplayerConfig, args, extra),
                        include_commands=args.include_commands, force=args.force)


def _cmd_info(args: argparse.Namespace) -> int:
    from services.bus.info import run_info

    return run_info(args.file, as_json=args.json)


def _cmd_export(args: argparse.Namespace) -> int:
    from pathlib import Path

    from services.bus.export import export_topic, write_csv, write_npz
    from services.cli import CLIError

    src = Path(args.file)
    outs = [(Path(o), w) for o, w in ((args.csv, write_csv), (args.npz, write_npz)) if o]
    if not outs:
        raise CLIError("nothing to write: give --csv OUT.csv and/or --npz OUT.npz")
    for out, _ in outs:
        if out.is_file() and src.exists() and out.samefile(src):
            raise CLIError(f"{out}: is the input recording; choose another output file")
    fields = None
    if args.fields is not None:
        fields = [f.strip() for f in args.fields.split(",") if f.strip()]
        if not fields:
            raise CLIError("--fields: expected a comma-separated list of field names")
    table = export_topic(src, args.topic, fields=fields, start_s=args.start, end_s=args.end)
    if table.problem:
        print(f"psm export: warning: {src}: {table.problem}", file=sys.stderr)
    if table.skipped:
        print(f"psm export: warning: {table.skipped} messages on {table.topic} did not decode "
              "and were skipped", file=sys.stderr)
    if table.left_out:
        left = "; ".join(f"{f} ({why})" for f, why in table.left_out.items())
        print(f"psm export: left out: {left}", file=sys.stderr)
    for out, write in outs:
        write(table, out)
        print(f"wrote {out}: {table.rows} rows x {len(table.columns)} columns "
              f"({table.topic}, {table.schema})",
              file=sys.stdout if out.is_file() else sys.stderr)  # not among data on stdout
    return 0


def _cmd_echo(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.bus.echo import EchoConfig, run_echo

    extra = {"echo.key_exprs": args.key_exprs or None,
             "echo.quiet": True if args.quiet else None}
    return run_echo(config_from_args(EchoConfig, args, extra))


def _cmd_router(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.bus.router import RouterConfig, run_router

    listen, args.listen = args.listen, None
    return run_router(config_from_args(RouterConfig, args, {"router.listen": listen}))


def _cmd_secrets(args: argparse.Namespace) -> int:
    from services.bus.credentials import write_secrets

    owner = None
    if args.owner:
        uid, _, gid = args.owner.partition(":")
        if not uid.isdigit() or not (gid or uid).isdigit():
            raise ValueError(f"--owner: expected UID[:GID], got {args.owner!r}")
        owner = (int(uid), int(gid or uid))
    result = write_secrets(args.out_dir, args.roles, force=args.force, owner=owner)
    for path in result.written:
        print(f"wrote {path}")
    for path in result.kept:
        print(f"kept {path}")
    return 0


def register(subparsers: Any) -> None:
    """Add ``record``, ``replay``, ``info``, ``export``, ``echo``, ``secrets`` and ``serve
    router`` to the ``psm`` command line."""
    from services.bus.config import add_config_arguments

    p = subparsers.add_parser(
        "record", help="record bus traffic to MCAP",
        description="Subscribe to <prefix>/** and write every sample, bytes unchanged, to MCAP. "
        "SIGINT/SIGTERM finalise the file.",
    )
    p.add_argument("-o", "--output", help="output .mcap (default out/recording-<time>.mcap)")
    p.add_argument("-k", "--key-expr", action="append",
                   help="key expression to record (repeatable; default <prefix>/**)")
    p.add_argument("--split-size-mb", type=float, help="start a new file every N MB")
    p.add_argument("--split-duration-s", type=float, help="start a new file every N seconds")
    p.add_argument("--chunk-size", type=int, help="MCAP chunk size, bytes")
    p.add_argument("--overwrite", action="store_true", help="overwrite an existing file")
    p.add_argument("--history", action=argparse.BooleanOptionalAction, default=None,
                   help="fetch late-joiner history at start (default on)")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_record)

    p = subparsers.add_parser(
        "replay", help="republish an MCAP recording on the bus",
        description="Republish every message with the same key, bytes and encoding, "
        "preserving the recorded timing.",
    )
    p.add_argument("files", nargs="+", metavar="FILE.mcap")
    p.add_argument("--speed", type=float, help="time scale (default 1)")
    p.add_argument("--as-fast-as-possible", action="store_true", help="ignore recorded timing")
    p.add_argument("--topics", nargs="+", metavar="KEYEXPR", help="only these key expressions")
    p.add_argument("--exclude", nargs="+", metavar="KEYEXPR", help="drop these key expressions")
    p.add_argument("--remap-prefix", metavar="OLD=NEW", help="move keys to another prefix")
    p.add_argument("--loop", action="store_true", help="repeat until stopped")
    p.add_argument("--wait-subscribers", type=float, metavar="SECONDS",
                   help="wait up to SECONDS for a matching subscriber before sending")
    p.add_argument("--include-commands", action="store_true",
                   help="also replay command streams (<prefix>/arm/command); refused while "
                   "an arm is alive on the target prefix")
    p.add_argument("--force", action="store_true",
                   help="with --include-commands: replay commands even to a live arm")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_replay)

    p = subparsers.add_parser(
        "info", help="what an MCAP recording holds (topics, counts, rates, metadata)",
        description="Read FILE.mcap once (checking every chunk) and print its size, duration, "
        "start and end, message count, per channel the schema, encoding, count, mean rate and "
        "bandwidth, its metadata records and attachments. A truncated or corrupt file is "
        "described up to where it stops being readable, with one warning line on stderr "
        "(exit code 0); a file that is not MCAP or has no readable message is an error "
        "(exit code 2).",
    )
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument("--json", action="store_true", help="print one JSON object instead")
    p.set_defaults(func=_cmd_info)

    p = subparsers.add_parser(
        "export", help="one recorded topic as CSV or NPZ columns",
        description="Decode every message of one topic with the protobuf schema stored in "
        "FILE.mcap and write its fields as columns: log_time_ns, publish_time_ns, t_s (s since "
        "the recording's first message), then nested fields as dotted names (pose.position.x) "
        "and fixed-length repeated fields as indexed ones (q.0 ... q.6). Bytes fields and "
        "repeated fields of varying length are left out and listed on stderr.",
    )
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument("--topic", required=True, metavar="KEY", help="the recorded key, e.g. "
                   "psm/arm/state (psm info lists them)")
    p.add_argument("--csv", metavar="OUT.csv",
                   help="write a CSV file (header row of columns; - for stdout)")
    p.add_argument("--npz", metavar="OUT.npz", help="write an NPZ file (one array per column)")
    p.add_argument("--fields", metavar="A,B,...",
                   help="only these fields (a column, or a field whose columns to take: q, "
                   "pose.position); the time columns are always written")
    p.add_argument("--start", type=float, metavar="SECONDS",
                   help="only messages from this time on (s since the recording's start)")
    p.add_argument("--end", type=float, metavar="SECONDS",
                   help="only messages up to this time (s since the recording's start)")
    p.set_defaults(func=_cmd_export)

    p = subparsers.add_parser(
        "echo", help="print and check bus messages",
        description="Print every message (decoded) and count malformed ones as rejected.",
    )
    p.add_argument("key_exprs", nargs="*", metavar="KEYEXPR", help="default <prefix>/**")
    p.add_argument("-q", "--quiet", action="store_true", help="only count and check")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_echo)

    from services.bus.acl import ROLE_NAMES

    p = subparsers.add_parser(
        "secrets", help="write the bus credentials of the roles (access control)",
        description="Write OUT_DIR/<role>.password (random, mode 0600) for each role and "
        "OUT_DIR/users.txt, the router's user/password dictionary (docs/security.md). Existing "
        "password files are kept unless --force.",
    )
    p.add_argument("out_dir", metavar="OUT_DIR", help="directory of the secret files")
    p.add_argument("--roles", nargs="+", metavar="ROLE", choices=ROLE_NAMES,
                   help=f"only these roles (default all: {', '.join(ROLE_NAMES)})")
    p.add_argument("--force", action="store_true", help="replace existing password files")
    p.add_argument("--owner", metavar="UID[:GID]",
                   help="give the files to this user (the containers' user, e.g. 10001; needs root)")
    p.set_defaults(func=_cmd_secrets)

    r = serve_targets(subparsers).add_parser(
        "router", help="zenoh router (python zenoh, router mode)",
        description="Run a Zenoh router; listens on router.listen (default tcp/0.0.0.0:7447; "
        "--listen sets it).",
    )
    add_config_arguments(r)
    r.set_defaults(func=_cmd_router)


def main(argv: list[str] | None = None) -> int:
    """Run a bus sub-command directly (``python -m services.bus.cli record ...``)."""
    from services.cli import module_main

    return module_main(register, "python -m services.bus.cli", argv)

if __name__ == "__main__":
    sys.exit(main())
