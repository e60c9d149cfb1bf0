"""`fieldcal calibrate`: fit a lens profile from a chart stack. Not implemented yet (issue 3)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "calibrate", "fit a lens profile from a chart stack [not implemented yet]", "fieldcal calibrate STACK --out lens.json")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal calibrate` is not implemented yet (tracked in issue 3)",
                            fix="use the stages that exist; see README.md")
