"""`fieldcal targets`: write printable calibration charts. Not implemented yet (issue 2)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "targets", "write printable calibration charts [not implemented yet]", "fieldcal targets --out calibration_targets")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal targets` is not implemented yet (tracked in issue 2)",
                            fix="use the stages that exist; see README.md")
