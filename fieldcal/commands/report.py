"""`fieldcal report`: plots and an HTML page for a lens profile. Not implemented yet (issue 3)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "report", "plots and an HTML page for a lens profile [not implemented yet]", "fieldcal report lens.json --out report")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal report` is not implemented yet (tracked in issue 3)",
                            fix="use the stages that exist; see README.md")
