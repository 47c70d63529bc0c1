"""`semmap config show`: the effective configuration (defaults, `--config` file, `--set` overrides), validated,
as commented YAML that `--config` takes back."""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "config",
        help="print the effective configuration (validated) as commented YAML",
        description="Every setting with its value and what it does. Exit code 2 (and every bad "
        "key named) when the file or an override does not validate.",
    )
    commands = p.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    show = commands.add_parser("show", help="print the configuration `semmap run` would use with these options")
    show.add_argument("--config", default=None, help="YAML config file (any subset of the layout printed)")
    show.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one setting; repeatable",
    )
    show.set_defaults(func=_show)


def _show(args: argparse.Namespace) -> int:
    from semmap.cli.run import check_plugins
    from semmap.core.config import ConfigError, load_config, render_yaml

    try:
        config = load_config(args.config, args.overrides)
        check_plugins(config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    sys.stdout.write(render_yaml(config))
    return 0
