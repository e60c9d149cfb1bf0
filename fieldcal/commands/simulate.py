"""`fieldcal simulate`: render a through-focus stack from a simulated lens. Not implemented yet (issue 2)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "simulate", "render a through-focus stack from a simulated lens [not implemented yet]", "fieldcal simulate models/triplet-uncorrected.json out --z -200 200 25")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal simulate` is not implemented yet (tracked in issue 2)",
                            fix="use the stages that exist; see README.md")
