"""`datagen`: build, inspect and validate II-DSU shards from SUMO traffic.

datagen towns                                  list the built-in towns
datagen build --towns 8 --frames 146000        generate the dataset into data/
datagen validate data/                         check every shard
datagen inspect data/ --frame 10 --out f.png   draw one frame (paper Fig. 5)
"""

from __future__ import annotations

import argparse
import importlib
import sys

from datagen.errors import UserError

# subcommand -> module exposing HELP, add_arguments(parser) and run(args) -> exit status.
COMMANDS = {
    "towns": "datagen.world.towns",
    "build": "datagen.dataset.build",
    "validate": "datagen.dataset.validate",
    "inspect": "datagen.dataset.inspect",
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="datagen", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    modules = {}
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        modules[name] = module
    args = parser.parse_args(argv)
    try:
        return int(modules[args.command].run(args) or 0)
    except UserError as e:
        print(f"datagen {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"datagen {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
