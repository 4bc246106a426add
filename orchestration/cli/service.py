"""The service command: `serve` (the HTTP API and web page on Ray Serve, `rllock.orchestration.service`)."""

from __future__ import annotations

import argparse

from rllock.orchestration.cli.common import ray_on_loopback_unless
from rllock.orchestration.cli.flags import add_flags, from_flags


def cmd_serve(args: argparse.Namespace) -> int:
    from rllock.config import ServeConfig

    config = from_flags(ServeConfig, args)
    config.validate()
    ray_on_loopback_unless(config.address)
    from rllock.orchestration.service.app import serve_forever

    return serve_forever(config)


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    from rllock.config import ServeConfig

    p = subparsers.add_parser(
        "serve", help="the HTTP API and web page: jobs that solve or generate, on Ray Serve (127.0.0.1:8000)"
    )
    add_flags(p, ServeConfig)
    p.set_defaults(func=cmd_serve)
