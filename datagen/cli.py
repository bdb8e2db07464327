"""`datagen`: build, inspect and validate II-DSU shards from SUMO traffic.

datagen towns                                  list the built-in towns
datagen build --towns 8 --frames 146000        generate the dataset into data/
datagen validate data/                         check every shard
datagen inspect data/ --frame 10 --out f.png   draw one frame (paper Fig. 5)
"""

from __future__ import annotations

import importlib
import sys

from schemas import cli

# subcommand -> module exposing HELP, add_arguments(parser) and run(args) -> exit status.
COMMANDS = {
    "towns": "datagen.world.towns",
    "build": "datagen.dataset.build",
    "validate": "datagen.dataset.validate",
    "inspect": "datagen.dataset.inspect",
}
RESUMABLE = {"build"}  # a stopped build resumes when the same command runs again


def _resume_hint(args) -> str:
    from datagen.dataset.build import RESUME

    return RESUME


def commands() -> list[cli.Command]:
    result = []
    for name, module_name in COMMANDS.items():
        m = importlib.import_module(module_name)
        resume = _resume_hint if name in RESUMABLE else None
        result.append(cli.Command(name, m.HELP, m.add_arguments, m.run, resume))
    return result


def main(argv: list[str] | None = None) -> int:
    return cli.main("datagen", __doc__, commands(), argv)


if __name__ == "__main__":
    sys.exit(main())
