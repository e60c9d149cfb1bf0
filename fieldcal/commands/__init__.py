"""One module per CLI subcommand: ``register(subparsers)`` + ``run(args) -> int``."""

import argparse


def add_parser(sub, name: str, help: str, example: str, description: str | None = None) -> argparse.ArgumentParser:
    """Every subcommand's --help ends with an example."""
    return sub.add_parser(name, help=help, description=description or help,
                          formatter_class=argparse.RawDescriptionHelpFormatter,
                          epilog=f"example:\n  {example}")
